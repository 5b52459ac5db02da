#!/usr/bin/env python3
"""Time ``hapticd study`` (model observers): one worker, a process pool and a Dask cluster.

One run compares, on the same reduced design (default: the stiffness experiment, 2
observers, every standard, 4 repetitions: 288 trials), the study computed

- in this process (``--workers 1``: the baseline),
- by a process pool of K workers (``--workers K``),
- on a real Dask cluster on loopback: a ``dask scheduler`` process and K ``dask worker``
  processes of one thread each (``hapticd.experiment.cluster``), started once before the
  runs, like a lab's cluster.

Each configuration first runs a small untimed study (so every process has its kernels
loaded, as on a cluster already in use); then the configurations run in turn, R times,
into fresh stores (alternating, so the machine's other load hits all alike). Every run
must store the same answers. Prints the median and worst wall time, the CPU time the
trials took (this process, the pool's reaped workers, the Dask workers), trials per
second and the speed-up over one worker, and saves a bar plot.

Usage: python scripts/bench_study.py [--workers K] [--repeats R] [--plot PATH]
[--exp FILE] [--observers N] [--standards A,B] [--repetitions N] [--no-dask]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sqlite3
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from hapticd.experiment import check_experiment
from hapticd.experiment.study import run_study

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_PLOT = Path(tempfile.gettempdir()) / "hapticd-bench-study.png"


def answers(db: Path) -> list[tuple]:
    con = sqlite3.connect(db)
    try:
        return con.execute(
            "SELECT subject, plan_index, answer_second_more, status FROM trials ORDER BY 1, 2"
        ).fetchall()
    finally:
        con.close()


def own_cpu() -> float:
    """CPU s of this process and its reaped children (a pool's workers)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--exp", default=str(ROOT / "configs/experiments/stiffness-jnd.yaml"))
    ap.add_argument("--observers", type=int, default=2)
    ap.add_argument("--standards", help="e.g. 60 or 30,90 (default: all the file's)")
    ap.add_argument("--repetitions", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2, help="K: pool and Dask workers")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-dask", action="store_true", help="one worker and the pool only")
    ap.add_argument("--plot", type=Path, default=DEFAULT_PLOT)
    args = ap.parse_args()
    standards = [float(s) for s in args.standards.split(",")] if args.standards else None
    k = args.workers
    design = dict(seed=1, standards=standards, repetitions=args.repetitions)
    # Untimed first: the first standard, the fewest repetitions (a few tasks), so that
    # every process has loaded its kernels (as on a cluster already in use).
    exp = check_experiment(args.exp)[0]
    fewest = exp.blocks.per_standard * (2 if exp.interval.order == "randomized" else 1)
    warm = dict(seed=2, standards=(standards or exp.varied.standards)[:1], repetitions=fewest)
    load_before = os.getloadavg()[0]
    with (
        tempfile.TemporaryDirectory(prefix="bench-study-") as tmp,
        dask_client(not args.no_dask, k, Path(tmp) / "cluster") as client,
    ):
        how: dict[str, dict[str, Any]] = {"one worker": {"workers": 1}}
        how[f"pool of {k}"] = {"workers": k}
        cpu_of: dict[str, Callable[[], float]] = {name: own_cpu for name in how}
        if client is not None:
            how[f"Dask, {k} workers"] = {"scheduler": client}
            cpu_of[f"Dask, {k} workers"] = lambda: (
                own_cpu() + sum(client.run(lambda: sum(os.times()[:2])).values())
            )
        for i, kw in enumerate(how.values()):
            run_study(args.exp, 2, Path(tmp) / f"warm-{i}.sqlite", **kw, **warm)
        times: dict[str, list[float]] = {name: [] for name in how}
        cpu: dict[str, list[float]] = {name: [] for name in how}
        reference, n_trials = None, 0
        for r in range(args.repeats):
            for i, (name, kw) in enumerate(how.items()):
                db = Path(tmp) / f"{r}-{i}.sqlite"
                c0 = cpu_of[name]()
                t0 = time.perf_counter()
                res = run_study(args.exp, args.observers, db, **kw, **design)
                times[name].append(time.perf_counter() - t0)
                cpu[name].append(cpu_of[name]() - c0)
                n_trials = res.total
                got = answers(db)
                if reference is None:
                    reference = got
                elif got != reference:
                    raise SystemExit(f"{name}: other answers than the first run")
    print(
        f"{Path(args.exp).name}: {args.observers} observers, standards "
        f"{standards or 'all'}, {args.repetitions} repetitions: {n_trials} trials; "
        f"{args.repeats} runs each; identical stored answers in every run"
    )
    print(
        f"load average (1 min) before {load_before:.2f}, after {os.getloadavg()[0]:.2f} "
        f"on {os.cpu_count()} cores (other work on the machine slows every run)"
    )
    print()
    print("| configuration | median s | worst s | CPU s | trials/s | speed-up |")
    print("|---|---|---|---|---|---|")
    base = float(np.median(times["one worker"]))
    for name, ts in times.items():
        med = float(np.median(ts))
        print(
            f"| {name} | {med:.2f} | {max(ts):.2f} | {np.median(cpu[name]):.1f} | "
            f"{n_trials / med:.1f} | {base / med:.2f}x |"
        )
    print()
    for name, ts in times.items():
        if name != "one worker":
            print(f"speed-up {name}: {base / float(np.median(ts)):.2f}x")
    _plot(args.plot, times, base, n_trials)


@contextlib.contextmanager
def dask_client(on: bool, k: int, folder: Path) -> Iterator[Any]:
    """A Client of a loopback cluster of ``k`` workers (None when ``on`` is false)."""
    if not on:
        yield None
        return
    from distributed import Client

    from hapticd.experiment.cluster import loopback_cluster

    with loopback_cluster(k, folder) as address, Client(address, timeout="60s") as client:
        yield client


def _plot(path: Path, times: dict[str, list[float]], base: float, n_trials: int) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    names = list(times)
    meds = [float(np.median(times[n])) for n in names]
    fig, ax = plt.subplots(figsize=(5.5, 3.2))
    bars = ax.bar(names, meds, color=[f"C{i}" for i in range(len(names))])
    for b, m, name in zip(bars, meds, names, strict=True):
        ax.annotate(
            f"{base / m:.2f}x", (b.get_x() + b.get_width() / 2, m), ha="center", va="bottom"
        )
        ax.scatter([b.get_x() + b.get_width() / 2] * len(times[name]), times[name], s=8, c="k")
    ax.set_ylabel("wall time, s (bar: median; dots: runs)")
    ax.set_title(f"hapticd study, {n_trials} trials")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"plot: {path}")


if __name__ == "__main__":
    main()
