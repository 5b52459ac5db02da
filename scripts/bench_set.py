#!/usr/bin/env python3
"""What a live ``set`` costs the servo tick: a plain tick against a tick that applies a set.

Each run builds the real loop (``hapticd.daemon.session.build_session``: the
profile's replay devices, renderer and safety chain) in a subprocess of its own
and runs it unpaced (as fast as it can, on the nominal clock), without
real-time settings or a recording. Every ``--every``-th tick a control command
is submitted just before the tick, in turn for each case, from the loop's own
thread (``--submit-in thread``: from a client thread, as the control server's,
the loop waiting for it without the GIL; the GIL's hand-over is then timed too):

- numbers: stiffness, damping, mass, friction (lift: its profile has friction),
  force limit, each between its profile's value and a second one;
- structural: the allocator (between two), the actuated directions (tilted and
  back) and, on grasp (no friction in its profile), friction on and off.

Each tick is timed with perf_counter_ns around ``ServoLoop._tick`` (read,
apply the inbox, render, safety, write): the ticks that applied a command per
case, and the plain ticks halfway between (``tick``). ``submit`` is the time
``ServoLoop.submit`` took in the caller's thread (in a tree that prepares a
change there, its preparation). A case whose command failed is reported.

``--compare DIR``: the hapticd package in DIR (e.g. a clone of main at an older
commit) in the same interleaved rounds as this tree's: medians over rounds of
each run's p50 and p99, per case, and the ratios old/new.

    python scripts/bench_set.py --rounds 3
    python scripts/bench_set.py --compare /tmp/hapticd-before --rounds 3
    python scripts/bench_set.py --compare /tmp/hapticd-before --kernels python  # uncompiled

Prints a Markdown table and saves a plot in the system temp dir unless --plot PATH.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROFILES = ("grasp-stiffness", "lift-weight")
DEFAULT_PLOT = Path(tempfile.gettempdir()) / "hapticd-bench-set.png"
NUMBERS = ("stiffness", "damping", "mass", "friction", "force limit")
STRUCTURAL = ("allocator", "actuation", "friction on/off")


def _pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))] if s else float("nan")


# -- the child: one run of the loop in this process ---------------------------------------


def _cases(loop: object, profile: str) -> dict[str, tuple[str, list[object]]]:
    """Each case's parameter and the values it alternates between (the first: the
    profile's own)."""
    p = loop.param  # type: ignore[attr-defined]
    k, b, m = p("stiffness_n_per_m"), p("damping_n_s_per_m"), p("mass_kg")
    limit = max(p("force_limit_n"))
    mu = p("friction")
    dirs = p("actuated_directions")
    # Each finger's directions tilted a little about the y axis (normalised by the spec).
    tilted = [[[d[0] + 0.05, d[1], d[2] - 0.05] for d in ds] for ds in dirs]
    methods = ("if", "pinv") if p("allocator") == "if" else (p("allocator"), "if")
    cases: dict[str, tuple[str, list[object]]] = {
        "stiffness": ("stiffness_n_per_m", [k, k * 1.25]),
        "damping": ("damping_n_s_per_m", [b, b + 0.25]),
        # A fixed object's mass is 0 in its profile: any two in the range.
        "mass": ("mass_kg", [m, m * 1.25] if m > 0 else [0.1, 0.125]),
        "force limit": ("force_limit_n", [limit, limit * 0.75]),
        "allocator": ("allocator", list(methods)),
        "actuation": ("actuated_directions", [dirs, tilted]),
    }
    if mu[0] > 0:
        cases["friction"] = ("friction", [list(mu), [mu[0] * 0.9, mu[1] * 0.9]])
    else:
        cases["friction on/off"] = ("friction", [list(mu), [0.8, 0.6]])
    del profile
    return cases


