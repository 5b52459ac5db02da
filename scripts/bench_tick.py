#!/usr/bin/env python3
"""Where a servo tick's time goes, and how fast this tree's tick is against another tree's.

Every case runs the real loop (``hapticd.daemon.session.build_session``: the
profile's replay devices, renderer, safety chain and, with ``--record``, the
recorder and its writer process) in a subprocess of its own, unpaced (as fast as
it can, on the nominal clock) or paced at a given rate, without real-time
settings.

``--profile-stages``: each part of a tick (device read, the renderer's one call,
its Python stages, safety, device write, the loop's own bookkeeping, recording) timed with
perf_counter_ns on every tick: median and p99 per part, unpaced and paced, and
the ratio paced/unpaced. The timers cost ~0.1 us per part, so the parts' sum is
a little above an untimed tick. Besides the loop's own pacing (sleep until 200 us
before the deadline, spin the rest) it paces with a 600 us spin (a shorter
sleep) and by spinning the whole period (no sleep): does the slower tick after a
sleep come from the sleep? Every mode runs the same ticks (``--seconds`` of the
bundled trajectory).

``--compare DIR``: the tick compute time (the loop's own ``compute_s``: read,
render, safety, write, statistics) of the hapticd package in DIR (e.g. main's,
``git archive main | tar -x -C /tmp/hapticd-main``) against this tree's, in
interleaved rounds, unpaced and paced at 1, 4 and 8 kHz, next to a bare deadline
wait with no work (the machine's floor for overruns): medians over rounds of the
runs' p50 and p99, and the ratios old/new. ``--compare-kernels``: the same table for
this tree's Python code (``rendering.kernels=python``) against its compiled
kernels (``compiled``); with ``--compare DIR`` too, three variants in one run
(DIR's tree, python, compiled: before and after in one table). ``--kernels MODE``
sets this tree's rendering.kernels otherwise; DIR's tree runs its own defaults.

    python scripts/bench_tick.py --profile-stages --rounds 3
    python scripts/bench_tick.py --compare /tmp/hapticd-main --rounds 5
    python scripts/bench_tick.py --compare-kernels --rounds 5
    python scripts/bench_tick.py --compare /tmp/hapticd-before --compare-kernels --rounds 3
    python scripts/bench_tick.py --profile-stages --kernels compiled
    python scripts/bench_tick.py --fingers 2 3 5 --rounds 3
    python scripts/bench_tick.py --fingers 2 3 --directions 1 2 3 --against /tmp/hapticd-main

Prints Markdown tables and saves a plot in the system temp dir unless --plot PATH.
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
DEFAULT_PLOT = Path(tempfile.gettempdir()) / "hapticd-bench-tick.png"


# -- the child: one run of the loop in this process ---------------------------------------


def _pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))] if s else float("nan")


def child(args: argparse.Namespace) -> dict:
    """One run; returns per-part and compute times in us."""
    import time

    import yaml

    from hapticd.daemon.session import build_session
    from hapticd.profile import parse_profile

    path = ROOT / "configs" / f"{args.profile}.yaml"
    data = yaml.safe_load(path.read_text())
    data.setdefault("loop", {})["rate_hz"] = args.rate
    data["loop"]["realtime"] = {"enabled": False}
    if args.kernels is not None:
        data.setdefault("rendering", {})["kernels"] = args.kernels
    # A loaded machine can stall an unpaced run's recording for 0.1 s: not what is measured.
    data.setdefault("safety", {})["watchdog_s"] = None
    profile = parse_profile(data, path)
    tmp = tempfile.mkdtemp(prefix="hapticd-bench-tick-")
    record = os.path.join(tmp, "run.hrec") if args.record else None
    session = build_session(
        profile,
        paced=args.paced,
        duration_s=args.seconds,  # the same ticks paced and unpaced
        record_path=record,
    )
    loop = session.loop
    compute: list[float] = []
    pacer = loop.pacer
    end = pacer.end

    def timed_end(k: int, start: float) -> float:
        c = end(k, start)
        compute.append(c)
        return c

    pacer.end = timed_end  # type: ignore[method-assign]
    if args.wait == "spin":
        pacer.margin = pacer.period  # never sleeps: spins the whole period
    elif args.margin_us is not None:
        pacer.margin = min(args.margin_us * 1e-6, pacer.period)  # a shorter sleep
    parts: dict[str, list[int]] = {}
    if args.instrument:
        ns = time.perf_counter_ns

        def wrap(obj: object, attr: str, name: str) -> None:
            fn = getattr(obj, attr)
            acc = parts.setdefault(name, [])

            def timed(*a: object, _fn=fn, _acc=acc) -> object:
                t0 = ns()
                out = _fn(*a)
                _acc.append(ns() - t0)
                return out

            setattr(obj, attr, timed)

        wrap(loop.bank, "read", "device read")
        # The plan's one call (physics and the safety chain's normal tick), and the stages
        # it runs in Python between its parts (none in the bundled profiles); the chain's own
        # run only on ticks it takes back.
        wrap(loop.renderer.one_call, "run", "one call (renderer + safety)")
        for part in loop.renderer.one_call._parts:
            if not isinstance(part, tuple):
                wrap(part, "run", f"stage {part.name}")
        wrap(loop.safety, "run", "safety")
        wrap(loop.bank, "write", "device write")
        tick = loop._tick
        acc = parts.setdefault("tick (read..write)", [])

        def timed_tick(k: int, t: float, start: float) -> None:
            t0 = ns()
            tick(k, t, start)
            acc.append(ns() - t0)

        loop._tick = timed_tick  # type: ignore[method-assign]
        if loop.recorder is not None:
            wrap(loop.recorder, "append", "recording")
        begin = pacer.begin
        late = parts.setdefault("wake-up late", [])

        def timed_begin(k: int) -> tuple[float, str | None]:
            out = begin(k)
            if pacer.paced:
                late.append(int((out[0] - (pacer.t0 + k * pacer.period)) * 1e9))
            return out

        pacer.begin = timed_begin  # type: ignore[method-assign]
    try:
        st = loop.run()
    finally:
        if session.recorder is not None:
            session.recorder.close()
    skip = min(len(compute) // 10, 200)  # the first ticks warm caches up
    us = [c * 1e6 for c in compute[skip:]]
    out = {
        "ticks": st.ticks,
        "overruns": st.overruns,
        "fault": None if loop.safety.fault is None else loop.safety.fault.cause,
        "compute_p50": _pct(us, 0.5),
        "compute_p99": _pct(us, 0.99),
        "period_err_p99": st.period_error.percentile(99.0) * 1e6,
        "parts": {
            name: (_pct([x / 1e3 for x in v[skip:]], 0.5), _pct([x / 1e3 for x in v[skip:]], 0.99))
            for name, v in parts.items()
            if v
        },
    }
    return out


BARE = r"""
import gc, json, sys, time
rate, seconds = float(sys.argv[1]), float(sys.argv[2])
T = 1.0 / rate
margin = min(200e-6, 0.5 * T)
n = int(seconds * rate)
gc.freeze(); gc.disable()
t0 = time.monotonic() + 2e-3
prev = None
over = 0
errs = []
for k in range(n):
    d = t0 + k * T
    r = d - time.monotonic()
    if r > margin:
        time.sleep(r - margin)
    while time.monotonic() < d:
        pass
    s = time.monotonic()
    if prev is not None:
        errs.append(abs(s - prev - T))
        over += s - prev > 1.1 * T
    prev = s
