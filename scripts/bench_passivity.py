#!/usr/bin/env python3
"""What the passivity controller buys and costs on asymmetric renderings explored in loops.

A ``sim`` finger (hapticd_drivers.sim.Hand: a 50 g fingertip pulled by the hand's
spring-damper, 300 N/m and 3 N s/m, feeling the rendered force) goes from rest
outside, into the object, round a circle of radius r a number of times the way
the rendering delivers energy, and back out to rest: a closed path. Two scenes:

(a) the seed's tilted wall (hapticd.analysis.examples.tilted_wall, 30 deg,
    60 N/m, one actuator), loops in the plane of the wall's normal and the
    actuator, centred 2.5 mm deep;
(b) the two-finger grasp of configs/grasp-stiffness.yaml with the pinv
    allocator, each finger looping in the x-z plane on its face, 2 mm deep.

For each, with the controller off and on (the profile's defaults:
``rendering.passivity``): the energy the display injects into the fingers per
loop, exactly as the held (zero-order hold) force does work on the finger,
sum_n f(n) . (x(n+1) - x(n)); the same as the passivity observer counts it,
-sum_n f(n) . (x(n) - x(n-1)); the lowest observed energy with the controller;
what the controller costs in displayed force (RMS over the ticks in contact of
the damping force it adds, i.e. of the difference to the rendering it
received, in N and relative to that rendering's RMS); and its cost per tick
(the renderer's tick with and without the stage on the same positions, and the
stage alone; medians and p99 over interleaved rounds).

Usage: python scripts/bench_passivity.py [--rounds 10] [--loops 6] [--plot docs/img/passivity.png]
(the plot goes to the temp directory unless --plot says where).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from hapticd_drivers.sim import Hand

from hapticd.analysis import examples
from hapticd.daemon.build import build_renderer
from hapticd.physics.passivity import PassivityParams
from hapticd.physics.render import Renderer
from hapticd.profile import PassivityConfig, load_profile

ROOT = Path(__file__).resolve().parent.parent
GRASP = ROOT / "configs" / "grasp-stiffness.yaml"
DT = 1e-3
PERIOD_S = 0.5  # one loop
REST_S, MOVE_S = 0.1, 0.3  # at rest outside, then the move in (and the same out)
DEFAULTS = PassivityConfig()
PARAMS = PassivityParams(DEFAULTS.velocity_threshold_m_per_s, DEFAULTS.max_damping_n_s_per_m)


class LoopPath:
    """The hand's path for one finger (the ``path`` of a sim Hand): rest at ``outside``, a
    smooth move to the circle's start, ``loops`` times round the circle of ``radius`` (m)
    about ``center`` from ``e1`` toward ``e2``, the same move back out, rest."""

    def __init__(self, center, e1, e2, radius: float, outside, loops: int) -> None:
        self.center, self.e1, self.e2 = (np.asarray(v, dtype=float) for v in (center, e1, e2))
        self.radius, self.loops = radius, loops
        self.outside = np.asarray(outside, dtype=float)
        self.start = self.center + radius * self.e1
        self.t_loops = REST_S + MOVE_S
        self.t_out = self.t_loops + loops * PERIOD_S
        self.duration = self.t_out + MOVE_S + REST_S

    def at(self, t: float) -> tuple[tuple[float, ...], tuple[float, float, float]]:
        if t < REST_S or t >= self.t_out + MOVE_S:
            p = self.outside
        elif t < self.t_loops:
            s = (t - REST_S) / MOVE_S
            p = self.outside + s * s * (3 - 2 * s) * (self.start - self.outside)
        elif t < self.t_out:
            ph = 2 * math.pi * (t - self.t_loops) / PERIOD_S
            p = self.center + self.radius * (math.cos(ph) * self.e1 + math.sin(ph) * self.e2)
        else:
            s = (t - self.t_out) / MOVE_S
            p = self.start + s * s * (3 - 2 * s) * (self.outside - self.start)
        return tuple(p.tolist()), (0.0, 0.0, 0.0)  # the hand's own velocity is not used


@dataclass
class Scene:
    name: str
    make: object  # (passivity params or None) -> Renderer
    paths: list[LoopPath]
    directions: list[np.ndarray] = field(default_factory=list)  # for the plot's labels


def wall_scene(loops: int) -> Scene:
    w = examples.tilted_wall(math.radians(30.0), k=60.0)
    pipe = w.pipeline

    def make(params: PassivityParams | None) -> Renderer:
        return Renderer(pipe.scene, [0.0], pipe.actuation, "pinv", passivity=params, dt=DT)

    # The wall is the plane y = 0, its normal +y; the actuator is tilted 30 deg toward +x.
    # Round from +x toward +y the rendered force's work is k sin cos per unit area > 0.
    path = LoopPath((0.0, -0.0025, 0.0), (1, 0, 0), (0, 1, 0), 0.002, (0.002, 0.005, 0.0), loops)
    return Scene("tilted wall, 1 actuator", make, [path])


def grasp_scene(loops: int) -> Scene:
    prof = load_profile(GRASP)

    def make(params: PassivityParams | None) -> Renderer:
        r = build_renderer(prof)
        return Renderer(
            r.scene,
            r.radii,
            r.actuation,
            "pinv",
            robust=r.allocator.robust,
            adaptive=r.allocator.adaptive,
            dt=r.dt,
            passivity=params,
        )

    # Faces at x = -+33 mm for the fingertip centres; each actuator 30 deg up from the grasp
    # line. Active ways round: the thumb from +x toward -z, the index from +x toward +z.
    thumb = LoopPath((-0.031, 0, 0), (1, 0, 0), (0, 0, -1), 0.0015, (-0.045, 0, 0), loops)
    index = LoopPath((0.031, 0, 0), (1, 0, 0), (0, 0, 1), 0.0015, (0.045, 0, 0), loops)
    return Scene("grasp, pinv, 1 actuator per finger", make, [thumb, index])


def simulate(scene: Scene, params: PassivityParams | None) -> dict[str, np.ndarray]:
    """One closed exploration on sim hands; per tick: positions, the force the stage received
    and the force displayed, observed energy and damping."""
    r = scene.make(params)
    stage_in = np.zeros_like(r.frame.rendered_force)
    if params is not None:
        stage = r.passivity
        run = stage.run

        def tapped(frame, _run=run) -> None:
            stage_in[...] = frame.rendered_force
            _run(frame)

        stage.run = tapped  # type: ignore[method-assign]
    hands = [Hand(p, 0.05, 300.0, 3.0) for p in scene.paths]
    n = round(scene.paths[0].duration / DT)
    F = len(hands)
    out = {k: np.zeros((n, F, 3)) for k in ("x", "v", "f_in", "f_out")} | {
        k: np.zeros((n, F)) for k in ("energy", "damping", "contact")
    }
    force = [(0.0, 0.0, 0.0)] * F
    x = np.zeros((F, 3))
    v = np.zeros((F, 3))
    for k in range(n):
        for i, h in enumerate(hands):
            h.advance(k * DT, force[i])
            x[i], v[i] = h.x, h.v
        fr = r.step(x, v)
        out["x"][k], out["v"][k] = x, v
        out["f_out"][k] = fr.rendered_force
        out["f_in"][k] = stage_in if params is not None else fr.rendered_force
        out["energy"][k] = fr.passivity_energy
        out["damping"][k] = fr.passivity_damping
        out["contact"][k] = fr.in_contact
        force = [tuple(f) for f in fr.rendered_force.tolist()]
    return out


def energies(run: dict[str, np.ndarray], loops: int) -> dict[str, float]:
    """Injected energy per loop (J): exact for the held force, and as the observer counts."""
    f, x = run["f_out"], run["x"]
    dx = np.diff(x, axis=0)
    exact = float(np.sum(f[:-1] * dx))  # f(n) held while the finger moves to x(n+1)
    observed = float(np.sum(f[1:] * dx))  # f(n) with the motion into tick n
    return {"exact": exact / loops, "observed": observed / loops}


def time_ticks(scene: Scene, positions: np.ndarray, rounds: int) -> dict[str, list[float]]:
    """Per-tick times (s) of the renderer without and with the stage on the same positions,
    and of the stage alone (a third run, its stage wrapped in a timer); rounds interleaved."""
    times: dict[str, list[float]] = {"off": [], "on": [], "stage": []}
    clock = time.perf_counter
    for _ in range(rounds):
        for variant in ("off", "on", "stage"):
            r = scene.make(None if variant == "off" else PARAMS)
            ticks = times[variant]
            if variant == "stage":
                stage = r.passivity
                run = stage.run

                def timed(frame, _run=run, _acc=ticks) -> None:
                    t0 = clock()
                    _run(frame)
                    _acc.append(clock() - t0)

                stage.run = timed  # type: ignore[method-assign]
            frame = r.frame
            prev = positions[0]
            for x in positions:
                frame.device_pos[:] = x
                frame.device_vel[:] = (x - prev) / DT
                prev = x
                t0 = clock()
                r.run(frame)
                if variant != "stage":
                    ticks.append(clock() - t0)
    return times


def q(ts: list[float], p: float) -> float:
    s = sorted(ts)
    return s[min(len(s) - 1, int(p / 100 * len(s)))] * 1e6


def plot(path: Path, results: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, len(results), figsize=(6.2 * len(results), 9.0), squeeze=False)
    for col, res in enumerate(results):
        off, on = res["off"], res["on"]
        t = np.arange(off["x"].shape[0]) * DT
        ax = axes[0, col]
        for run, label, color in ((off, "off", "tab:red"), (on, "on", "tab:blue")):
            dx = np.diff(run["x"], axis=0)
            w = np.concatenate([[0.0], np.cumsum(np.sum(run["f_out"][:-1] * dx, axis=(1, 2)))])
            ax.plot(t, w * 1e3, color=color, label=f"controller {label}")
        ax.set_ylabel("energy injected so far (mJ)")
        ax.set_title(res["name"])
        ax.legend(loc="upper left", fontsize=8)
        ax = axes[1, col]
        ax.plot(t, on["energy"].sum(axis=1) * 1e3, color="tab:blue", label="controller on")
        dx = np.diff(off["x"], axis=0, prepend=off["x"][:1])
        obs_off = -np.cumsum(np.sum(off["f_out"] * dx, axis=(1, 2)))
        ax.plot(t, obs_off * 1e3, color="tab:red", label="controller off")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylabel("observed energy, all fingers (mJ)\n(< 0: the display generated it)")
        ax.legend(loc="lower left", fontsize=8)
        ax = axes[2, col]
        for i in range(on["damping"].shape[1]):
            ax.plot(t, on["damping"][:, i], lw=0.8, label=f"finger {i}")
        ax.axhline(PARAMS.max_damping, color="k", ls="--", lw=0.6, label="max damping")
        ax.set_ylabel("added damping (N s/m)")
        ax.set_xlabel("time (s)")
        ax.legend(loc="upper right", fontsize=8)
        for ax in axes[:, col]:
            ax.grid(True, alpha=0.3)
    fig.suptitle(
        "Passivity controller on a sim finger exploring closed loops "
        f"(threshold {PARAMS.velocity_threshold:g} m/s, max damping {PARAMS.max_damping:g} N s/m)"
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def main() -> None:
    ap = argparse.ArgumentParser(description="Passivity controller: energy, force error, time.")
    ap.add_argument("--rounds", type=int, default=10, help="interleaved timing rounds")
    ap.add_argument("--loops", type=int, default=6, help="loops per exploration")
    ap.add_argument(
        "--plot",
        type=Path,
        default=Path(tempfile.gettempdir()) / "hapticd-bench-passivity.png",
        help="where to save the plot (default: the temp directory)",
    )
    args = ap.parse_args()

    results = []
    for scene in (wall_scene(args.loops), grasp_scene(args.loops)):
        off = simulate(scene, None)
        on = simulate(scene, PARAMS)
        e_off, e_on = energies(off, args.loops), energies(on, args.loops)
        touching = on["contact"].astype(bool)
        added = on["f_out"] - on["f_in"]
        rms_added = float(np.sqrt(np.mean(np.sum(added[touching] ** 2, axis=1))))
        rms_in = float(np.sqrt(np.mean(np.sum(on["f_in"][touching] ** 2, axis=1))))
        times = time_ticks(scene, on["x"], args.rounds)
        results.append(
            {
                "name": scene.name,
                "off": off,
                "on": on,
                "e_off": e_off,
                "e_on": e_on,
                "min_energy": float(on["energy"].min()),
                "rms_added": rms_added,
                "rms_in": rms_in,
                "acting": float(np.mean(on["damping"][touching] > 0)),
                "times": times,
            }
        )

    print(
        f"passivity controller: threshold {PARAMS.velocity_threshold:g} m/s, max damping "
        f"{PARAMS.max_damping:g} N s/m; {args.loops} loops of {PERIOD_S:g} s on sim fingers "
        f"(50 g, hand 300 N/m, 3 N s/m); timing: {args.rounds} rounds\n"
    )
    print(
        "| scene | injected per loop, off (J) | injected per loop, on (J) | on / off | "
        "observed per loop, off / on (J) | lowest observed energy, on (J) | "
        "added force RMS (N) | relative | ticks acting |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        eo, en = r["e_off"], r["e_on"]
        print(
            f"| {r['name']} | {eo['exact']:.3g} | {en['exact']:.3g} | "
            f"{en['exact'] / eo['exact']:.3f} | {eo['observed']:.3g} / {en['observed']:.2g} | "
            f"{r['min_energy']:.3g} | {r['rms_added']:.3g} | "
            f"{r['rms_added'] / r['rms_in']:.3f} | {100 * r['acting']:.0f} % |"
        )
    print()
    print(
        "| scene | tick off median / p99 (us) | tick on median / p99 (us) | on / off median | "
        "on / off p99 | stage alone median / p99 (us) |"
    )
    print("|---|---|---|---|---|---|")
    for r in results:
        t = r["times"]
        print(
            f"| {r['name']} | {q(t['off'], 50):.1f} / {q(t['off'], 99):.1f} | "
            f"{q(t['on'], 50):.1f} / {q(t['on'], 99):.1f} | "
            f"{q(t['on'], 50) / q(t['off'], 50):.2f} | {q(t['on'], 99) / q(t['off'], 99):.2f} | "
            f"{q(t['stage'], 50):.1f} / {q(t['stage'], 99):.1f} |"
        )
    plot(args.plot, results)
    print(f"\nplot: {args.plot}")


if __name__ == "__main__":
    main()
