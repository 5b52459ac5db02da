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

Usage: python scripts/psychometric_recovery.py [--experiments 300] [--boot 1000]
[--plot PATH] (the plot goes to the temp directory unless --plot says where).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import stats

from hapticd import psychophysics as pp

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
    t0 = time.perf_counter()
    for i in range(n_exp):
        k = rng.binomial(REPS, p)
        fit = pp.fit_psychometric(LEVELS, k, REPS, n_boot=n_boot, seed=seed * 100_000 + i)
        if not fit.estimable:
            continue
        pse.append(fit.pse)
        jnd.append(fit.jnd)
        lo, hi = fit.jnd_ci
        cover.append(lo <= true_jnd <= hi)
        cover_pse.append(fit.pse_ci[0] <= mu <= fit.pse_ci[1])
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
        "s_per_fit": (time.perf_counter() - t0) / n_exp,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--experiments", type=int, default=300, help="series per observer")
    ap.add_argument("--boot", type=int, default=1000, help="bootstrap refits per fit")
    ap.add_argument("--plot", type=Path, help="where the plot goes (default: temp dir)")
    args = ap.parse_args()
    rows = [study(*obs, args.experiments, args.boot, seed=j + 1) for j, obs in enumerate(OBSERVERS)]
    head = (
        f"{'observer':<32} {'estim.':>6} {'PSE bias':>14} {'JND med':>8} {'JND mean':>8} "
        f"{'cov JND':>8} {'cov PSE':>8} {'width':>6} {'s/fit':>6}"
    )
    print(f"{args.experiments} series per observer, {args.boot} bootstrap refits per fit")
    print("(JND med/mean: relative to the true JND; width: median JND interval / true JND)")
    print(head)
    for r in rows:
        print(
            f"{r['observer']:<32} {r['estimable']:>6.2f} "
            f"{r['pse_bias']:>+7.2f} +- {r['pse_bias_se']:.2f} {r['jnd_median']:>8.3f} "
            f"{r['jnd_mean']:>8.3f} {r['coverage_jnd']:>8.3f} {r['coverage_pse']:>8.3f} "
            f"{r['width']:>6.2f} {r['s_per_fit']:>6.3f}"
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


if __name__ == "__main__":
    main()
