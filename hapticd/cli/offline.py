"""The offline commands on profiles and recordings: analyze, plot and export."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from hapticd import params
from hapticd.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_ERROR,
    EXIT_OK,
    _at,
    _every,
    _ProgressLine,
    _wants_progress,
)
from hapticd.profile import ProfileError, load_profile
from hapticd.recording import RecordingError
from hapticd.recording import read as read_recording
from hapticd.recording.export import csv_columns, export_csv, export_mcap

log = logging.getLogger("hapticd")


def cmd_analyze(args: argparse.Namespace) -> int:
    """Barbagli & Salisbury's analysis of a profile's rendering (docs/analysis.md)."""

    from hapticd.analysis import Pipeline, report

    try:
        profile = load_profile(args.profile)
        allocators = args.allocators.split(",") if args.allocators else None
        pipe = Pipeline.from_profile(profile, allocators=allocators)
    except ProfileError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ValueError as exc:
        print(f"hapticd: --allocators: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    obj = profile.scene.object
    head = (
        f"hapticd analyze {args.profile}: profile {profile.name!r}, {obj.shape} "
        f"{'fixed' if obj.fixed else 'free (held at its pose)'}, "
        f"{pipe.scene.object.material.stiffness:g} N/m, "
        f"{'friction' if pipe.has_friction else 'frictionless'}, "
        f"{profile.rendering.actuation_frame}-frame actuation; at rest (zero velocity), "
        "before safety"
    )
    out: dict[str, Any] = {"profile": str(args.profile), "allocators": list(pipe.allocators)}
    try:
        if args.recording is not None:
            rec = read_recording(args.recording)
            if "device_pos" not in rec:
                raise RecordingError(f"{args.recording}: no device_pos field")
            pos = rec["device_pos"]
            note = ""
            if list(rec.fingers) != list(pipe.finger_names):
                if pos.ndim != 3 or pos.shape[1] != pipe.n_fingers:
                    raise RecordingError(
                        f"{args.recording} has fingers {rec.fingers}, the profile "
                        f"{list(pipe.finger_names)}"
                    )
                note = f"; its fingers {', '.join(rec.fingers)} taken in the profile's order"
            extra = {
                k: rec[k] for k in ("object_pos", "object_rot", "stiffness_n_per_m") if k in rec
            }
            times = rec["t"] if "t" in rec else np.arange(len(pos)) * pipe.dt
            show = args.progress or sys.stderr.isatty()
            samples = pipe.along(
                pos,
                args.every,
                object_pos=extra.get("object_pos"),
                object_rot=extra.get("object_rot"),
                stiffness=extra.get("stiffness_n_per_m"),
                progress=report.Progress("analyze") if show else None,
            )
            recorded = ", ".join(extra) or "none"
            print(head)
            print(
                f"recording {args.recording}: {len(pos)} ticks; every {args.every}th: "
                f"{len(samples)} samples (recorded scene state applied: {recorded}){note}\n"
            )
            print(report.format_samples(samples, times, pipe.allocators), end="")
            out["recording"] = str(args.recording)
            out["every"] = args.every
            out["samples"] = report.samples_json(samples, times)
            plot_kw: dict[str, Any] = {"samples": samples, "times": times}
        else:
            if args.at is not None:
                x = np.array(_at(args.at, pipe.n_fingers)).reshape(-1, 3)
                how = "given with --at"
            else:
                x, how = report.default_configuration(pipe)
            results = pipe.linearize(x)
            print(
                report.format_linearization(results, header=[head, f"configuration: {how}"]),
                end="",
            )
            out["configuration"] = {"x_m": x.tolist(), "how": how}
            out["results"] = report.to_json(results)
            plot_kw = {"results": results}
    except (ValueError, RecordingError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        if args.json is not None:
            args.json.write_text(json.dumps(out, indent=1, allow_nan=False) + "\n")
        if args.plot is not None:
            try:
                report.plot(
                    args.plot,
                    pipe.allocators,
                    title=f"{profile.name}: asymmetry and work per loop area, per allocator",
                    **plot_kw,
                )
            except ImportError:
                print(
                    "hapticd: --plot needs matplotlib: pip install matplotlib "
                    "(or the 'bench' extra)",
                    file=sys.stderr,
                )
                return EXIT_ERROR
    except OSError as exc:
        print(f"hapticd: cannot write: {exc}", file=sys.stderr)
        return EXIT_ERROR
    return EXIT_OK


def _add_analyze(sub: Any) -> None:
    """The analyze subcommand's arguments."""
    ana = sub.add_parser(
        "analyze",
        help="Barbagli & Salisbury's asymmetry analysis of a profile's rendering, per allocator",
        description="Linearize the rendering of PROFILE (central differences on the loop's own "
        "stages, at rest, before safety): K_full (the seed's F_L), K_rendered (M_A F_L M_S), "
        "asymmetry, controllability, observability, the directions without rendered stiffness "
        "and the work per unit loop area, for each allocator. See docs/analysis.md.",
    )
    ana.add_argument("profile", type=Path)
    where = ana.add_mutually_exclusive_group()
    where.add_argument(
        "--at",
        nargs="+",
        metavar="M",
        help="finger positions, x y z in m per finger (default: each finger 2 mm inside the "
        "object along its x axis, the first on the -x side)",
    )
    where.add_argument(
        "--recording", type=Path, metavar="REC", help="analyse the ticks of a recording"
    )
    ana.add_argument(
        "--every", type=_every, default=10, metavar="K", help="every K-th tick (default 10)"
    )
    ana.add_argument(
        "--allocators",
        metavar="A,B",
        help=f"allocators to compare (default: pinv,if,ef,adaptive; any of "
        f"{','.join(params.ALLOCATORS)})",
    )
    ana.add_argument("--json", type=Path, metavar="OUT", help="write every number as JSON")
    ana.add_argument("--plot", type=Path, metavar="OUT.png", help="plot (needs matplotlib)")
    ana.add_argument(
        "--progress", action="store_true", help="show progress on stderr even when not a terminal"
    )
    ana.set_defaults(func=cmd_analyze)


