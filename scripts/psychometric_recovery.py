#!/usr/bin/env python3
"""How well hapticd.psychophysics.fit_psychometric recovers known observers in the seed's
design (a simulation study, not a timing benchmark).

For each simulated observer (true PSE, sigma, lapse) and ``--experiments`` simulated
series of the seed's design (standard 60, comparisons 0.7-1.3 x the standard without
1.0, 10 presentations each: 60 trials), fit the psychometric function with the
default bootstrap and count: how many series are estimable, the PSE's bias, the
JND's median and mean relative to the truth, how often the 95 % BCa intervals of
the JND and of the PSE cover the truth, and the median width of the JND interval
relative to the true JND. Prints a table and saves a plot of the coverage per
observer.

Then three checks of the fit itself:

- near-flat observers (sigma 40 and 80 at standard 60): how many series are
  estimable, and how many of those report an unbounded upper JND end (never the
  search bound as a number);
- the global optimum: ``--series`` generated series (observers from sharp to flat,
  with and without lapse) fitted, and each estimable fit's log-likelihood compared
  with an independent global search (scipy's differential evolution, polished):
  the largest shortfall, and how many fall short by more than 1e-4;
- with ``--psignifit N``: N series fitted by psignifit 4 too (no lapse, so both fit
  the same model): the differences in PSE (in sigmas) and JND (relative), split by
  whether psignifit's width is within the level range (its priors flat) or not.

Usage: python scripts/psychometric_recovery.py [--experiments 300] [--boot 1000]
[--series 400] [--psignifit 40] [--plot PATH] (the plot goes to the temp directory
unless --plot says where).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import optimize, stats

from hapticd import psychophysics as pp
from hapticd.experiment.fitters import fit_psignifit

STANDARD = 60.0
LEVELS = STANDARD * np.array([0.7, 0.8, 0.9, 1.1, 1.2, 1.3])
REPS = np.full(6, 10)
# (PSE, sigma, lapse): the notes' sigma 9 (Weber 0.10), sharper and blunter observers.
OBSERVERS = [
    (60.0, 9.0, 0.0),
    (62.0, 9.0, 0.02),
    (60.0, 6.0, 0.0),
    (63.0, 15.0, 0.03),
    (58.0, 12.0, 0.05),
]


def study(mu: float, sigma: float, lapse: float, n_exp: int, n_boot: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    p = lapse / 2 + (1 - lapse) * stats.norm.cdf((LEVELS - mu) / sigma)
    true_jnd = pp.Z75 * sigma
    pse, jnd, cover, cover_pse, width = [], [], [], [], []
    open_ends = 0
    t0 = time.perf_counter()
    for i in range(n_exp):
        k = rng.binomial(REPS, p)
        fit = pp.fit_psychometric(LEVELS, k, REPS, n_boot=n_boot, seed=seed * 100_000 + i)
        if not fit.estimable:
            continue
        pse.append(fit.pse)
        jnd.append(fit.jnd)
        # An unbounded end (None) reaches 0 below, infinity above.
        lo, hi = (0.0 if v is None else v for v in fit.jnd_ci)
        hi = np.inf if fit.jnd_ci[1] is None else hi
        open_ends += (fit.jnd_ci[0] is None) + (fit.jnd_ci[1] is None)
        cover.append(lo <= true_jnd <= hi)
        plo, phi = fit.pse_ci
        cover_pse.append((plo is None or plo <= mu) and (phi is None or mu <= phi))
        width.append((hi - lo) / true_jnd)
    return {
        "observer": f"PSE {mu:g}, sigma {sigma:g}, lapse {lapse:g}",
        "estimable": len(pse) / n_exp,
        "pse_bias": float(np.mean(pse) - mu),
        "pse_bias_se": float(np.std(pse, ddof=1) / np.sqrt(len(pse))),
        "jnd_median": float(np.median(jnd) / true_jnd),
        "jnd_mean": float(np.mean(jnd) / true_jnd),
        "coverage_jnd": float(np.mean(cover)),
        "coverage_pse": float(np.mean(cover_pse)),
        "width": float(np.median(width)),
        "open_ends": open_ends,
        "s_per_fit": (time.perf_counter() - t0) / n_exp,
    }


# Near-flat observers: the curve barely rises over the levels.
FLAT = [(60.0, 40.0, 0.02), (60.0, 80.0, 0.02)]


def flat_study(mu: float, sigma: float, lapse: float, n_exp: int, n_boot: int, seed: int) -> dict:
    """Near-flat series: estimable share, and the estimable fits' upper JND ends."""
    rng = np.random.default_rng(seed)
    p = lapse / 2 + (1 - lapse) * stats.norm.cdf((LEVELS - mu) / sigma)
    bound = pp._SIGMA_HI * (LEVELS[-1] - LEVELS[0]) * pp.Z75
    fits = [
        pp.fit_psychometric(LEVELS, rng.binomial(REPS, p), REPS, n_boot=n_boot, seed=i)
        for i in range(n_exp)
    ]
    est = [f for f in fits if f.estimable]
    return {
        "observer": f"PSE {mu:g}, sigma {sigma:g}, lapse {lapse:g}",
        "estimable": len(est),
        "n": n_exp,
        "unbounded": sum(f.jnd_ci[1] is None for f in est),
        "at_bound": sum(f.jnd_ci[1] is not None and f.jnd_ci[1] >= 0.999 * bound for f in est),
    }