errs.sort()
p99 = errs[int(0.99 * len(errs))] * 1e6
print(json.dumps({"overruns": over, "ticks": n, "period_err_p99": p99}))
"""


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
    # In the tree's folder: the recorder's writer (python -m) imports from its cwd first.
    cwd = tree if tree is not None else ROOT
    res = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True, timeout=600)
    if res.returncode != 0:
        raise RuntimeError(f"{cmd} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def run_bare(rate: float, seconds: float) -> dict:
    res = subprocess.run(
        [sys.executable, "-c", BARE, str(rate), str(seconds)],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return json.loads(res.stdout)


def med(xs: list[float]) -> float:
    return statistics.median(xs) if xs else float("nan")


# -- the breakdown --------------------------------------------------------------------------


def profile_stages(args: argparse.Namespace) -> list[dict]:
    cases = []
    for profile in PROFILES:
        for label, paced, wait, margin in (
            ("unpaced", False, "sleep", None),
            ("paced 1 kHz", True, "sleep", None),
            ("paced 1 kHz, spin 600 us", True, "sleep", 600),
            ("paced 1 kHz, spin all", True, "spin", None),
        ):
            cases.append((profile, label, paced, wait, margin))
    runs: dict[tuple[str, str], list[dict]] = {(c[0], c[1]): [] for c in cases}
    for r in range(args.rounds):
        for profile, label, paced, wait, margin in cases:
            out = run_child(
                None,
                profile=profile,
                rate=1000,
                paced=paced,
                seconds=args.seconds,
                record=True,
                instrument=True,
                wait=wait,
                margin_us=margin,
                kernels=args.kernels,
            )
            runs[(profile, label)].append(out)
            print(f"round {r + 1}: {profile} {label}: {out['compute_p50']:.1f} us", file=sys.stderr)
    rows = []
    for profile in PROFILES:
        names = list(runs[(profile, "unpaced")][0]["parts"])
        print(f"\n### {profile} (median over {args.rounds} runs of each run's p50 / p99, us)\n")
        labels = [c[1] for c in cases if c[0] == profile]
        head = "| part | " + " | ".join(f"{lb} p50 / p99" for lb in labels)
        print(head + " | " + " | ".join(f"{lb} / unpaced p50" for lb in labels[1:]) + " |")
        print("|---" * (2 * len(labels)) + "|")
        for name in [*names, "compute (loop's compute_s)"]:
            vals = []
            for lb in labels:
                rs = runs[(profile, lb)]
                if name.startswith("compute"):
                    p50 = med([o["compute_p50"] for o in rs])
                    p99 = med([o["compute_p99"] for o in rs])
                elif name in rs[0]["parts"]:
                    p50 = med([o["parts"][name][0] for o in rs])
                    p99 = med([o["parts"][name][1] for o in rs])
                else:
                    p50 = p99 = float("nan")
                vals.append((p50, p99))
            cells = " | ".join(f"{a:.1f} / {b:.1f}" for a, b in vals)
            ratios = " | ".join(f"{v[0] / vals[0][0]:.2f}" for v in vals[1:])
            print(f"| {name} | {cells} | {ratios} |")
            rows.append({"profile": profile, "part": name, "values": vals})
    return rows


# -- old against new ------------------------------------------------------------------------


def compare(args: argparse.Namespace) -> list[dict]:
    """Variants of the tick side by side, in interleaved rounds: another tree's package
    (``--compare DIR``, with its own defaults) against this tree's, and/or this tree's
    Python code against its compiled kernels (``--compare-kernels``); with both, three
    variants (before, python, compiled) in one run. Ratios are against the first."""
    variants: dict[str, tuple[Path | None, str | None]] = {}
    if args.compare:
        old = Path(args.compare).resolve()
        if not (old / "hapticd" / "__init__.py").is_file():
            raise SystemExit(f"--compare {old}: no hapticd package there")
        # hapticd_drivers lived in drivers/ in older trees: give it an importable name.
        if (old / "drivers").is_dir():
            shim = old / "drivers_root"
            if not (shim / "hapticd_drivers").exists():
                shim.mkdir(exist_ok=True)
                (shim / "hapticd_drivers").symlink_to(old / "drivers")
        variants["old"] = (old, None)  # an older tree may not know rendering.kernels
    if args.compare_kernels:
        variants["python"] = (None, "python")
        variants["compiled"] = (None, "compiled")
    else:
        variants["new"] = (None, args.kernels)
    names = list(variants)
    what = "; ".join(
        f"{n}: {tree or 'this tree'}" + (f", rendering.kernels={k}" if k else "")
        for n, (tree, k) in variants.items()
    )
    modes = [("unpaced", False, 1000)] + [(f"paced {r // 1000} kHz", True, r) for r in args.rates]
    results: dict[tuple, list[dict]] = {}
    for rnd in range(args.rounds):
        for profile in PROFILES:
            for label, paced, rate in modes:
                for name, (tree, kernels) in variants.items():
                    out = run_child(
                        tree,
                        profile=profile,
                        rate=rate,
                        paced=paced,
                        seconds=args.seconds,
                        record=True,
                        kernels=kernels,
                    )
                    results.setdefault((profile, label, name), []).append(out)
                    print(
                        f"round {rnd + 1}: {profile} {label} {name}: "
                        f"p50 {out['compute_p50']:.1f} us p99 {out['compute_p99']:.1f} us "
                        f"overruns {out['overruns']}",
                        file=sys.stderr,
                    )
                if paced:
                    results.setdefault(("bare", label, "bare"), []).append(
                        run_bare(rate, args.seconds)
                    )
    first = names[0]
    print(
        f"\n### tick compute, us (median over {args.rounds} rounds of each run's p50 / p99; "
        f"{what})\n"
    )
    head = ["profile", "mode"]
    head += [f"{n} p50" for n in names] + [f"{first}/{n} p50" for n in names[1:]]
    head += [f"{n} p99" for n in names] + [f"{first}/{n} p99" for n in names[1:]]
    head += ["overruns " + " / ".join([*names, "bare"])]
    print("| " + " | ".join(head) + " |")
    print("|---" * len(head) + "|")
    rows = []
    for profile in PROFILES:
        for label, paced, _ in modes:
            runs = {n: results[(profile, label, n)] for n in names}
            p50 = {n: med([x["compute_p50"] for x in r]) for n, r in runs.items()}
            p99 = {n: med([x["compute_p99"] for x in r]) for n, r in runs.items()}
            ov = "-"  # unpaced: no deadlines
            if paced:
                counts = [med([x["overruns"] for x in runs[n]]) for n in names]
                counts.append(med([x["overruns"] for x in results[("bare", label, "bare")]]))
                ov = " / ".join(f"{c:g}" for c in counts)
            cells = [profile, label]
            cells += [f"{p50[n]:.1f}" for n in names]
            cells += [f"{p50[first] / p50[n]:.2f}" for n in names[1:]]
            cells += [f"{p99[n]:.1f}" for n in names]
            cells += [f"{p99[first] / p99[n]:.2f}" for n in names[1:]]
            cells.append(ov)
            print("| " + " | ".join(cells) + " |")
            rows.append({"profile": profile, "mode": label, "p50": p50, "p99": p99})
    return rows


# -- cost against the number of fingers ---------------------------------------------------

FINGERS_CHILD = r"""
import json, sys, time
import numpy as np
from hapticd.physics import jit
from hapticd.allocation.actuation import Actuation
from hapticd.physics.render import Renderer
from hapticd.physics.safety import SafetyChain
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject, Surface

