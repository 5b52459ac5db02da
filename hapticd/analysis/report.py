"""What ``hapticd analyze`` prints, saves and plots (the command's arguments are in hapticd.cli).

Tables put the allocators side by side; matrices are labelled by finger and axis
(``thumb.x``). Nothing here reads files: the command line reads the profile and
the recording and hands over built objects and arrays.
"""

from __future__ import annotations

import math
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from hapticd.analysis.pipeline import Linearization, Pipeline, Sample

MATRIX_CELL = 9  # characters per matrix entry
GAP = "   "


def _num(v: float, digits: int = 4) -> str:
    """A compact number: 0 for tiny values, no trailing noise."""
    if not math.isfinite(v):
        return "n/a"
    if abs(v) < 5e-13:
        return "0"
    return f"{v:.{digits}g}"


def vector(v: np.ndarray, digits: int = 4) -> str:
    """(a, b, c) with compact numbers."""
    return "(" + ", ".join(_num(float(c), digits) for c in v) + ")"


def combination(v: np.ndarray, labels: Sequence[str]) -> str:
    """A unit vector as a sum of labelled axes, e.g. '0.7071 thumb.y + 0.7071 index.y'."""
    terms = []
    for c, name in zip(v.tolist(), labels, strict=True):
        if abs(c) < 1e-9:
            continue
        if abs(abs(c) - 1.0) < 1e-9:
            terms.append(("-" if c < 0 else "+", name))
        else:
            terms.append(("-" if c < 0 else "+", f"{abs(c):.4g} {name}"))
    if not terms:
        return "0"
    text = ("-" if terms[0][0] == "-" else "") + terms[0][1]
    for sign, t in terms[1:]:
        text += f" {sign} {t}"
    return text


def matrix_lines(K: np.ndarray, labels: Sequence[str], title: str) -> list[str]:
    """A labelled matrix as lines of equal width (entries in N/m, 3 decimals)."""
    lw = max(len(lab) for lab in labels) + 1
    width = lw + MATRIX_CELL * len(labels)
    lines = [title.ljust(width)[:width] if len(title) <= width else title]
    lines.append(" " * lw + "".join(f"{lab:>{MATRIX_CELL}}" for lab in labels))
    for lab, row in zip(labels, K, strict=True):
        cells = "".join(f"{(0.0 if abs(v) < 5e-13 else v):{MATRIX_CELL}.3f}" for v in row)
        lines.append(f"{lab:<{lw}}{cells}")
    return [ln.ljust(width) for ln in lines]


