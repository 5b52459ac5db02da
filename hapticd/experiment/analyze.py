"""``hapticd experiment analyze``: psychometric fits per subject, condition and standard,
group means, paired t-tests between conditions, JSON and plots."""

from __future__ import annotations

import itertools
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from hapticd.psychophysics import FITTERS, paired_t


def _key(row: dict[str, Any]) -> tuple[str, str, float]:
    return (row["subject"], row["condition"], float(row["standard"]))


def analyze(
    trials: list[dict[str, Any]],
    *,
    conditions: list[str] | None = None,
    n_boot: int = 1000,
    seed: int = 0,
    jnd_point: float = 0.75,
    fitter: str = "ml",
) -> dict[str, Any]:
    """``fits`` (per subject, condition, standard), ``groups`` (per condition and
    standard: Weber mean, SD over subjects) and ``tests`` (per standard and pair of
    conditions: paired t over the subjects estimable in both) from complete trial rows
    (hapticd.experiment.store). JND = x(jnd_point) - x(0.5); Weber = JND / standard.
    ``fitter``: ``ml`` (hapticd.psychophysics.fit_psychometric) or ``psignifit``.
    Non-estimable fits carry a ``reason`` and null numbers; an interval end that is
    null is unbounded; JSON-ready (no NaN). ``conditions`` orders the groups
    and the tests (the experiment file's order; others after it, sorted); the test of
    conditions [a, b] is of Weber(a) - Weber(b)."""
    cells: dict[tuple[str, str, float], list[dict[str, Any]]] = defaultdict(list)
    for row in trials:
        cells[_key(row)].append(row)
    present = sorted({k[1] for k in cells})
    order = [c for c in conditions or [] if c in present]
    order += [c for c in present if c not in order]
    if fitter not in FITTERS:
        raise ValueError(f"unknown fitter {fitter!r}; fitters: {', '.join(FITTERS)}")
    fit_one = FITTERS[fitter]
    fits = []
    curves = {}
    for i, (subject, cond, standard) in enumerate(sorted(cells)):
        rows = cells[(subject, cond, standard)]
        x = np.array([r["comparison"] for r in rows], dtype=float)
        yes = np.array([r["comparison_more"] for r in rows], dtype=float)
        levels, inv = np.unique(x, return_inverse=True)
        n_yes = np.bincount(inv, yes, len(levels))
        n_tot = np.bincount(inv, minlength=len(levels)).astype(float)
        fit = fit_one(levels, n_yes, n_tot, n_boot=n_boot, seed=seed + i, jnd_point=jnd_point)
        curves[(subject, cond, standard)] = (fit, levels, n_yes, n_tot)
        fits.append(
            {
                "subject": subject,
                "condition": cond,
                "standard": standard,
                "estimable": fit.estimable,
                "reason": fit.reason,
                "pse": fit.pse,
                "jnd": fit.jnd,
                "weber": None if fit.jnd is None else fit.jnd / standard,
                "jnd_ci": None if fit.jnd_ci is None else list(fit.jnd_ci),
                "pse_ci": None if fit.pse_ci is None else list(fit.pse_ci),
                "sigma": fit.sigma,
                "lapse": fit.lapse,
                "n_trials": len(rows),
            }
        )
    weber = {(f["subject"], f["condition"], f["standard"]): f["weber"] for f in fits}
    standards = sorted({k[2] for k in cells})
    subjects = sorted({k[0] for k in cells})
    groups = []
    for cond in order:
        for s in standards:
            w = [
                weber[(subj, cond, s)]
                for subj in subjects
                if weber.get((subj, cond, s)) is not None
            ]
            groups.append(
                {
                    "condition": cond,
                    "standard": s,
                    "weber_mean": float(np.mean(w)) if w else None,
                    "weber_sd": float(np.std(w, ddof=1)) if len(w) > 1 else None,
                    "n_subjects": len(w),
                }
            )
    tests = []
    for s in standards:
        for a, b in itertools.combinations(order, 2):
            both = [
                subj
                for subj in subjects
                if weber.get((subj, a, s)) is not None and weber.get((subj, b, s)) is not None
            ]
            entry: dict[str, Any] = {"standard": s, "conditions": [a, b], "n_subjects": len(both)}
            try:
                r = paired_t([weber[(x, a, s)] for x in both], [weber[(x, b, s)] for x in both])
                entry.update(t=r.t, df=r.df, p=r.p, mean_diff=r.mean_diff, reason=None)
            except ValueError as exc:
                entry.update(t=None, df=None, p=None, mean_diff=None, reason=str(exc))
            tests.append(entry)
    return {
        "jnd_point": jnd_point,
        "fitter": fitter,
        "fits": fits,
        "groups": groups,
        "tests": tests,
        "_curves": curves,
    }


