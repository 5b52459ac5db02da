#!/usr/bin/env python3
"""How large a subject's recordings are with and without ``recording.rate_hz``, and what
the decimation loses, measured on intervals the model observer explores.

For R intervals of an experiment (default: the stiffness design's, standards and
comparisons drawn at random) the model observer plans its hand's path and the servo loop
runs it (``hapticd.experiment.observer``: the records the loop hands a recorder, at the
loop rate given, default 1000 Hz as a rig runs); each interval is written as a recording
at the full rate and kept every N-th tick (the writer's decimation), and read back. Prints
bytes per recorded second, MB per interval (the observer's intervals, and at the
experiment's exploration limit, a person's longest), MB per subject of TRIALS trials (2
intervals each), and what each N loses on the export's columns: the error of each
finger's peak and in-contact mean |device_force| (N) and contact time (s), median and
worst (p99) over the intervals.

Usage: python scripts/bench_recording_size.py [--intervals R] [--every 2,5,10]
[--trials 360] [--rate-hz 1000] [--exp FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import numpy as np

from hapticd.experiment import check_experiment
from hapticd.experiment import export as ex
from hapticd.experiment import observer as ob
from hapticd.recording import read
from hapticd.recording.format import header_bytes, loop_fields

ROOT = Path(__file__).resolve().parent.parent


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exp", type=Path, default=ROOT / "configs/experiments/stiffness-jnd.yaml")
    ap.add_argument("--intervals", type=int, default=12)
    ap.add_argument("--every", default="2,5,10")
    ap.add_argument("--trials", type=int, default=360)
    ap.add_argument("--rate-hz", type=float, default=1000.0)
    args = ap.parse_args()
    exp, _ = check_experiment(args.exp)
    config = dataclasses.replace(ob.default_config(exp), rate_hz=args.rate_hz)
    profile = ob.observer_profile(exp, config)
    kind = ob.exploration_kind(exp)
    rng = np.random.default_rng(1)
    everies = [int(x) for x in args.every.split(",")]
    sizes: dict[int, list[int]] = {1: [], **{n: [] for n in everies}}
    errors: dict[int, dict[str, list[float]]] = {n: {} for n in everies}
    seconds: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.intervals):
            standard = float(rng.choice(exp.varied.standards))
            ratio = float(rng.choice(exp.varied.ratios or (1.0,)))
            settings = {**exp.conditions[i % len(exp.conditions)].values(),
                        exp.varied.param: standard * ratio}  # fmt: skip
            t, x, _ = ob.plan_path(kind, profile, config.motor, rng, settings=settings,
                                   hand=config.hand)  # fmt: skip
            rows = ob.run_interval(profile, settings, (t, x), config)
            fields = loop_fields(len(profile.fingers), rows["lam_a"].shape[1])
            seconds.append(len(rows) / args.rate_hz)
            stats = {}
            for n in (1, *everies):
                path = Path(tmp) / f"i{i}-{n}.hrec"
                meta = {"rate_hz": args.rate_hz, "record_every": n}
                head = header_bytes(fields, list(profile.finger_names), meta)
                path.write_bytes(head + rows[::n].tobytes())
                sizes[n].append(path.stat().st_size)
                stats[n] = ex.interval_stats(read(path))
            for n in everies:
                for key, full in stats[1].items():
                    if key.startswith(("peak", "mean", "contact")) and full is not None:
                        got = stats[n][key]
                        err = abs((got if got is not None else 0.0) - full)
                        errors[n].setdefault(key.rsplit("_", 2)[0], []).append(err)
    per_s = np.sum(sizes[1]) / np.sum(seconds)
    limit_s = exp.interval.exploration_s
    print(f"{args.intervals} intervals of {exp.name} at {args.rate_hz:g} Hz, mean "
          f"{np.mean(seconds):.2f} s each (the exploration limit: {limit_s:g} s)")  # fmt: skip
    print(
        "| kept | bytes/s | MB/interval (observer) | MB/interval (at the limit) | "
        f"MB per {args.trials}-trial subject (at the limit) |"
    )
    print("|---|---|---|---|---|")
    for n in (1, *everies):
        rate = np.sum(sizes[n]) / np.sum(seconds)
        print(f"| every {n} ({args.rate_hz / n:g} Hz) | {rate:,.0f} | "
              f"{np.mean(sizes[n]) / 1e6:.3f} | {rate * limit_s / 1e6:.3f} | "
              f"{rate * limit_s * 2 * args.trials / 1e6:,.0f} |")  # fmt: skip
    print(f"(full rate: {per_s:,.0f} bytes per recorded second)")
    print("| kept | column | median error | p99 error |")
    print("|---|---|---|---|")
    for n in everies:
        for key, errs in errors[n].items():
            e = np.asarray(errs)
            print(f"| every {n} | {key} | {np.median(e):.3g} | {np.percentile(e, 99):.3g} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
