"""``hapticd experiment analyze``: psychometric fits per subject, condition and standard,
group means, paired t-tests between conditions, JSON and plots."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from hapticd.experiment.comparisons import _test_lines, paired_tests, session_rows
from hapticd.experiment.fitters import FITTERS
from hapticd.psychophysics import jnd_z


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
    for row in session_rows(trials):
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
    tests = paired_tests(weber, order, standards, subjects)
    return {
        "jnd_point": jnd_point,
        "fitter": fitter,
        "fits": fits,
        "groups": groups,
        "tests": tests,
        "_curves": curves,
    }


def failed_trials(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The trials whose exploration failed (store rows of status failed), left out of
    every fit: how many, and how many per cause (``failure``'s kind: the text before its
    first colon after the interval, e.g. "the cube slipped or dropped") and per
    condition and standard."""
    causes: dict[str, int] = defaultdict(int)
    cells: dict[str, int] = defaultdict(int)
    rows = session_rows(rows)
    for r in rows:
        for part in str(r.get("failure") or "unknown").split("; "):
            causes[
                part.split(": ")[1] if part.startswith("interval ") else part.split(": ")[0]
            ] += 1
        cells[f"{r['condition']} {float(r['standard']):g}"] += 1
    return {
        "n": len(rows),
        "causes": dict(sorted(causes.items())),
        "cells": dict(sorted(cells.items())),
    }


def format_failed(failed: dict[str, Any]) -> str:
    """The failed trials as the report's lines."""
    causes = ", ".join(f"{c} ({n} intervals)" for c, n in failed["causes"].items())
    cells = ", ".join(f"{c}: {n}" for c, n in failed["cells"].items())
    return (
        f"{failed['n']} trial(s) whose exploration failed are left out (never judged): "
        f"{causes}; by condition and standard: {cells}\n"
    )


