#!/usr/bin/env python3
"""Time ``hapticd study`` (model observers) on a process pool against one worker.

Runs the same reduced design (default: the stiffness experiment, 2 observers, standard
60 N/m, 2 repetitions: 48 trials) with --workers 1 and with --workers K, each R times
into fresh stores, checks that every run stored the same answers, and prints the median
and worst wall time per configuration, trials per second and the pool's speed-up.
Usage: python scripts/bench_study.py [--exp FILE] [--observers N] [--standards A,B]
[--repetitions N] [--workers K] [--repeats R] [--plot PATH]
"""

from __future__ import annotations

import argparse
import os
import sqlite3
import tempfile
import time
from pathlib import Path

import numpy as np

from hapticd.experiment.study import run_study

ROOT = Path(__file__).resolve().parent.parent


def answers(db: Path) -> list[tuple]:
    con = sqlite3.connect(db)
    try:
        return con.execute(
            "SELECT subject, plan_index, answer_second_more FROM trials ORDER BY 1, 2"
        ).fetchall()
    finally:
        con.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--exp", default=str(ROOT / "configs/experiments/stiffness-jnd.yaml"))
    ap.add_argument("--observers", type=int, default=2)
    ap.add_argument("--standards", default="60")
    ap.add_argument("--repetitions", type=int, default=2)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--plot", type=Path, help="save a bar plot here (default: a temp dir)")
    args = ap.parse_args()
    standards = [float(s) for s in args.standards.split(",")]
    configs = {"one worker": 1, f"pool of {args.workers}": args.workers}
    times: dict[str, list[float]] = {k: [] for k in configs}
    cpu: dict[str, list[float]] = {k: [] for k in configs}
    load_before = os.getloadavg()[0]
    reference = None
    n_trials = 0
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for name, workers in configs.items():  # alternate: the same load for both
                db = Path(tmp) / f"{r}-{workers}.sqlite"
                c0 = os.times()
                t0 = time.perf_counter()
                res = run_study(
                    args.exp,
                    args.observers,
                    db,
                    seed=1,
                    workers=workers,
                    standards=standards,
                    repetitions=args.repetitions,
                )
                times[name].append(time.perf_counter() - t0)
                c1 = os.times()
                # This process and its (reaped) pool workers: the CPU the trials took.
                cpu[name].append(sum(c1[:4]) - sum(c0[:4]))
                n_trials = res.total
                got = answers(db)
                if reference is None:
                    reference = got
                elif got != reference:
                    raise SystemExit(f"{name}: other answers than the first run")
    print(
        f"{Path(args.exp).name}: {args.observers} observers, standards {standards}, "
        f"{args.repetitions} repetitions: {n_trials} trials; {args.repeats} runs each; "
        "identical stored answers in every run"
    )
    print(
        f"load average (1 min) before {load_before:.2f}, after {os.getloadavg()[0]:.2f} "
        f"on {os.cpu_count()} cores (other work on the machine slows both alike)"
    )
    print(
        f"{'configuration':<16} {'median s':>9} {'worst s':>8} {'CPU s':>7} {'trials/s':>9} "
        f"{'speed-up':>9}"
    )
    base = float(np.median(times["one worker"]))
    for name, ts in times.items():
        med = float(np.median(ts))
        print(
            f"{name:<16} {med:>9.2f} {max(ts):>8.2f} {np.median(cpu[name]):>7.1f} "
            f"{n_trials / med:>9.1f} {base / med:>8.2f}x"
        )
    plot = args.plot or Path(tempfile.gettempdir()) / "bench_study.png"
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(4.5, 3))
    ax.bar(list(times), [np.median(v) for v in times.values()], color=["C0", "C1"])
    ax.set_ylabel("wall time, s (median)")
    ax.set_title(f"hapticd study, {n_trials} trials")
    fig.tight_layout()
    fig.savefig(plot, dpi=100)
    print(f"plot: {plot}")


if __name__ == "__main__":
    main()
