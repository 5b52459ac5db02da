#!/usr/bin/env python3
"""What a lab's allocator costs the tick: the built-ins against the example plugin.

The example allocator (examples/plugins/hapticd-allocator-tikhonov) is installed by pip
(offline, no dependencies) into a temporary folder. Each run builds the loop of the lift
profile (``hapticd.daemon.session.build_session``, not running) in a subprocess of its
own, with compiled kernels, and times ``Renderer.run`` (the one call: contact, forces,
allocation, passivity, dynamics) over a squeeze that varies and lifts, both fingers in
contact. Variants, interleaved in each round:

- ``if``, ``pinv``: built-ins, compiled into the call;
- ``tikhonov``: the plugin, compiled (numba) and called by the compiled call;
- ``tikhonov (Python)``: the plugin where numba cannot compile it (the allocation stage
  runs its Python form between the call's compiled parts), forced by hiding the compiler.

    python scripts/bench_allocator_plugin.py --rounds 5

Prints a Markdown table (medians over rounds of each run's p50 and p99, us) and saves a
plot in the system temp dir unless --plot PATH.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "plugins" / "hapticd-allocator-tikhonov"
DEFAULT_PLOT = Path(tempfile.gettempdir()) / "hapticd-bench-allocator-plugin.png"
VARIANTS = ("if", "pinv", "tikhonov", "tikhonov (Python)")


def _pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))]


def child(allocator: str, python_plugin: bool, ticks: int) -> dict:
    """One run: each tick's Renderer.run time (us) after a warm-up, and whether the
    allocation ran in the call."""
    import numpy as np

    from hapticd.allocation import plugins
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile

    if python_plugin:  # no compiler: the plugin's Python form, between the call's parts
        plugins.PLUGIN_COMPILERS = "hapticd.none"
    profile = load_profile(
        ROOT / "configs" / "lift-weight.yaml",
        [
            "rendering.kernels=compiled",
            f"rendering.allocator={allocator}",
            "loop.realtime.enabled=false",
        ],
    )
    loop = build_session(profile, paced=False).loop
    renderer, frame = loop.renderer, loop.frame
    squeeze = np.array([[0.031, 0.0, 0.0], [-0.031, 0.0, 0.0]])
    times = []
    ns = time.perf_counter_ns
    for k in range(ticks + 500):
        s = 0.002 + 0.001 * np.sin(k / 10.0)
        lift = 5e-6 * (k % 2000)
        frame.device_pos[:] = squeeze + np.array([[-s, 0, lift], [s, 0, lift]])
        frame.device_vel[:] = 0.0
        t0 = ns()
        renderer.run(frame)
        dt = ns() - t0
        if k >= 500:
            times.append(dt / 1e3)
    return {
        "p50": _pct(times, 0.5),
        "p99": _pct(times, 0.99),
        "in_call": bool(renderer.one_call._single),
        "contact": bool(frame.in_contact.all()),
    }


def run_child(site: Path, variant: str, ticks: int) -> dict:
    allocator = variant.split()[0]
    env = {**os.environ, "PYTHONPATH": f"{site}:{os.environ.get('PYTHONPATH', '')}"}
    cmd = [sys.executable, __file__, "--child", allocator, "--ticks", str(ticks)]
    if variant.endswith("(Python)"):
        cmd.append("--python-plugin")
    res = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)
    if res.returncode != 0:
        raise RuntimeError(f"{variant}: {res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def plot(path: Path, rows: dict[str, tuple[float, float]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    names = list(rows)
    x = range(len(names))
    ax.bar([i - 0.2 for i in x], [rows[n][0] for n in names], 0.4, label="p50")
    ax.bar([i + 0.2 for i in x], [rows[n][1] for n in names], 0.4, label="p99")
    ax.axhline(125.0, color="grey", lw=0.8, ls="--", label="8 kHz budget (125 us)")
    ax.set_xticks(list(x), names, fontsize=8)
    ax.set_ylabel("Renderer.run, us")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"\nplot: {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--ticks", type=int, default=5000, help="timed ticks a run")
    ap.add_argument("--plot", type=Path, default=DEFAULT_PLOT)
    ap.add_argument("--child", metavar="ALLOCATOR", help=argparse.SUPPRESS)
    ap.add_argument("--python-plugin", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.python_plugin, args.ticks)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        site = Path(tmp)
        subprocess.run(
            [sys.executable, "-m", "pip", "install", "-q", "--disable-pip-version-check",
             "--no-deps", "--no-build-isolation", "--no-index", "--target", str(site),
             str(EXAMPLE)],
            check=True, timeout=300,
        )  # fmt: skip
        results: dict[str, list[dict]] = {v: [] for v in VARIANTS}
        for rnd in range(args.rounds):
            for v in VARIANTS:
                out = run_child(site, v, args.ticks)
                results[v].append(out)
                print(
                    f"round {rnd + 1}: {v}: p50 {out['p50']:.2f} us p99 {out['p99']:.2f} us"
                    f" (in the call: {out['in_call']}, both in contact: {out['contact']})",
                    file=sys.stderr,
                )
    print(
        f"\n### Renderer.run on the lift profile, us (median over {args.rounds} rounds of "
        f"each run's p50 / p99, {args.ticks} ticks a run, compiled kernels)\n"
    )
    print("| allocator | p50 | p99 | allocation in the compiled call |")
    print("|---|---|---|---|")
    rows = {}
    for v, rs in results.items():
        p50 = statistics.median(r["p50"] for r in rs)
        p99 = statistics.median(r["p99"] for r in rs)
        rows[v] = (p50, p99)
        print(f"| {v} | {p50:.2f} | {p99:.2f} | {'yes' if rs[0]['in_call'] else 'no'} |")
    plot(args.plot, rows)


if __name__ == "__main__":
    main()