def reference_optimum(z: np.ndarray, k: np.ndarray, n: np.ndarray, seed: int) -> float:
    """An independent global maximum of the log-likelihood: differential evolution
    over the same bounds, polished by L-BFGS-B."""
    bounds = pp._bounds(0.06)
    res = optimize.differential_evolution(
        lambda th: pp._nll_and_grad(th, z, k, n)[0],
        bounds,
        seed=seed,
        tol=1e-10,
        popsize=30,
        polish=True,
    )
    return -float(res.fun)


def global_study(n_series: int, seed: int) -> dict:
    """Our fit's log-likelihood against the reference optimum on generated series."""
    rng = np.random.default_rng(seed)
    z = (LEVELS - STANDARD) / (LEVELS[-1] - LEVELS[0])
    gaps, reasons = [], {}
    for i in range(n_series):
        sigma = [3.0, 6.0, 9.0, 15.0, 40.0][i % 5]
        lapse = [0.0, 0.05][i % 2]
        mu = STANDARD + rng.normal(0, 3)
        k = rng.binomial(REPS, lapse / 2 + (1 - lapse) * stats.norm.cdf((LEVELS - mu) / sigma))
        fit = pp.fit_psychometric(LEVELS, k, REPS, n_boot=0)
        if not fit.estimable:
            why = next(
                w for w in ("switch", "steeper", "flat", "beyond", "every", "") if w in fit.reason
            )
            reasons[why] = reasons.get(why, 0) + 1
            continue
        ref = reference_optimum(z, k.astype(float), REPS.astype(float), seed=i)
        gaps.append(ref - fit.log_likelihood)
    gaps_a = np.array(gaps)
    return {
        "series": n_series,
        "estimable": len(gaps),
        "worst_gap": float(gaps_a.max()),
        "over_1e-4": int(np.sum(gaps_a > 1e-4)),
        "reasons": reasons,
    }


def psignifit_study(n_series: int, seed: int) -> list[dict]:
    """Our fit and psignifit's (no lapse) on the same series: the differences."""
    rng = np.random.default_rng(seed)
    span = LEVELS[-1] - LEVELS[0]
    rows = []
    for i in range(n_series):
        sigma = [4.0, 6.0, 9.0, 15.0][i % 4]
        k = rng.binomial(REPS, stats.norm.cdf((LEVELS - STANDARD - rng.normal(0, 2)) / sigma))
        ours = pp.fit_psychometric(LEVELS, k, REPS, n_boot=0, lapse_max=0.0)
        theirs = fit_psignifit(LEVELS, k, REPS, lapse_max=0.0)
        rows.append(
            {
                "both": ours.estimable and theirs.estimable,
                "agree_estimable": ours.estimable == theirs.estimable,
                "flat_prior": theirs.estimable and 3.29 * theirs.sigma <= span,
                "pse": abs(theirs.pse - ours.pse) / ours.sigma if ours.estimable else None,
                "jnd": abs(theirs.jnd / ours.jnd - 1) if ours.estimable else None,
            }
        )
    return rows


