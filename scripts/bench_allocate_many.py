#!/usr/bin/env python3
"""Batched allocation for offline work: allocate_many against per-grasp loops, in one run.

Workloads (generated, fixed seed): two-finger grasps of a 50 mm cube like
configs/grasp-stiffness.yaml, (1) one actuated direction per finger, 30 degrees
up from the grasp line, and (2) three directions (the thumb gets a second one,
sideways); contact points, directions and forces vary per grasp.

Variants per method (pinv, if, ef), per grasp:

- seed loop      : a Python loop over the seed's formulas in plain numpy
                   (hapticd.allocation.exact: np.linalg.pinv, SVD null spaces), the baseline
- allocate loop  : a Python loop over allocate() (robust, closed form where it applies)
- allocate_many  : one call on the loop's grasps, as a caller makes it (the default: the
                   installed compiler's allocate_grasps, compiled once and cached)
- python         : the same call with kernel="python" (the same per-grasp code on Python
                   floats, uncompiled)
- compiled       : allocate_many with kernel= (hapticd.allocation.kernels.allocate_grasps, compiled
                   by hapticd.physics.jit): one call on a batch of 1e3, and of 1e4, grasps

Every variant is timed the same way: the process's CPU time of a whole pass
divided by its number of grasps (a loop over ``--loop-grasps`` grasps, a batch
of N), median and p99 over the passes of ``--rounds`` rounds (each round runs
all 1e4 grasps in compiled batches: ten of 1e3, one of 1e4). CPU time, because the
machine is shared: wall-clock time would count other jobs' time slices, and
unevenly (a 5 ms batch is nearly always preempted, a 20 us call rarely).
Variants are interleaved within each round; ratios are against the seed loop
and the allocate loop of the same run. The last column is the largest
|allocate_many - allocate| over the loop's grasps (N), compiled and not. Prints a Markdown table
and saves a plot.

Usage: python scripts/bench_allocate_many.py [--rounds 25] [--plot PATH]
(default plot: bench-allocate-many.png in the system temp directory)
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from hapticd.allocation import allocate, allocate_many, ef_exact, if_exact, pinv_exact
from hapticd.physics import jit

METHODS = ("pinv", "if", "ef")
SEED: dict[str, Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]] = {
    "pinv": pinv_exact,
    "if": if_exact,
    "ef": ef_exact,
}
BATCHES = (1_000, 10_000)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _jitter(rng: np.random.Generator, base: np.ndarray, n: int, deg: float) -> np.ndarray:
    """(n, 3) unit vectors within about ``deg`` degrees of ``base``."""
    return _unit(base + rng.normal(size=(n, 3)) * np.radians(deg))


def workload(n: int, three: bool, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(G (n, 6, 6), M_a (n, 6, r), lam (n, 6)) for two fingers on a 50 mm cube."""
    rng = np.random.default_rng(seed)
    a = 0.025
    pts = np.stack(
        [
            np.column_stack([np.full(n, -a), rng.uniform(-0.02, 0.02, (n, 2))]),
            np.column_stack([np.full(n, a), rng.uniform(-0.02, 0.02, (n, 2))]),
        ],
        axis=1,
    )  # (n, 2, 3) m, the cube's centre at the origin
    G = np.zeros((n, 6, 6))
    for i in range(2):
        x, y, z = pts[:, i, 0], pts[:, i, 1], pts[:, i, 2]
        G[:, 0:3, 3 * i : 3 * i + 3] = np.eye(3)
        G[:, 3, 3 * i + 1], G[:, 3, 3 * i + 2] = -z, y
        G[:, 4, 3 * i + 0], G[:, 4, 3 * i + 2] = z, -x
        G[:, 5, 3 * i + 0], G[:, 5, 3 * i + 1] = -y, x
    up = np.sin(np.radians(30.0))
    d_thumb = _jitter(rng, np.array([np.cos(np.radians(30.0)), 0.0, up]), n, 10.0)
    d_index = _jitter(rng, np.array([-np.cos(np.radians(30.0)), 0.0, up]), n, 10.0)
    r = 3 if three else 2
    M = np.zeros((n, 6, r))
    M[:, 0:3, 0] = d_thumb
    M[:, 3:6, r - 1] = d_index
    if three:
        M[:, 0:3, 1] = _jitter(rng, np.array([0.0, 1.0, 0.0]), n, 20.0)
    squeeze = rng.uniform(0.5, 4.0, n)  # N, along the grasp line
    weight = rng.uniform(0.0, 0.5, n)  # N, shared by the fingers
    lam = np.zeros((n, 6))
    lam[:, 0], lam[:, 3] = squeeze, -squeeze
    lam[:, 2] = lam[:, 5] = weight / 2
    lam += rng.normal(size=(n, 6)) * 0.2  # friction and noise
    return G, M, lam


def _stats(ts: list[float]) -> tuple[float, float]:
    s = sorted(ts)
    return statistics.median(s) * 1e6, s[min(len(s) - 1, int(0.99 * len(s)))] * 1e6