def analyze_staircases(
    trials: list[dict[str, Any]], staircase: dict[str, Any], conditions: list[str] | None = None
) -> dict[str, Any]:
    """A staircase store's tracks and thresholds from the last reversals: ``tracks`` (per
    subject and track: its reversals, threshold distance (fraction of the standard) and
    comparison), ``thresholds`` (per subject, condition and standard: the JND at the
    rule's target share, the mean of its sides' threshold distances times the standard,
    and its Weber fraction) and ``tests`` (paired t of those Weber fractions between
    conditions). ``staircase``: the design's staircase section."""
    from hapticd.experiment.adaptive import tracks_from_rows
    from hapticd.experiment.spec import Staircase

    st = Staircase.model_validate(staircase)
    tracks = tracks_from_rows(session_rows(trials), st)
    rows = []
    for (subject, _), t in tracks.items():
        d = t.threshold(st)
        rows.append(
            {
                "subject": subject,
                "condition": t.condition,
                "standard": t.standard,
                "side": t.side,
                "trials": t.n,
                "reversals": len(t.reversals),
                "done": t.done(st),
                "threshold_distance": d,
                "threshold": None if d is None else t.standard * (1 + t.sign * d),
                "_track": t,
            }
        )
    cells: dict[tuple[str, str, float], list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        cells[(r["subject"], r["condition"], r["standard"])].append(r)
    thresholds, weber = [], {}
    for key in sorted(cells):
        ds = [r["threshold_distance"] for r in cells[key]]
        ok = all(d is not None for d in ds)
        w = float(np.mean(ds)) if ok else None
        weber[key] = w
        thresholds.append(
            {
                "subject": key[0],
                "condition": key[1],
                "standard": key[2],
                "target": st.target_share,
                "jnd": None if w is None else w * key[2],
                "weber": w,
                "reason": None
                if ok
                else f"a track has fewer than {st.threshold_reversals} reversals",
            }
        )
    present = sorted({k[1] for k in cells})
    order = [c for c in conditions or [] if c in present] + [
        c for c in present if c not in (conditions or [])
    ]
    return {
        "target": st.target_share,
        "rule": st.rule,
        "n_up": st.moves[0],
        "n_down": st.moves[1],
        "tracks": rows,
        "thresholds": thresholds,
        "tests": paired_tests(
            weber, order, sorted({k[2] for k in cells}), sorted({k[0] for k in cells})
        ),
    }


def analyze_quest(
    trials: list[dict[str, Any]],
    quest: dict[str, Any],
    jnd_point: float = 0.75,
    conditions: list[str] | None = None,
) -> dict[str, Any]:
    """A QUEST+ store's tracks: per subject, condition and standard the posterior mean
    PSE and sigma after all its trials, the JND (x(jnd_point) - x(0.5)) and Weber
    fraction, and paired t-tests of those between conditions."""
    from hapticd.experiment.adaptive import QuestTrack
    from hapticd.experiment.spec import QuestPlusDesign

    q = QuestPlusDesign.model_validate(quest)
    by: dict[tuple[str, int], list[dict[str, Any]]] = defaultdict(list)
    for r in session_rows(trials):
        if r.get("block") is not None:
            by[(r["subject"], int(r["block"]))].append(r)
    rows, weber = [], {}
    z = jnd_z(jnd_point)
    for (subject, block), rs in sorted(by.items()):
        rs.sort(key=lambda r: r["plan_index"])
        track = QuestTrack(block, rs[0]["condition"], float(rs[0]["standard"]), q)
        for r in rs:
            track.answer(bool(r["comparison_more"]), q, r["comparison"])
        est = track.estimate()
        jnd = z * est["sigma"]
        weber[(subject, track.condition, track.standard)] = jnd / track.standard
        rows.append(
            {
                "subject": subject,
                "condition": track.condition,
                "standard": track.standard,
                "trials": track.n,
                "pse": est["pse"],
                "sigma": est["sigma"],
                "jnd": jnd,
                "weber": jnd / track.standard,
            }
        )
    present = sorted({r["condition"] for r in rows})
    order = [c for c in conditions or [] if c in present]
    order += [c for c in present if c not in order]
    return {
        "jnd_point": jnd_point,
        "tracks": rows,
        "tests": paired_tests(
            weber,
            order,
            sorted({r["standard"] for r in rows}),
            sorted({r["subject"] for r in rows}),
        ),
    }


def format_quest(result: dict[str, Any], unit: str) -> str:
    """The QUEST+ section of the report."""
    lines = [
        f"QUEST+ tracks (posterior means; {jnd_label(result['jnd_point'])}; standards in {unit}):"
    ]
    for r in result["tracks"]:
        lines.append(
            f"  {r['subject']:<10} {r['condition']:<10} standard {r['standard']:<8.4g} "
            f"{r['trials']:>3} trials PSE {r['pse']:.4g} JND {r['jnd']:.4g} "
            f"Weber {r['weber']:.3f}"
        )
    lines += _test_lines(
        result["tests"], f"the QUEST+ Weber fractions ({jnd_label(result['jnd_point'])})"
    )
    return "\n".join(lines) + "\n"


def format_staircases(result: dict[str, Any], unit: str) -> str:
    """The staircase section of the report."""
    rule = result["rule"]
    if rule == "updown":
        rule = f"updown, {result.get('n_up', 1)} up {result.get('n_down')} down"
    lines = [
        f"staircase tracks ({rule}, converging on {result['target']:.1%} correct; "
        "threshold: mean of the last reversals):"
    ]
    for r in result["tracks"]:
        thr = "n/a" if r["threshold"] is None else f"{r['threshold']:.4g} {unit}"
        lines.append(
            f"  {r['subject']:<10} {r['condition']:<10} standard {r['standard']:<8.4g} "
            f"{r['side']:<6} {r['trials']:>3} trials {r['reversals']:>3} reversals "
            f"threshold {thr}{'' if r['done'] else ' (not finished)'}"
        )
    lines.append(
        f"thresholds from the reversals (JND at {result['target']:.1%} = the sides' mean "
        "distance from the standard; Weber = JND / standard):"
    )
    for t in result["thresholds"]:
        what = t["reason"] if t["jnd"] is None else f"JND {t['jnd']:.4g}, Weber {t['weber']:.3f}"
        lines.append(f"  {t['subject']:<10} {t['condition']:<10} {t['standard']:<8.4g} {what}")
    lines += _test_lines(
        result["tests"], f"the reversal Weber fractions (JND at {result['target']:.1%} correct)"
    )
    return "\n".join(lines) + "\n"


def plot_staircases(result: dict[str, Any], out_dir: Path, *, param: str, unit: str) -> list[Path]:
    """Every track, one figure per subject (``staircase-SUBJECT.png``): a panel per
    condition and standard, the comparison of each trial (filled: correct, open: wrong),
    the reversals ringed, each side's threshold dashed. Needs matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for subj in sorted({r["subject"] for r in result["tracks"]}):
        mine = [r for r in result["tracks"] if r["subject"] == subj]
        panels = sorted({(r["condition"], r["standard"]) for r in mine})
        fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.4), squeeze=False)
        for ax, (cond, s) in zip(axes[0], panels, strict=True):
            for j, r in enumerate(x for x in mine if (x["condition"], x["standard"]) == (cond, s)):
                t = r["_track"]
                y = s * (1 + t.sign * np.array(t.levels))
                n = np.arange(1, len(y) + 1)
                ok = np.array(t.correct, dtype=bool)
                color = f"C{j}"
                ax.plot(n, y, "-", color=color, lw=0.8, label=r["side"])
                ax.plot(n[ok], y[ok], "o", color=color, ms=4)
                ax.plot(n[~ok], y[~ok], "o", mfc="none", color=color, ms=4)
                rev = s * (1 + t.sign * np.array(t.reversals))
                ax.plot(t.reversal_trials, rev, "o", mfc="none", mec="k", ms=8)
                if r["threshold"] is not None:
                    ax.axhline(r["threshold"], color=color, ls="--", lw=0.8)
            ax.axhline(s, color="0.6", lw=0.8)
            ax.set_title(f"{cond}, standard {s:g} {unit}", fontsize=9)
            ax.set_xlabel("trial of the track")
            ax.legend(fontsize=7)
        axes[0][0].set_ylabel(f"comparison {param} ({unit})")
        fig.suptitle(
            f"subject {subj}: staircases (filled: correct, open: wrong, ringed: reversals, "
            f"dashed: threshold at {result['target']:.1%})",
            fontsize=8,
        )
        written.append(_save(fig, out_dir / f"staircase-{subj}.png"))
    return written


def _save(fig: Any, path: Path) -> Path:
    """Lay out, write and close a figure; its path."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


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
    lines += _test_lines(result["tests"], f"the Weber fractions ({jnd_label(point)})")
    return "\n".join(lines) + "\n"


def to_json(result: dict[str, Any]) -> dict[str, Any]:
    """The result without its private parts (keys starting with _, at any depth)."""
    if isinstance(result, dict):
        return {k: to_json(v) for k, v in result.items() if not str(k).startswith("_")}
    if isinstance(result, list):
        return [to_json(v) for v in result]  # type: ignore[return-value]
    return result


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
        written.append(_save(fig, out_dir / f"psychometric-{subj}.png"))
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
    written.append(_save(fig, out_dir / "jnd-ratio.png"))
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