def jnd_label(jnd_point: float) -> str:
    """What the JND is, for tables and plots: ``JND = x(0.75) - x(0.5)``."""
    return f"JND = x({jnd_point:g}) - x(0.5)"


def ci_text(ci: list[float | None] | tuple[float | None, float | None] | None, floor: str) -> str:
    """An interval as text; an unbounded end (None) is ``floor`` below (``0`` for a JND,
    ``-inf`` for a PSE) or ``inf`` above, with an open bracket."""
    if not ci:
        return ""
    lo, hi = ci
    left = f"({floor}" if lo is None else f"[{lo:.4g}"
    right = "inf)" if hi is None else f"{hi:.4g}]"
    return f"{left}, {right}"


def format_report(result: dict[str, Any], unit: str) -> str:
    point = result.get("jnd_point", 0.75)
    lines = [
        f"fits (per subject, condition, standard; {jnd_label(point)}, fitter "
        f"{result.get('fitter', 'ml')}; an interval end 'inf' or '(0' is unbounded):"
    ]
    lines.append(
        f"  {'subject':<10} {'condition':<10} {'standard':>10} {'PSE':>10} {'JND':>10} "
        f"{'Weber':>7} {'JND 95% CI':>22} {'n':>4}"
    )
    for f in result["fits"]:
        if f["estimable"]:
            ci = ci_text(f["jnd_ci"], "0")
            nums = f"{f['pse']:>10.4g} {f['jnd']:>10.4g} {f['weber']:>7.3f} {ci:>22}"
        else:
            nums = f"not estimable: {f['reason']}"
        lines.append(
            f"  {f['subject']:<10} {f['condition']:<10} {f['standard']:>10.4g} {nums} "
            f"{f['n_trials'] if f['estimable'] else ''}"
        )
    lines.append(
        f"groups (Weber fraction = JND / standard, {jnd_label(point)}; standards in {unit}):"
    )
    for g in result["groups"]:
        mean = "n/a" if g["weber_mean"] is None else f"{g['weber_mean']:.3f}"
        sd = "n/a" if g["weber_sd"] is None else f"{g['weber_sd']:.3f}"
        lines.append(
            f"  {g['condition']:<10} standard {g['standard']:<8.4g} Weber {mean} "
            f"(SD {sd}, {g['n_subjects']} subjects)"
        )
    lines.append("paired t-tests of the Weber fractions across subjects:")
    for t in result["tests"]:
        a, b = t["conditions"]
        if t["t"] is None:
            lines.append(f"  standard {t['standard']:<8.4g} {a} vs {b}: {t['reason']}")
        else:
            lines.append(
                f"  standard {t['standard']:<8.4g} {a} vs {b}: t({t['df']}) = {t['t']:.3f}, "
                f"p = {t['p']:.4f}"
            )
    return "\n".join(lines) + "\n"


def to_json(result: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in result.items() if not k.startswith("_")}