def side_by_side(blocks: list[list[str]], width: int) -> list[str]:
    """Blocks of equal-width lines next to each other, as many per row as ``width`` holds."""
    if not blocks:
        return []
    bw = max(len(ln) for b in blocks for ln in b)
    per_row = max(1, (width + len(GAP)) // (bw + len(GAP)))
    out: list[str] = []
    for i in range(0, len(blocks), per_row):
        row = blocks[i : i + per_row]
        height = max(len(b) for b in row)
        for k in range(height):
            out.append(GAP.join((b[k] if k < len(b) else "").ljust(bw) for b in row).rstrip())
        out.append("")
    return out


def terminal_width() -> int:
    """Columns to fill (COLUMNS, the terminal, else 130: two 6 x 6 matrices)."""
    return shutil.get_terminal_size((130, 24)).columns


def format_linearization(
    results: dict[str, Linearization],
    *,
    header: list[str],
    width: int | None = None,
) -> str:
    """The analysis at one configuration: indices per allocator side by side, then K_full,
    then every allocator's K_rendered, then the directions without rendered stiffness."""
    width = terminal_width() if width is None else width
    names = list(results)
    first = results[names[0]]
    labels = first.labels
    lines = list(header)
    fingers = [lab.rsplit(".", 1)[0] for lab in first.labels[::3]] if first.q is None else []
    if first.q is None:
        for i, name in enumerate(fingers):
            contact = "in contact" if first.in_contact[i] else "no contact"
            lines.append(
                f"  {name:<10} at {vector(first.x[i])} m, {contact}, full force "
                f"{vector(first.full_force[i])} N"
            )
    else:
        lines.append(
            "  q = " + ", ".join(f"{lab} {_num(v)}" for lab, v in zip(labels, first.q, strict=True))
        )
    what = "point contacts" if first.q is None else "generalized coordinates"
    lines.append(
        f"n = {first.n} ({what}), s = {first.s} (sensed: full sensing), "
        f"r = {first.r} (rank of the actuation)"
    )
    lines.append(
        f"central differences, step {first.fd_step:g} m; largest change against twice the "
        f"step: {max(r.fd_error for r in results.values()):.2g} N/m"
    )
    rough = [n for n, r in results.items() if not r.smooth]
    if rough:
        lines.append(
            f"WARNING: the force has a kink here for {', '.join(rough)} (the estimate with "
            "twice the step differs): those matrices are difference quotients across a jump"
        )
    lines.append("")
    col = max(10, *(len(n) + 2 for n in names))
    rows: list[tuple[str, list[str]]] = [
        ("asymmetry ||K-K^T||/2||K||", [f"{r.asymmetry:.4f}" for r in results.values()]),
        ("controllability k = s/n", [_num(r.controllability) for r in results.values()]),
        ("observability o = r/n", [_num(r.observability) for r in results.values()]),
        (
            "rank of K_rendered",
            [str(r.n - r.null_directions.shape[1]) for r in results.values()],
        ),
        (
            "directions without stiffness",
            [str(r.null_directions.shape[1]) for r in results.values()],
        ),
        ("work per loop area (J/m^2)", [_num(r.work_per_area) for r in results.values()]),
    ]
    if first.q is None:
        for i, name in enumerate(fingers):
            rows.append(
                (
                    f"rendered force {name} (N)",
                    [vector(r.rendered_force[i], 3) for r in results.values()],
                )
            )
    else:
        rows.append(("generalized force Q_full", [vector(r.Q_full, 4) for r in results.values()]))
        rows.append(
            ("generalized force Q_rendered", [vector(r.Q_rendered, 4) for r in results.values()])
        )
    lw = max(len(r[0]) for r in rows) + 2
    col = max(col, *(len(c) + 2 for _, cells in rows for c in cells))
    lines.append(" " * lw + "".join(f"{n:<{col}}" for n in names).rstrip())
    for label, cells in rows:
        lines.append(f"{label:<{lw}}" + "".join(f"{c:<{col}}" for c in cells).rstrip())
    lines.append("")
    unit = "N/m" if first.q is None else "per coordinate unit squared"
    lines += [
        ln.rstrip()
        for ln in matrix_lines(
            first.K_full, labels, f"K_full ({unit}), derivative of the full forces (the seed's F_L)"
        )
    ]
    lines.append("")
    lines.append(
        f"K_rendered ({unit}), derivative of the rendered forces (M_A F_L M_S), per allocator"
    )
    blocks = [matrix_lines(r.K_rendered, labels, name) for name, r in results.items()]
    lines += side_by_side(blocks, width)
    lines.append("no rendered stiffness along (null space of K_rendered, orthonormal):")
    for name, r in results.items():
        dirs = [combination(v, labels) for v in r.null_directions.T]
        lines.append(f"  {name:<{col}}" + ("; ".join(dirs) if dirs else "none"))
    return "\n".join(lines).rstrip() + "\n"


# -- along a recording ----------------------------------------------------------------------


class Progress:
    """A one-line progress bar on ``stream`` (stderr), drawn at most 10 times a second."""

    def __init__(self, what: str, stream: TextIO | None = None) -> None:
        self.what = what
        self.stream = stream if stream is not None else sys.stderr
        self._last = 0.0

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if done < total and now - self._last < 0.1:
            return
        self._last = now
        frac = done / total if total else 1.0
        bar = "#" * int(30 * frac)
        self.stream.write(f"\r{self.what} [{bar:<30}] {done}/{total}")
        if done >= total:
            self.stream.write("\n")
        self.stream.flush()


def format_samples(samples: list[Sample], times: np.ndarray, allocators: Sequence[str]) -> str:
    """A row per analysed tick with contact (asymmetry and work per loop area per
    allocator), the ticks skipped and why, and a summary per allocator."""
    names = list(allocators)
    col = max(9, *(len(n) + 2 for n in names))
    rows: list[tuple[Sample, str]] = []
    quiet = 0
    skipped = []
    for s in samples:
        if s.result is None:
            skipped.append(s)
            continue
        first = s.result[names[0]]
        if not first.in_contact.any():
            quiet += 1
            continue
        fingers = [lab.rsplit(".", 1)[0] for lab in first.labels[::3]]
        rows.append((s, "+".join(f for f, on in zip(fingers, first.in_contact, strict=True) if on)))
    cw = max([9, *(len(c) + 1 for _, c in rows)])
    head = f"{'tick':>7} {'t (s)':>8}  {'contact':<{cw}}"
    lines = [
        " " * len(head)
        + "  "
        + "asymmetry".ljust(col * len(names))
        + "  work per loop area (J/m^2)",
        head
        + "  "
        + "".join(f"{n:<{col}}" for n in names)
        + "  "
        + "".join(f"{n:<{col}}" for n in names).rstrip(),
    ]
    for s, contact in rows:
        assert s.result is not None
        mark = " " if all(r.smooth for r in s.result.values()) else "*"
        lines.append(
            (
                f"{s.tick:>7}{mark}{float(times[s.tick]):>8.3f}  {contact:<{cw}}  "
                + "".join(f"{s.result[n].asymmetry:<{col}.4f}" for n in names)
                + "  "
                + "".join(f"{_num(s.result[n].work_per_area):<{col}}" for n in names)
            ).rstrip()
        )
    kinked = [s for s, _ in rows if not all(r.smooth for r in s.result.values())]  # type: ignore[union-attr]
    if kinked:
        lines.append(
            f"* {len(kinked)} samples where the force has a kink (contact onset, a face edge): "
            "the finite differences straddle a jump; left out of the summary"
        )
    if quiet:
        lines.append(f"({quiet} samples without contact omitted: zero matrices, asymmetry 0)")
    for s in skipped:
        lines.append(f"tick {s.tick} skipped: {s.skipped}")
    touching = [s for s, _ in rows if s not in kinked]
    lines.append("")
    if not touching:
        lines.append("no sample is in contact with a smooth force: nothing to summarize")
        return "\n".join(lines) + "\n"
    lines.append(f"over the {len(touching)} samples in contact (smooth):")
    stats = [
        (
            "mean asymmetry",
            [f"{np.mean([s.result[n].asymmetry for s in touching]):.4f}" for n in names],
        ),
        (
            "largest asymmetry (tick)",
            [
                "{:.4f} ({})".format(*max((s.result[n].asymmetry, s.tick) for s in touching))
                for n in names
            ],
        ),
        (
            "largest work/area (J/m^2)",
            [_num(max(s.result[n].work_per_area for s in touching)) for n in names],
        ),
    ]
    lw = max(len(label) for label, _ in stats) + 2
    width = max(col, *(len(c) + 2 for _, cells in stats for c in cells))
    lines.append((" " * lw + "".join(f"{n:<{width}}" for n in names)).rstrip())
    for label, cells in stats:
        lines.append((f"{label:<{lw}}" + "".join(f"{c:<{width}}" for c in cells)).rstrip())
    return "\n".join(lines) + "\n"


def to_json(results: dict[str, Linearization]) -> dict[str, Any]:
    return {name: r.to_dict() for name, r in results.items()}


def samples_json(samples: list[Sample], times: np.ndarray) -> list[dict[str, Any]]:
    return [
        {
            "tick": s.tick,
            "t": float(times[s.tick]),
            "skipped": s.skipped,
            "results": None if s.result is None else to_json(s.result),
        }
        for s in samples
    ]


def plot(
    out: Path,
    allocators: Sequence[str],
    *,
    results: dict[str, Linearization] | None = None,
    samples: list[Sample] | None = None,
    times: np.ndarray | None = None,
    title: str = "",
) -> None:
    """Asymmetry and work per unit loop area per allocator: along a recording (lines over
    time) or at one configuration (bars). Needs matplotlib (imported only here)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=samples is not None)
    if samples is not None and times is not None:
        ok = [s for s in samples if s.result is not None]
        t = np.array([float(times[s.tick]) for s in ok])
        # Allocators often coincide (adaptive is IF while squeezing): each its own dash.
        styles = ["-", "--", "-.", ":"]
        for i, n in enumerate(allocators):
            ls = styles[i % len(styles)]
            lins = [s.result[n] for s in ok]  # type: ignore[index]
            # A kink (contact onset, an edge) leaves a gap: its quotient is no stiffness.
            asym = [lin.asymmetry if lin.smooth else np.nan for lin in lins]
            work = [lin.work_per_area if lin.smooth else np.nan for lin in lins]
            ax1.plot(t, asym, ls, label=n)
            ax2.plot(t, work, ls, label=n)
        ax2.set_xlabel("t (s)")
        ax1.legend(loc="best")
    elif results is not None:
        xs = np.arange(len(allocators))
        ax1.bar(xs, [results[n].asymmetry for n in allocators])
        ax2.bar(xs, [results[n].work_per_area for n in allocators])
        for ax in (ax1, ax2):
            ax.set_xticks(xs, list(allocators))
    ax1.set_ylabel("asymmetry of K_rendered")
    ax2.set_ylabel("work per loop area (J/m^2)")
    ax1.set_ylim(bottom=0)
    ax2.set_ylim(bottom=0)
    if title:
        ax1.set_title(title)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def default_configuration(pipeline: Pipeline) -> tuple[np.ndarray, str]:
    """The configuration ``hapticd analyze`` uses without --at, and how it was chosen."""
    return pipeline.grasp_configuration(0.002)