def measure(
    method: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray, rounds: int, loop_n: int
) -> dict[str, tuple[float, float]]:
    """Per-grasp CPU time (median us, p99 us) of every variant, interleaved over ``rounds``."""
    seed_fn = SEED[method]
    kernel = jit.compile_kernels(["allocate_grasps"])["allocate_grasps"]
    times: dict[str, list[float]] = {
        "seed loop": [],
        "allocate loop": [],
        "allocate_many": [],
        "python": [],
    }
    for nb in BATCHES:
        times[f"compiled {nb:.0e}"] = []
    clock = time.process_time  # this process's CPU time: other jobs' time slices do not count
    for _ in range(rounds):
        t0 = clock()
        for i in range(loop_n):
            seed_fn(G[i], M[i], lam[i])
        times["seed loop"].append((clock() - t0) / loop_n)
        t0 = clock()
        for i in range(loop_n):
            allocate(method, G[i], M[i], lam[i])
        times["allocate loop"].append((clock() - t0) / loop_n)
        t0 = clock()
        allocate_many(method, G[:loop_n], M[:loop_n], lam[:loop_n])
        times["allocate_many"].append((clock() - t0) / loop_n)
        t0 = clock()
        allocate_many(method, G[:loop_n], M[:loop_n], lam[:loop_n], kernel="python")
        times["python"].append((clock() - t0) / loop_n)
        for nb in BATCHES:
            ts = times[f"compiled {nb:.0e}"]
            for k in range(0, G.shape[0] - nb + 1, nb):  # every grasp once per round
                t0 = clock()
                allocate_many(method, G[k : k + nb], M[k : k + nb], lam[k : k + nb], kernel=kernel)
                ts.append((clock() - t0) / nb)
    return {k: _stats(v) for k, v in times.items()}


def max_difference(method: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray, n: int) -> float:
    """Largest |allocate_many - allocate one by one| (N) over the first ``n`` grasps: by
    default, compiled and uncompiled."""
    kernel = jit.compile_kernels(["allocate_grasps"])["allocate_grasps"]
    ref = np.array([allocate(method, G[i], M[i], lam[i]) for i in range(n)])
    return max(
        float(np.abs(allocate_many(method, G[:n], M[:n], lam[:n], kernel=k) - ref).max())
        for k in (None, "python", kernel)
    )


def plot(path: Path, rows: list[tuple[str, str, str, float, float]]) -> None:
    """Median CPU time per grasp (bars, log scale, p99 whiskers) per workload and method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    workloads = list(dict.fromkeys(r[0] for r in rows))
    variants = list(dict.fromkeys(r[2] for r in rows))
    fig, axes = plt.subplots(1, len(workloads), figsize=(6 * len(workloads), 4.5), squeeze=False)
    width = 0.8 / len(variants)
    for ax, wl in zip(axes[0], workloads, strict=True):
        for j, v in enumerate(variants):
            sel = [r for r in rows if r[0] == wl and r[2] == v]
            x = np.arange(len(sel)) + (j - (len(variants) - 1) / 2) * width
            med = np.array([r[3] for r in sel])
            p99 = np.array([r[4] for r in sel])
            ax.bar(x, med, width, yerr=[np.zeros_like(med), p99 - med], label=v, capsize=2)
        ax.set_xticks(np.arange(len(METHODS)), METHODS)
        ax.set_yscale("log")
        ax.set_ylabel("CPU time per grasp (us): median, p99 whisker")
        ax.set_title(wl)
        ax.grid(True, axis="y", which="both", alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("allocate_many against per-grasp loops (same run)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description="allocate_many against per-grasp loops.")
    ap.add_argument("--rounds", type=int, default=25, help="interleaved timing rounds")
    ap.add_argument("--loop-grasps", type=int, default=1000, help="grasps per loop per round")
    ap.add_argument(
        "--plot", type=Path, default=Path(tempfile.gettempdir()) / "bench-allocate-many.png"
    )
    args = ap.parse_args()

    rows: list[tuple[str, str, str, float, float]] = []
    lines = [
        "| workload | method | variant | median CPU us/grasp | p99 CPU us/grasp | vs seed loop | "
        "vs allocate loop | max diff N |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, three in (("2 fingers, 1 direction each", False), ("2 fingers, 3 directions", True)):
        G, M, lam = workload(max(BATCHES), three)
        for method in METHODS:
            res = measure(method, G, M, lam, args.rounds, args.loop_grasps)
            diff = max_difference(method, G, M, lam, args.loop_grasps)
            seed_med, loop_med = res["seed loop"][0], res["allocate loop"][0]
            for variant, (med, p99) in res.items():
                rows.append((label, method, variant, med, p99))
                batch = variant.startswith(("allocate_many", "compiled"))
                lines.append(
                    f"| {label} | {method} | {variant} | {med:.3g} | {p99:.3g} | "
                    f"{seed_med / med:.1f}x | {loop_med / med:.1f}x | "
                    f"{f'{diff:.1e}' if batch else ''} |"
                )
    print("\n".join(lines))
    plot(args.plot, rows)
    print(f"\nplot: {args.plot}")


if __name__ == "__main__":
    main()