n, ticks, python, k = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "python", int(sys.argv[4])
cube = SceneObject(ConvexShape.box(np.array([0.04] * 3)), Material(400.0, 2.0, 0.6, 0.4, 0.002),
                   np.array([0.0, 0.0, 0.02]), np.eye(3), fixed=False, mass=0.05)
ground = Surface("ground", (0.0, 0.0, 1.0), 0.0, Material(2000.0, 5.0, 0.5, 0.4))
angles = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
# Each finger's first k actuated directions, in the world: toward the cube's centre, up,
# along the cube's side (three: a fully actuated finger).
dirs = [[(float(-np.cos(a)), float(-np.sin(a)), 0.0), (0.0, 0.0, 1.0),
         (float(-np.sin(a)), float(np.cos(a)), 0.0)][:k] for a in angles]
r = Renderer(Scene(cube, [ground], np.array([0.0, 0.0, -9.81]), substeps=2), [0.008] * n,
             Actuation(dirs, "world"), "if", dt=1e-3)
r.use_kernels({} if python else jit.compile_kernels(r.kernel_names))
safety = SafetyChain([8.0] * n, dt=1e-3)
safety.use_kernels({} if python else jit.compile_kernels(SafetyChain.kernel_names))
safety.start(0.0)
frame = r.frame
ns, out, contacts, handed = time.perf_counter_ns, [], [], 0
for k in range(ticks):
    # Fingers close in on the cube, then hold it (every finger in contact).
    rad = 0.035 - 0.012 * min(1.0, k / (ticks / 4))
    frame.device_pos[:, 0] = rad * np.cos(angles)
    frame.device_pos[:, 1] = rad * np.sin(angles)
    frame.device_pos[:, 2] = 0.02
    frame.t[()] = k * 1e-3
    t0 = ns()
    outcome = r.run(frame, safety if safety.ready() else None)
    if outcome is None:
        handed += 1
        safety.run(frame, None)
    else:
        safety.done(outcome, k, k * 1e-3, None)
    out.append(ns() - t0)
    contacts.append(int(frame.in_contact.sum()))