def _export_progress(args: argparse.Namespace) -> tuple[Any, _ProgressLine | None]:
    """The ``progress`` callback of an export (None without a progress line)."""
    if not _wants_progress(args):
        return None, None
    line = _ProgressLine(f"export {args.recording}:")

    def progress(done: int, total: int) -> None:
        line.show(done, total, "ticks", force=done == total)

    return progress, line


def _plot(source: Path, out: Path, panels: list[str] | None) -> int:
    """Draw ``source`` (a recording or a run summary) into ``out``; print where it went."""
    from hapticd import plot

    try:
        fig = plot.figure_for(source, panels)
        plot.save(fig, out)
    except plot.PlotError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ImportError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        print(f"hapticd: cannot write the plot {out}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_ERROR
    print(f"plot: {out}")
    return EXIT_OK


def cmd_plot(args: argparse.Namespace) -> int:
    from hapticd import plot

    try:
        panels = plot.parse_panels(args.fields)
    except plot.PlotError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    out = args.out or Path(tempfile.gettempdir()) / f"hapticd-plot-{args.source.stem}.png"
    return _plot(args.source, out, panels)


def _add_plot(sub: Any) -> None:
    """The plot subcommand's arguments."""
    from hapticd.plot import PANELS

    pl = sub.add_parser(
        "plot",
        help="plot a recording (forces, contact, residuals, object, timing) or a run summary",
        description="Draw a recording (.hrec) as panels over time, or a run summary "
        "(hapticd run --summary-json) as its period error histogram, into a PNG. Panels: "
        + "; ".join(f"{p.name}: {p.doc}" for p in PANELS)
        + ". Needs matplotlib (the 'plot' extra).",
    )
    pl.add_argument("source", type=Path, metavar="REC", help="a recording or a summary JSON")
    pl.add_argument(
        "--out",
        type=Path,
        metavar="FILE.png",
        help="where the figure goes (default: hapticd-plot-NAME.png in the temp dir)",
    )
    pl.add_argument(
        "--fields",
        metavar="A,B",
        help=f"the panels to draw, by name ({','.join(p.name for p in PANELS)}) or by a field "
        "they draw (default: every panel the recording can fill)",
    )
    pl.set_defaults(func=cmd_plot)


def cmd_export(args: argparse.Namespace) -> int:
    progress, line = _export_progress(args)
    try:
        rec = read_recording(args.recording)
        if args.mcap is not None:
            out, rows = args.mcap, export_mcap(rec, args.mcap, progress=progress)
            what = "messages on /hapticd/tick"
        else:
            out = args.csv or args.recording.with_suffix(".csv")
            rows = export_csv(rec, out, progress=progress)
            what = f"ticks, {len(csv_columns(rec))} columns"
    except RecordingError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except RuntimeError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        print(f"hapticd: cannot write the export: {exc}", file=sys.stderr)
        return EXIT_ERROR
    finally:
        if line is not None:
            line.done()
    torn = f" (a torn last record of {rec.torn_bytes} bytes was dropped)" if rec.torn_bytes else ""
    print(f"{out}: {rows} {what}{torn}")
    return EXIT_OK