def child(args: argparse.Namespace) -> dict:
    """One run; returns each case's tick times (p50, p99, us), submit times and failures."""
    import queue
    import threading
    import time

    import yaml

    from hapticd.daemon.session import build_session
    from hapticd.loop.commands import SetParam
    from hapticd.params import PARAMS
    from hapticd.profile import parse_profile

    path = ROOT / "configs" / f"{args.profile}.yaml"
    data = yaml.safe_load(path.read_text())
    data["loop"]["realtime"] = {"enabled": False}
    if args.kernels is not None:
        data.setdefault("rendering", {})["kernels"] = args.kernels
    data.setdefault("safety", {})["watchdog_s"] = None  # unpaced on a loaded machine
    profile = parse_profile(data, path)
    cases = _cases(build_session(profile, paced=False, duration_s=0.001).loop, args.profile)
    names = list(cases)
    ticks = args.warmup + args.samples * len(names) * args.every
    session = build_session(profile, paced=False, duration_s=ticks / profile.loop.rate_hz)
    loop = session.loop
    loop.end_with_trajectory = False  # the replay holds its last sample: ticks go on
    ns = time.perf_counter_ns
    times: dict[str, list[int]] = {name: [] for name in ["tick", *names]}
    submit: dict[str, list[int]] = {name: [] for name in names}
    failed: dict[str, str] = {}
    turn = [0] * len(names)
    tick = loop._tick
    half = args.every // 2
    requests: queue.SimpleQueue = queue.SimpleQueue()
    submitted = threading.Event()
    box: list = [None, 0]

    def client() -> None:
        while (cmd := requests.get()) is not None:
            t0 = ns()
            try:
                box[0] = loop.submit(cmd)
            finally:
                box[1] = ns() - t0
                submitted.set()

    def hand_over(cmd: SetParam) -> tuple[object, int]:
        if args.submit_in == "loop":
            t0 = ns()
            return loop.submit(cmd), ns() - t0
        submitted.clear()
        requests.put(cmd)
        submitted.wait()
        return box[0], box[1]

    def timed_tick(k: int, t: float, start: float) -> None:
        j = k - args.warmup
        which = None
        done = None
        if j >= 0 and j % args.every == 0:
            i = (j // args.every) % len(names)
            which = names[i]
            param, values = cases[which]
            turn[i] += 1
            value = PARAMS[param].check(values[turn[i] % len(values)])
            done, took = hand_over(SetParam(param, value))
            submit[which].append(took)
        t0 = ns()
        tick(k, t, start)
        dt = ns() - t0
        if which is not None:
            times[which].append(dt)
            if done is not None and done.error is not None:
                failed.setdefault(which, done.error)
        elif j >= 0 and j % args.every == half:
            times["tick"].append(dt)

    loop._tick = timed_tick  # type: ignore[method-assign]
    worker = threading.Thread(target=client, name="client", daemon=True)
    worker.start()
    try:
        st = loop.run()
    finally:
        requests.put(None)
        worker.join(timeout=10)
    fault = None if loop.safety.fault is None else loop.safety.fault.cause

    def us(v: list[int]) -> tuple[float, float]:
        x = [n / 1e3 for n in v]
        return (_pct(x, 0.5), _pct(x, 0.99))

    return {
        "ticks": st.ticks,
        "fault": fault,
        "failed": failed,
        "tick": {name: us(v) for name, v in times.items()},
        "submit": {name: us(v) for name, v in submit.items()},
    }


def run_child(tree: Path | None, **kw: object) -> dict:
    """Run one case in a subprocess, on the hapticd package in ``tree`` (None: this one)."""
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = f"{tree}:{tree / 'drivers_root'}"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child"]
    for k, v in kw.items():
        if v is True:
            cmd.append(f"--{k.replace('_', '-')}")
        elif v is not False and v is not None:
            cmd += [f"--{k.replace('_', '-')}", str(v)]
    cwd = tree if tree is not None else ROOT
    res = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True, timeout=900)
    if res.returncode != 0:
        raise RuntimeError(f"{cmd} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def med(xs: list[float]) -> float:
    return statistics.median(xs) if xs else float("nan")


def compare(args: argparse.Namespace) -> list[dict]:
    """This tree (and DIR's, with ``--compare``) in interleaved rounds; one table."""
    variants: dict[str, Path | None] = {}
    if args.compare:
        old = Path(args.compare).resolve()
        if not (old / "hapticd" / "__init__.py").is_file():
            raise SystemExit(f"--compare {old}: no hapticd package there")
        if (old / "drivers").is_dir():  # hapticd_drivers lives in drivers/: an importable name
            shim = old / "drivers_root"
            if not (shim / "hapticd_drivers").exists():
                shim.mkdir(exist_ok=True)
                (shim / "hapticd_drivers").symlink_to(old / "drivers")
        variants["old"] = old
    variants["new"] = None
    results: dict[tuple[str, str], list[dict]] = {}
    for rnd in range(args.rounds):
        for profile in PROFILES:
            for name, tree in variants.items():
                out = run_child(
                    tree,
                    profile=profile,
                    kernels=args.kernels,
                    samples=args.samples,
                    every=args.every,
                    warmup=args.warmup,
                    submit_in=args.submit_in,
                )
                results.setdefault((profile, name), []).append(out)
                tick = out["tick"]
                line = " ".join(f"{c} {v[0]:.1f}/{v[1]:.1f}" for c, v in tick.items())
                print(f"round {rnd + 1}: {profile} {name}: p50/p99 us: {line}", file=sys.stderr)
                for case, why in out["failed"].items():
                    print(f"  {name} {profile} {case} FAILED: {why}", file=sys.stderr)
                if out["fault"]:
                    print(f"  {name} {profile} fault: {out['fault']}", file=sys.stderr)
    names = list(variants)
    first = names[0]
    print(
        f"\n### servo-thread tick with a set, us (median over {args.rounds} rounds of each "
        f"run's p50 / p99; {args.samples} sets per case a run; kernels: "
        f"{args.kernels}; submitted from {args.submit_in}; "
        + "; ".join(f"{n}: {t or 'this tree'}" for n, t in variants.items())
        + ")\n"
    )
    head = ["profile", "case"]
    head += [f"{n} p50" for n in names] + [f"{n} p99" for n in names]
    head += [f"{first}/{n} p99" for n in names[1:]]
    head += [f"{n} submit p50" for n in names] + ["failed"]
    print("| " + " | ".join(head) + " |")
    print("|---" * len(head) + "|")
    rows = []
    for profile in PROFILES:
        cases = list(results[(profile, names[-1])][0]["tick"])
        for case in cases:
            p50, p99, sub = {}, {}, {}
            for n in names:
                rs = results[(profile, n)]
                p50[n] = med([r["tick"][case][0] for r in rs if case in r["tick"]])
                p99[n] = med([r["tick"][case][1] for r in rs if case in r["tick"]])
                sub[n] = med([r["submit"][case][0] for r in rs if case in r.get("submit", {})])
            fails = sorted({n for n in names for r in results[(profile, n)] if case in r["failed"]})
            cells = [profile, case]
            cells += [f"{p50[n]:.1f}" for n in names] + [f"{p99[n]:.1f}" for n in names]
            cells += [f"{p99[first] / p99[n]:.1f}" for n in names[1:]]
            cells += ["-" if case == "tick" else f"{sub[n]:.1f}" for n in names]
            cells.append(", ".join(fails) or "-")
            print("| " + " | ".join(cells) + " |")
            rows.append({"profile": profile, "case": case, "p50": p50, "p99": p99})
    return rows


def plot(path: Path, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4))
    labels = [f"{r['profile'].split('-')[0]}\n{r['case']}" for r in rows]
    names = list(rows[0]["p50"])
    x = range(len(rows))
    w = 0.8 / (2 * len(names))
    bars = [(n, q) for q in ("p50", "p99") for n in names]
    for j, (n, q) in enumerate(bars):
        off = (j - (len(bars) - 1) / 2) * w
        ax.bar([i + off for i in x], [r[q][n] for r in rows], w, label=f"{n} {q}")
    ax.axhline(125.0, color="grey", lw=0.8, ls="--", label="8 kHz budget (125 us)")
    ax.set_xticks(list(x), labels, fontsize=7)
    ax.set_ylabel("servo-thread tick, us")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"\nplot: {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--compare", metavar="DIR", help="a tree with another hapticd package")
    ap.add_argument(
        "--kernels",
        choices=("python", "compiled", "auto"),
        default="compiled",
        help="rendering.kernels for every tree (compiled: loaded or compiled before the run)",
    )
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--samples", type=int, default=400, help="sets per case a run")
    ap.add_argument("--every", type=int, default=6, help="ticks from one set to the next")
    ap.add_argument("--warmup", type=int, default=500, help="ticks before the first set")
    ap.add_argument(
        "--submit-in",
        choices=("thread", "loop"),
        default="loop",
        help="where a command is submitted: the loop's own thread, just before its tick "
        "(default), or a client thread (the control server's place; the GIL's hand-over "
        "then is in the tick too)",
    )
    ap.add_argument("--plot", type=Path, default=DEFAULT_PLOT)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--profile", default="lift-weight", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args)))
        return
    plot(args.plot, compare(args))


if __name__ == "__main__":
    main()