us = np.array(out[ticks // 4:]) / 1e3  # holding: every finger in contact
print(json.dumps({"p50": float(np.median(us)), "p99": float(np.percentile(us, 99)),
                  "contacts": max(contacts), "handed_back": handed,
                  "one_call": r.one_call is not None}))
"""


def fingers(args: argparse.Namespace) -> list[dict]:
    """The renderer's tick with the safety chain's (the one call) against the number of
    fingers holding a free cube on the ground and each finger's number of actuated
    directions (IF), in this tree and, with ``--against DIR``, DIR's: medians over
    interleaved rounds of each run's p50 and p99."""
    trees = [("this", None)] + ([("against", Path(args.against))] if args.against else [])
    cases = [(t, n, k) for t in trees for n in args.fingers for k in args.directions]
    got: dict[tuple, list[dict]] = {(t[0], n, k): [] for t, n, k in cases}
    mode = "python" if args.kernels == "python" else "compiled"
    for rnd in range(args.rounds):
        for (label, tree), n, k in cases:
            env = dict(os.environ)
            if tree is not None:
                env["PYTHONPATH"] = f"{tree}:{tree / 'drivers_root'}"
            res = subprocess.run(
                [sys.executable, "-c", FINGERS_CHILD, str(n), str(args.ticks), mode, str(k)],
                capture_output=True,
                text=True,
                timeout=600,
                cwd=tree or ROOT,
                env=env,
            )
            if res.returncode != 0:
                raise RuntimeError(res.stderr[-2000:])
            got[label, n, k].append(json.loads(res.stdout.strip().splitlines()[-1]))
            p50 = got[label, n, k][-1]["p50"]
            print(f"round {rnd + 1}: {label}: {n} fingers x {k}: {p50:.1f} us", file=sys.stderr)
    print(
        "\n### renderer + safety tick against fingers and directions (a free cube held on "
        f"the ground, IF, {mode}; median over {args.rounds} rounds of each run's p50 / p99, us)\n"
    )
    print("| tree | fingers | directions each | in contact | p50 | p99 | p50 per finger |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for (label, n, k), runs in got.items():
        p50, p99 = med([r["p50"] for r in runs]), med([r["p99"] for r in runs])
        print(
            f"| {label} | {n} | {k} | {runs[-1]['contacts']} | {p50:.1f} | {p99:.1f} | "
            f"{p50 / n:.2f} |"
        )
        rows.append({"tree": label, "fingers": n, "directions": k, "p50": p50, "p99": p99})
    return rows


def plot(path: Path, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4))
    labels = [f"{r['profile']}\n{r['mode']}" for r in rows]
    names = list(rows[0]["p50"])
    x = range(len(rows))
    w = 0.8 / (2 * len(names))
    bars = [(n, q) for q in ("p50", "p99") for n in names]
    for j, (n, q) in enumerate(bars):
        off = (j - (len(bars) - 1) / 2) * w
        ax.bar([i + off for i in x], [r[q][n] for r in rows], w, label=f"{n} {q}")
    ax.set_xticks(list(x), labels, fontsize=7)
    ax.set_ylabel("tick compute, us")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"\nplot: {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--profile-stages", action="store_true", help="the per-part breakdown")
    ap.add_argument("--compare", metavar="DIR", help="a tree with another hapticd package")
    ap.add_argument(
        "--compare-kernels",
        action="store_true",
        help="this tree's rendering.kernels python against compiled (with --compare DIR: "
        "three variants, DIR's tree first)",
    )
    ap.add_argument(
        "--kernels",
        choices=("python", "compiled", "auto"),
        default=None,
        help="rendering.kernels for --profile-stages, --compare and --fingers (python: the one"
        " call uncompiled; default: the profile's, compiled for --fingers)",
    )
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=5.0, help="length of a paced run, s")
    ap.add_argument("--rates", type=int, nargs="+", default=[1000, 4000, 8000])
    ap.add_argument("--plot", type=Path, default=DEFAULT_PLOT)
    ap.add_argument(
        "--fingers",
        type=int,
        nargs="+",
        help="the renderer's and safety's tick against these numbers of fingers",
    )
    ap.add_argument(
        "--directions",
        type=int,
        nargs="+",
        default=[1],
        choices=(1, 2, 3),
        help="with --fingers: each finger's numbers of actuated directions to run",
    )
    ap.add_argument("--against", metavar="DIR", help="with --fingers: another tree, too")
    ap.add_argument("--ticks", type=int, default=4000, help="ticks of a --fingers run")
    # One run (the subprocess's side).
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--profile", default="lift-weight", help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, default=1000.0, help=argparse.SUPPRESS)
    ap.add_argument("--paced", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--record", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--instrument", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--wait", choices=("sleep", "spin"), default="sleep", help=argparse.SUPPRESS)
    ap.add_argument("--margin-us", type=float, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args)))
        return
    if args.profile_stages:
        profile_stages(args)
    if args.compare or args.compare_kernels:
        plot(args.plot, compare(args))
    if args.fingers:
        fingers(args)
    if not (args.profile_stages or args.compare or args.compare_kernels or args.fingers):
        ap.error("give --profile-stages, --compare DIR, --compare-kernels or --fingers N...")


if __name__ == "__main__":
    main()