def plot(result: dict[str, Any], out_dir: Path, *, param: str, unit: str) -> list[Path]:
    """Psychometric curves per subject (one file each) and the JND-ratio figure (the
    seed's Figs. 3 and 5: mean Weber fraction against the standard, one line per
    condition, error bars one SD across subjects). Needs matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    point = result.get("jnd_point", 0.75)
    written = []
    curves = result["_curves"]
    subjects = sorted({k[0] for k in curves})
    standards = sorted({k[2] for k in curves})
    conds = list(dict.fromkeys(g["condition"] for g in result["groups"]))
    for subj in subjects:
        fig, axes = plt.subplots(
            1, len(standards), figsize=(4 * len(standards), 3.4), squeeze=False
        )
        for ax, s in zip(axes[0], standards, strict=True):
            for j, c in enumerate(conds):
                if (subj, c, s) not in curves:
                    continue
                fit, x, k, n = curves[(subj, c, s)]
                color = f"C{j}"
                ax.plot(x, k / n, "o", color=color)
                label = c
                if fit.estimable:
                    xs = np.linspace(x[0], x[-1], 200)
                    ax.plot(xs, fit.predict(xs), "-", color=color)
                    label += f" (Weber {fit.jnd / s:.3f})"
                    _jnd_interval(ax, fit, _panel_x(curves, subj, s), color)
                else:
                    label += " (not estimable)"
                ax.plot([], [], "o-", color=color, label=label)
            ax.axvline(s, color="0.7", lw=0.8)
            ax.set_ylim(-0.03, 1.03)
            ax.set_xlim(*_panel_x(curves, subj, s))
            ax.set_title(f"standard {s:g} {unit}")
            ax.set_xlabel(f"comparison {param} ({unit})")
            ax.legend(fontsize=7, loc="upper left")
        axes[0][0].set_ylabel("P(comparison judged more)")
        fig.suptitle(
            f"subject {subj}\n{jnd_label(point)}; bar at P = {point:g}: PSE + the JND's "
            "interval (arrow: unbounded)",
            fontsize=8,
        )
        fig.tight_layout()
        path = out_dir / f"psychometric-{subj}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    fig, ax = plt.subplots(figsize=(5, 3.6))
    for j, c in enumerate(conds):
        gs = [g for g in result["groups"] if g["condition"] == c and g["weber_mean"] is not None]
        ax.errorbar(
            [g["standard"] for g in gs],
            [g["weber_mean"] for g in gs],
            yerr=[g["weber_sd"] or 0.0 for g in gs],
            fmt="o-" if j == 0 else "s--",
            capsize=4,
            label=c,
        )
    ax.set_xlabel(f"standard {param} ({unit})")
    ax.set_ylabel("JND ratio (JND / standard)")
    ax.set_ylim(bottom=0)
    ax.legend()
    ax.set_title(f"JND ratio, {jnd_label(point)}: mean and SD across subjects", fontsize=9)
    fig.tight_layout()
    path = out_dir / "jnd-ratio.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    written.append(path)
    return written


def _panel_x(curves: dict, subj: str, s: float) -> tuple[float, float]:
    """The x range of one subject's panel at standard ``s``: its levels and a margin."""
    xs = [v[1] for (subject, _, standard), v in curves.items() if (subject, standard) == (subj, s)]
    return min(x[0] for x in xs) - 0.1 * s, max(x[-1] for x in xs) + 0.1 * s


def _jnd_interval(ax: Any, fit: Any, xlim: tuple[float, float], color: str) -> None:
    """The JND's interval as a bar from PSE + its lower end to PSE + its upper end at the
    height of the JND point; an unbounded end runs to the panel's edge as an arrow."""
    if not fit.jnd_ci:
        return
    lo, hi = fit.jnd_ci
    y = fit.jnd_point
    x0 = fit.pse + (0.0 if lo is None else lo)
    x1 = xlim[1] if hi is None else fit.pse + hi
    style = "->" if hi is None else "|-|"
    ax.annotate(
        "",
        xy=(x1, y),
        xytext=(x0, y),
        arrowprops={"arrowstyle": style, "color": color, "lw": 1.5, "shrinkA": 0, "shrinkB": 0},
    )
    if hi is None:
        ax.text(x1, y + 0.03, "unbounded", color=color, fontsize=6, ha="right")