def print_checks(args: argparse.Namespace) -> None:
    print("\nnear-flat observers (upper JND end: unbounded, or the search bound as a number):")
    for j, obs in enumerate(FLAT):
        r = flat_study(*obs, args.experiments, args.boot, seed=100 + j)
        print(
            f"  {r['observer']:<32} estimable {r['estimable']}/{r['n']}, upper end unbounded "
            f"{r['unbounded']}, at the bound {r['at_bound']}"
        )
    g = global_study(args.series, seed=25)
    print(
        f"\nglobal optimum: {g['series']} series, {g['estimable']} estimable; largest "
        f"shortfall from differential evolution {g['worst_gap']:.2e}, more than 1e-4 in "
        f"{g['over_1e-4']}; not estimable: {g['reasons']}"
    )
    if args.psignifit:
        rows = psignifit_study(args.psignifit, seed=7)
        print(f"\npsignifit 4 (no lapse), {len(rows)} series:")
        print(f"  estimable alike: {sum(r['agree_estimable'] for r in rows)}/{len(rows)}")
        for flat, what in ((True, "width within the level range"), (False, "wider")):
            sel = [r for r in rows if r["both"] and r["flat_prior"] == flat]
            if sel:
                pse = np.array([r["pse"] for r in sel])
                jnd = np.array([r["jnd"] for r in sel])
                print(
                    f"  {what:<30} n {len(sel):>3}: |PSE diff|/sigma median {np.median(pse):.1e} "
                    f"max {pse.max():.1e}; |JND ratio - 1| median {np.median(jnd):.1e} "
                    f"max {jnd.max():.1e}"
                )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--experiments", type=int, default=300, help="series per observer")
    ap.add_argument("--boot", type=int, default=1000, help="bootstrap refits per fit")
    ap.add_argument("--plot", type=Path, help="where the plot goes (default: temp dir)")
    ap.add_argument("--series", type=int, default=400, help="series for the global check")
    ap.add_argument("--psignifit", type=int, default=0, help="series fitted by psignifit too")
    ap.add_argument("--checks-only", action="store_true", help="skip the recovery table")
    ap.add_argument("--table-only", action="store_true", help="skip the checks")
    args = ap.parse_args()
    if args.checks_only:
        print_checks(args)
        return
    rows = [study(*obs, args.experiments, args.boot, seed=j + 1) for j, obs in enumerate(OBSERVERS)]
    head = (
        f"{'observer':<32} {'estim.':>6} {'PSE bias':>14} {'JND med':>8} {'JND mean':>8} "
        f"{'cov JND':>8} {'cov PSE':>8} {'width':>6} {'open':>5} {'s/fit':>6}"
    )
    print(f"{args.experiments} series per observer, {args.boot} bootstrap refits per fit")
    print(
        "(JND med/mean: relative to the true JND; width: median JND interval / true JND; "
        "open: unbounded JND interval ends)"
    )
    print(head)
    for r in rows:
        print(
            f"{r['observer']:<32} {r['estimable']:>6.2f} "
            f"{r['pse_bias']:>+7.2f} +- {r['pse_bias_se']:.2f} {r['jnd_median']:>8.3f} "
            f"{r['jnd_mean']:>8.3f} {r['coverage_jnd']:>8.3f} {r['coverage_pse']:>8.3f} "
            f"{r['width']:>6.2f} {r['open_ends']:>5} {r['s_per_fit']:>6.3f}"
        )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["coverage_jnd"] for r in rows], 0.4, label="JND interval")
    ax.bar(x + 0.2, [r["coverage_pse"] for r in rows], 0.4, label="PSE interval")
    ax.axhline(0.95, color="k", lw=0.8, ls="--")
    ax.set_xticks(x, [r["observer"].replace(", ", "\n") for r in rows], fontsize=7)
    ax.set_ylim(0.5, 1.0)
    ax.set_ylabel("coverage of the truth")
    ax.legend(loc="lower right")
    fig.tight_layout()
    out = args.plot or Path(tempfile.gettempdir()) / "psychometric-recovery.png"
    fig.savefig(out, dpi=100)
    print(f"plot: {out}")
    if not args.table_only:
        print_checks(args)


if __name__ == "__main__":
    main()
