"""``hapticd plot``: a run on one page, from its recording or its summary JSON.

A recording (``hapticd.recording.read``) gives panels over time: each finger's full
contact force against the rendered force (magnitude and components, N), contact,
the allocation residuals (N), the object's position (mm) and the loop's timing
(histograms of the period error from ``t_wall`` and of ``compute_s``, us). A run
summary (``hapticd run --summary-json``) holds only the period error histogram.

matplotlib is imported only inside the functions that draw (the ``plot`` extra);
figures are made with ``matplotlib.figure.Figure``, not pyplot, so nothing global
(backend, open figures) changes.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hapticd.loop.pacing import OVERRUN_FACTOR
from hapticd.recording import MAGIC, Recording, RecordingError
from hapticd.recording import read as read_recording

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

MISSING_MATPLOTLIB = (
    "hapticd plot needs matplotlib: pip install 'hapticd[plot]' (or pip install matplotlib)"
)
# Above this many ticks a trace is drawn as a min/max envelope per bucket (spikes stay).
MAX_POINTS = 20_000
FIELD_COLOURS = ("tab:red", "tab:green", "tab:blue")


class PlotError(ValueError):
    """A file or a choice of panels that cannot be plotted; the message says which and why."""


@dataclass(frozen=True)
class Panel:
    """A group of axes: its name (for ``--fields``) and the recording fields it draws."""

    name: str
    fields: tuple[str, ...]
    doc: str


PANELS: tuple[Panel, ...] = (
    Panel(
        "force",
        ("contact_force", "rendered_force"),
        "per finger: full contact force vs rendered force, magnitude and components (N)",
    ),
    Panel("contact", ("in_contact",), "each finger in contact"),
    Panel(
        "residuals",
        ("residual_internal", "residual_external"),
        "allocation residuals: squeeze lost, net wrench lost (N)",
    ),
    Panel("object", ("object_pos",), "object position x, y, z (mm)"),
    Panel("timing", ("t_wall", "compute_s"), "histograms: loop period error, tick compute (us)"),
)
PANEL_NAMES = tuple(p.name for p in PANELS)


def parse_panels(text: str | None) -> list[str] | None:
    """``--fields``: comma-separated panel names, or recording fields a panel draws (the
    panel is chosen); None for the default (every panel the file can fill)."""
    if text is None:
        return None
    out: list[str] = []
    for word in (w.strip() for w in text.split(",")):
        if not word:
            continue
        panel = next((p for p in PANELS if word in (p.name, *p.fields)), None)
        if panel is None:
            known = ", ".join(PANEL_NAMES)
            fields = ", ".join(f for p in PANELS for f in p.fields)
            raise PlotError(
                f"--fields: unknown panel or field {word!r}; panels: {known} (or a field they "
                f"draw: {fields})"
            )
        if panel.name not in out:
            out.append(panel.name)
    if not out:
        raise PlotError("--fields: no panel named")
    return out


def _new_figure(width_in: float, height_in: float) -> Figure:
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise ImportError(MISSING_MATPLOTLIB) from None
    return Figure(figsize=(width_in, height_in), layout="constrained")


def _envelope(t: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """At most about MAX_POINTS points of (t, y) (ticks first; y may have more axes): the
    minimum and maximum of each bucket, so a one-tick spike still shows."""
    n = len(t)
    if n <= MAX_POINTS:
        return t, y
    size = math.ceil(n / (MAX_POINTS // 2))
    m = n // size
    tb = t[: m * size].reshape(m, size)
    yb = y[: m * size].reshape(m, size, *y.shape[1:])
    ts = np.repeat(tb[:, 0], 2)
    ys = np.stack([yb.min(axis=1), yb.max(axis=1)], axis=1).reshape(2 * m, *y.shape[1:])
    return ts, ys


def _changes(rec: Recording, t: np.ndarray) -> np.ndarray:
    """Times (s) of the ticks at which a control change landed."""
    if "control_seq" not in rec or rec.ticks < 2:
        return np.empty(0)
    seq = rec["control_seq"].astype(np.int64)
    return t[1:][np.diff(seq) != 0]


def _mark_changes(ax: Axes, changes: np.ndarray) -> None:
    for tc in changes[:50]:  # a handful is informative; hundreds would hide the traces
        ax.axvline(tc, color="0.6", ls=":", lw=0.8)


def _period_error_us(rec: Recording) -> np.ndarray | None:
    """|t_wall[k] - t_wall[k-1] - period| per tick (us), as the loop's statistics count it;
    None for an unpaced run (its wall-clock periods are no error)."""
    if rec.ticks < 2 or rec.meta.get("paced") is False:
        return None
    rate = rec.meta.get("rate_hz")
    if isinstance(rate, int | float) and rate > 0:
        period = 1.0 / float(rate)
    else:  # not in the header: the nominal clock says it
        period = float(np.median(np.diff(rec["t"]))) if "t" in rec else 0.0
    if not period > 0:
        return None
    return np.abs(np.diff(rec["t_wall"]) - period) * 1e6


def _log_hist(ax: Axes, values_us: np.ndarray, colour: str) -> None:
    v = values_us[np.isfinite(values_us)]
    lo = max(float(v.min(initial=1.0)), 1e-3)
    hi = max(float(v.max(initial=1.0)), lo * 10)
    bins = np.geomspace(lo, hi, 60)
    ax.hist(np.clip(v, lo, hi), bins=bins, color=colour)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylabel("ticks")


def _quantiles_us(v: np.ndarray) -> str:
    p50, p99 = np.percentile(v, [50, 99])
    return f"p50 {p50:.3g} us, p99 {p99:.3g} us, max {v.max():.3g} us"


def recording_figure(rec: Recording, panels: Sequence[str] | None = None) -> Figure:
    """The figure of a recording: the named panels (default: every panel whose fields the
    recording holds). PlotError names the file and the missing field or the empty file."""
    where = str(rec.path)
    if rec.ticks == 0:
        raise PlotError(f"{where}: the recording holds no ticks")
    if "t" not in rec:
        raise PlotError(f"{where}: the recording has no field 't' (tick time, s)")
    if panels is None:
        chosen = [p for p in PANELS if all(f in rec for f in p.fields)]
        if not chosen:
            raise PlotError(
                f"{where}: nothing to plot: its fields are {', '.join(rec)}; the panels need "
                + "; ".join(f"{p.name}: {', '.join(p.fields)}" for p in PANELS)
            )
    else:
        chosen = []
        for name in panels:
            panel = next((p for p in PANELS if p.name == name), None)
            if panel is None:
                raise PlotError(f"unknown panel {name!r}; panels: {', '.join(PANEL_NAMES)}")
            missing = [f for f in panel.fields if f not in rec]
            if missing:
                raise PlotError(
                    f"{where}: panel {name!r} needs the field(s) {', '.join(missing)}, which "
                    "the recording does not hold"
                )
            chosen.append(panel)
    names = [p.name for p in chosen]
    fingers = list(rec.fingers)
    n_f = int(rec["contact_force"].shape[1]) if "force" in names else len(fingers)
    fingers = (fingers + [f"finger {i}" for i in range(len(fingers), n_f)])[: max(n_f, 1)]

    # The layout: force rows (a finger each: magnitude | components), then full-width rows;
    # timing is one row of two histograms.
    mosaic: list[list[str]] = []
    if "force" in names:
        mosaic += [[f"mag{i}", f"comp{i}"] for i in range(n_f)]
    for name in ("contact", "residuals", "object"):
        if name in names:
            mosaic.append([name, name])
    if "timing" in names:
        mosaic.append(["period", "compute"])
    fig = _new_figure(13.0, 2.5 * len(mosaic) + 0.6)
    axes = fig.subplot_mosaic(mosaic)
    t = rec["t"].astype(float)
    changes = _changes(rec, t)
    time_axes: list[Axes] = []

    if "force" in names:
        full, rendered = rec["contact_force"], rec["rendered_force"]
        sent = rec.get("device_force")
        for i, finger in enumerate(fingers[:n_f]):
            ax = axes[f"mag{i}"]
            tt, mags = _envelope(
                t,
                np.stack(
                    [np.linalg.norm(full[:, i], axis=-1), np.linalg.norm(rendered[:, i], axis=-1)]
                    + ([np.linalg.norm(sent[:, i], axis=-1)] if sent is not None else []),
                    axis=-1,
                ),
            )
            ax.plot(tt, mags[:, 0], color="tab:blue", lw=1.2, label="full |contact_force|")
            ax.plot(tt, mags[:, 1], color="tab:orange", lw=1.2, label="rendered |rendered_force|")
            if sent is not None:
                ax.plot(tt, mags[:, 2], color="k", lw=0.7, ls="--", label="sent |device_force|")
            ax.set_title(f"{finger}: force magnitude")
            ax.set_ylabel("N")
            ax.legend(loc="best", fontsize="small")
            ax = axes[f"comp{i}"]
            tt, comps = _envelope(t, np.concatenate([full[:, i], rendered[:, i]], axis=-1))
            for c, colour in enumerate(FIELD_COLOURS):
                axis = "xyz"[c]
                ax.plot(tt, comps[:, c], color=colour, lw=1.2, label=f"full {axis}")
                ax.plot(
                    tt, comps[:, 3 + c], color=colour, lw=1.0, ls="--", label=f"rendered {axis}"
                )
            ax.set_title(f"{finger}: force components")
            ax.set_ylabel("N")
            ax.legend(loc="best", fontsize="x-small", ncols=3)
            time_axes += [axes[f"mag{i}"], ax]

    if "contact" in names:
        ax = axes["contact"]
        contact = rec["in_contact"].astype(float)
        tt, cc = _envelope(t, contact)
        for i in range(contact.shape[1]):
            label = fingers[i] if i < len(fingers) else f"finger {i}"
            # Each finger on its own level: 0/1 steps offset by 1.5 per finger.
            ax.fill_between(tt, 1.5 * i, 1.5 * i + cc[:, i], step="post", alpha=0.6, label=label)
        ax.set_yticks([1.5 * i + 0.5 for i in range(contact.shape[1])], fingers[: contact.shape[1]])
        ax.set_title("contact")
        time_axes.append(ax)

    if "residuals" in names:
        ax = axes["residuals"]
        tt, res = _envelope(
            t, np.stack([rec["residual_internal"], rec["residual_external"]], axis=-1)
        )
        ax.plot(tt, res[:, 0], color="tab:purple", label="internal (squeeze lost)")
        ax.plot(tt, res[:, 1], color="tab:brown", label="external (net wrench lost)")
        ax.set_title("allocation residuals")
        ax.set_ylabel("N")
        ax.legend(loc="upper right", fontsize="small")
        time_axes.append(ax)

    if "object" in names:
        ax = axes["object"]
        tt, pos = _envelope(t, rec["object_pos"] * 1e3)
        for c, colour in enumerate(FIELD_COLOURS):
            ax.plot(tt, pos[:, c], color=colour, label="xyz"[c])
        ax.set_title("object position")
        ax.set_ylabel("mm")
        ax.legend(loc="upper right", fontsize="small")
        time_axes.append(ax)

    for ax in time_axes:
        _mark_changes(ax, changes)
        ax.set_xlim(float(t[0]), float(t[-1]) if t[-1] > t[0] else float(t[0]) + 1e-3)
        ax.grid(alpha=0.3)
    if time_axes:
        time_axes[-1].set_xlabel("t (s)")

    if "timing" in names:
        ax = axes["period"]
        err = _period_error_us(rec)
        ax.set_title("loop period error")
        if err is None or len(err) == 0:
            ax.text(0.5, 0.5, "unpaced run: no period error", ha="center", transform=ax.transAxes)
            ax.set_axis_off()
        else:
            _log_hist(ax, err, "tab:blue")
            rate = rec.meta.get("rate_hz")
            if isinstance(rate, int | float) and rate > 0:
                ax.axvline(
                    (OVERRUN_FACTOR - 1) / rate * 1e6,
                    color="tab:red",
                    ls="--",
                    label=f"overrun (period > {OVERRUN_FACTOR:g} x nominal)",
                )
                ax.legend(loc="upper right", fontsize="small")
            ax.set_xlabel(f"|period - nominal| (us); {_quantiles_us(err)}")
        ax = axes["compute"]
        ax.set_title("tick compute time")
        _log_hist(ax, rec["compute_s"] * 1e6, "tab:green")
        ax.set_xlabel(f"compute_s (us); {_quantiles_us(rec['compute_s'] * 1e6)}")

    meta = rec.meta
    head = [Path(where).name]
    if isinstance(meta.get("profile"), str):
        head.append(f"profile {meta['profile']}")
    head.append(f"{rec.ticks} ticks ({t[-1] - t[0]:.3f} s)")
    if isinstance(meta.get("allocator"), str):
        head.append(f"allocator {meta['allocator']} at the start")
    if meta.get("paced") is False:
        head.append("unpaced")
    if len(changes):
        head.append(f"dotted: {len(changes)} control change(s)")
    fig.suptitle(", ".join(head))
    return fig


def _number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def summary_figure(summary: dict[str, Any], where: str = "summary") -> Figure:
    """The figure of a run summary (``hapticd run --summary-json``): its period error
    histogram, with the rate, quantiles and overruns. PlotError names a missing key."""
    if not isinstance(summary, dict):
        raise PlotError(f"{where}: a run summary is a JSON object")
    hist = summary.get("period_error_hist_us")
    if not isinstance(hist, list) or not all(
        isinstance(b, list)
        and len(b) == 2
        and all(isinstance(v, int | float) and math.isfinite(v) for v in b)
        for b in hist
    ):
        raise PlotError(
            f"{where}: 'period_error_hist_us' must be a list of [error_us, count] pairs "
            "(a run summary from hapticd run --summary-json)"
        )
    rate = summary.get("rate_hz")
    rate = rate if isinstance(rate, dict) else {}
    target, achieved = rate.get("target"), rate.get("achieved")
    fig = _new_figure(9.0, 4.5)
    ax = fig.subplots()
    ax.set_title("loop period error")
    if not hist:
        ax.text(
            0.5,
            0.5,
            "no period error: unpaced run or no ticks",
            ha="center",
            transform=ax.transAxes,
        )
        ax.set_axis_off()
    else:
        e = np.array([max(float(b[0]), 1e-3) for b in hist])
        c = np.array([float(b[1]) for b in hist])
        ax.bar(e, c, width=e * 0.12, color="tab:blue", align="center")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("|period - nominal| (us), log bins")
        ax.set_ylabel("ticks")
        if _number(target) and target > 0:
            ax.axvline(
                (OVERRUN_FACTOR - 1) / target * 1e6,
                color="tab:red",
                ls="--",
                label=f"overrun (period > {OVERRUN_FACTOR:g} x nominal)",
            )
            ax.legend(loc="upper right", fontsize="small")
        ax.grid(alpha=0.3)
    lines = []
    pe = summary.get("period_error_us")
    if isinstance(pe, dict):
        lines.append(
            "period error " + ", ".join(f"{k} {v:g} us" for k, v in pe.items() if _number(v))
        )
    tc = summary.get("tick_compute_us")
    if isinstance(tc, dict):
        lines.append(
            "tick compute " + ", ".join(f"{k} {v:g} us" for k, v in tc.items() if _number(v))
        )
    if _number(summary.get("overruns")):
        lines.append(f"overruns {summary['overruns']}")
    if lines:
        ax.text(
            0.01,
            0.98,
            "\n".join(lines),
            transform=ax.transAxes,
            va="top",
            fontsize="small",
            family="monospace",
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
        )
    head = [Path(where).name]
    if isinstance(summary.get("profile"), str):
        head.append(f"profile {Path(summary['profile']).name}")
    if isinstance(summary.get("ticks"), int):
        head.append(f"{summary['ticks']} ticks")
    if _number(target) and _number(achieved):
        head.append(f"target {target:g} Hz, achieved {achieved:g} Hz")
    fig.suptitle(", ".join(head))
    return fig


def figure_for(path: str | Path, panels: Sequence[str] | None = None) -> Figure:
    """The figure of a recording (.hrec) or a run summary (JSON), told apart by content."""
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            start = fh.read(len(MAGIC))
    except OSError as exc:
        raise PlotError(f"{p}: cannot read: {exc.strerror or exc}") from None
    if start == MAGIC:
        try:
            rec = read_recording(p)
        except RecordingError as exc:
            raise PlotError(str(exc)) from None
        return recording_figure(rec, panels)
    if start.lstrip()[:1] == b"{":
        try:
            summary = json.loads(p.read_bytes())
        except (ValueError, OSError) as exc:
            raise PlotError(f"{p}: not a run summary (JSON): {exc}") from None
        if panels is not None and list(panels) != ["timing"]:
            raise PlotError(
                f"{p}: a run summary holds only the timing histogram (--fields timing); "
                "plot the run's recording for the other panels"
            )
        return summary_figure(summary, str(p))
    raise PlotError(
        f"{p}: neither a hapticd recording (it starts with {MAGIC!r}) nor a run summary "
        "(a JSON object from hapticd run --summary-json)"
    )


def save(fig: Figure, out: str | Path) -> Path:
    """Write ``fig`` as a PNG (or what the suffix names) and return the path."""
    out = Path(out)
    fig.savefig(out, dpi=100)
    return out
