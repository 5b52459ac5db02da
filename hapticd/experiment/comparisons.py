"""Comparisons between conditions shared by every procedure's analysis: the session's
rows, paired t-tests of Weber fractions, and their report lines. Pure."""

from __future__ import annotations

import itertools
from typing import Any

from hapticd.psychophysics import paired_t


def session_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The store rows of the session's own trials: practice trials (``practice`` true)
    are never analysed."""
    return [r for r in rows if not r.get("practice")]


def paired_tests(
    weber: dict[tuple[str, str, float], float | None],
    order: list[str],
    standards: list[float],
    subjects: list[str],
) -> list[dict[str, Any]]:
    """Per standard and pair of conditions [a, b] (in ``order``), the paired t-test of
    Weber(a) - Weber(b) over the subjects with both ({(subject, condition, standard):
    Weber or None}); ``reason`` where it is undefined."""
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
    return tests


def _test_lines(tests: list[dict[str, Any]], what: str) -> list[str]:
    """The paired t-tests of ``what``, a line per standard and pair of conditions."""
    lines = [f"paired t-tests of {what} across subjects:"]
    for t in tests:
        a, b = t["conditions"]
        res = t["reason"] if t["t"] is None else f"t({t['df']}) = {t['t']:.3f}, p = {t['p']:.4f}"
        lines.append(f"  standard {t['standard']:<8.4g} {a} vs {b}: {res}")
    return lines
