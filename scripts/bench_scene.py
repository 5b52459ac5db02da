#!/usr/bin/env python3
"""What scene accuracy costs in time: effect sets, mesh resolutions, integration substeps.

1. Effect sets: one renderer tick (contact ... dynamics) over the bundled lift
   trajectory, from a fixed frictionless cube up to a free cube with friction,
   gravity, ground and walls, with the Python code and with the compiled kernels
   (rendering.kernels; interleaved, the ratio python / compiled). Each effect's
   cost is the difference to the row above; an effect that is off is not in the
   plan and costs nothing.
2. Mesh resolution: a 25 mm sphere as a box-like coarse hull up to ~20k faces:
   tick time against the surface-distance error (how far the hull's faces lie
   inside the true sphere), with the compiled kernels (uncompiled, the contact's
   pass over a mesh's planes is a Python loop: seconds a tick at 20k faces).
3. Substeps 1, 2, 4, 8: the tick's time (its one call, compiled: the free cube's step
   and a finger touching nothing) against energy drift of a free-falling cube (1 s, no
   ground) and the creep of a cube resting on the ground (1 s).

Timings are medians and p99 over repeated runs, interleaved per section.
Usage: python scripts/bench_scene.py [--rounds 3] [--plot PATH]
(the plot goes to the system temp dir unless --plot names a file; the docs'
figure: --plot docs/img/bench-scene.png)
"""

from __future__ import annotations

import argparse
import copy
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from hapticd import recording
from hapticd.allocation.actuation import Actuation
from hapticd.daemon.build import build_scene, builtin_trajectory
from hapticd.physics import jit
from hapticd.physics.render import Renderer
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject, Surface
from hapticd.profile import parse_profile

ROOT = Path(__file__).resolve().parent.parent
# Outside the repository: a run never overwrites the docs' figure unless asked to.
DEFAULT_PLOT = Path(tempfile.gettempdir()) / "hapticd-bench-scene.png"
LIFT = ROOT / "configs" / "lift-weight.yaml"


def renderer_for(data: dict, kernels: str = "python") -> Renderer:
    """The profile ``data``'s renderer, with its compiled kernels when ``kernels`` is
    "compiled" (hapticd.physics.jit; an error if they do not compile)."""
    prof = parse_profile(data, LIFT)
    scene = build_scene(prof.scene, prof)
    r = Renderer(
        scene,
        [f.radius_m for f in prof.fingers],
        Actuation(
            [list(f.actuated_directions) for f in prof.fingers], prof.rendering.actuation_frame
        ),
        prof.rendering.allocator,
        dt=1.0 / prof.loop.rate_hz,
    )
    if kernels == "compiled":
        r.use_kernels(jit.compile_kernels(r.kernel_names))
    return r


# The effect sets run with the Python code and with the compiled kernels (hapticd.physics.kernels).
KERNELS = ("python", "compiled")


def tick_times(r: Renderer, positions: np.ndarray, dt: float) -> list[float]:
    out = []
    prev = positions[0]
    clock = time.perf_counter
    for x in positions:
        v = (x - prev) / dt
        t0 = clock()
        r.step(x, v)
        out.append(clock() - t0)
        prev = x
    return out


def stats(ts: list[float]) -> tuple[float, float]:
    s = sorted(ts)
    return statistics.median(s) * 1e6, s[min(len(s) - 1, int(0.99 * len(s)))] * 1e6


def effect_sets() -> dict[str, dict]:
    base = yaml.safe_load(LIFT.read_text())
    sc = base["scene"]

    def variant(fixed: bool, friction: bool, gravity: bool, ground: bool, walls: bool) -> dict:
        d = copy.deepcopy(base)
        s = d["scene"]
        s["object"]["fixed"] = fixed
        if not friction:
            s["object"]["friction"] = {"static": 0.0, "dynamic": 0.0}
        s["gravity_m_s2"] = sc["gravity_m_s2"] if gravity else None
        if not ground:
            s.pop("ground")
        if not walls:
            s.pop("walls")
        return d

    return {
        "fixed cube, no friction": variant(True, False, False, False, False),
        "fixed cube + friction": variant(True, True, False, False, False),
        "fixed cube + friction + ground + walls": variant(True, True, False, True, True),
        "free cube (dynamics only)": variant(False, False, False, False, False),
        "free cube + gravity + ground": variant(False, False, True, True, False),
        "free cube + friction + gravity + ground + walls": variant(False, True, True, True, True),
    }


def bench_effects(rounds: int) -> list[dict]:
    rec = recording.read(builtin_trajectory("lift-weight"))
    # The trajectory at the loop rate (1 kHz), interpolated like the replay device does.
    t = np.arange(0.0, rec["t"][-1], 1e-3)
    pos = np.stack(
        [
            np.stack([np.interp(t, rec["t"], rec["device_pos"][:, f, k]) for k in range(3)], axis=1)
            for f in range(2)
        ],
        axis=1,
    )
    sets = effect_sets()
    keys = [(name, k) for name in sets for k in KERNELS]
    times: dict[tuple[str, str], list[float]] = {key: [] for key in keys}
    stages: dict[str, list[str]] = {}
    for name, k in keys:
        tick_times(renderer_for(sets[name], k), pos[:200], 1e-3)  # warm-up, not timed
    for _ in range(rounds):
        for name, k in keys:  # interleaved: python and compiled of a set side by side
            r = renderer_for(sets[name], k)
            stages[name] = r.stage_names
            times[(name, k)] += tick_times(r, pos, 1e-3)
    rows = []
    base = None
    for name in sets:
        row: dict = {"set": name, "stages": " ".join(stages[name])}
        for k in KERNELS:
            med, p99 = stats(times[(name, k)])
            row[k] = {"median_us": med, "p99_us": p99}
        base = base or row["python"]["median_us"]
        row["ratio"] = row["python"]["median_us"] / base
        row["speedup"] = row["python"]["median_us"] / row["compiled"]["median_us"]
        rows.append(row)
    return rows


def bench_meshes(rounds: int, tmp: Path, kernels: str = "compiled") -> list[dict]:
    import trimesh

    radius = 0.025
    shapes = {"box (6 faces)": None}
    for sub in (1, 3, 5):
        path = tmp / f"sphere{sub}.stl"
        trimesh.creation.icosphere(subdivisions=sub, radius=radius).export(path)
        shapes[f"sphere, {20 * 4**sub} faces"] = path
    # The thumb presses 3 mm into the +x side and slides in a 5 mm circle: in contact all along.
    n = 600
    a = np.linspace(0, 2 * np.pi, n)
    thumb = np.stack(
        [np.full(n, radius + 0.008 - 0.003), 0.005 * np.cos(a), 0.005 * np.sin(a)], axis=1
    )
    pos = np.stack([thumb, np.tile([-0.07, 0.0, 0.0], (n, 1))], axis=1)
    times: dict[str, list[float]] = {k: [] for k in shapes}
    errors: dict[str, float] = {}
    for _ in range(rounds):
        for name, path in shapes.items():
            data = yaml.safe_load(LIFT.read_text())
            data["scene"] = {
                "object": {
                    "shape": "box",
                    "size_m": [0.05] * 3,
                    "fixed": True,
                    "stiffness_n_per_m": 200.0,
                }
            }
            if path is not None:
                data["scene"]["object"] = {
                    "shape": "mesh",
                    "mesh": str(path),
                    "fixed": True,
                    "stiffness_n_per_m": 200.0,
                }
            tick_times(renderer_for(data, kernels), pos[:50], 1e-3)  # warm-up, not timed
            r = renderer_for(data, kernels)
            times[name] += tick_times(r, pos, 1e-3)
            shape = r.obj.shape
            # Surface-distance error against the 25 mm sphere a mesh approximates (a box is exact).
            verts = np.linalg.norm(shape.vertices, axis=1).max()
            err = max(radius - shape.offsets.min(), verts - radius)
            errors[name] = 0.0 if path is None else float(err)
    rows = []
    base = None
    for name in shapes:
        med, p99 = stats(times[name])
        base = base or med
        rows.append(
            {
                "shape": name,
                "median_us": med,
                "p99_us": p99,
                "ratio": med / base,
                "error_mm": errors[name] * 1e3,
            }
        )
    return rows


def kinetic_energy(obj: SceneObject) -> float:
    """Translational plus rotational kinetic energy, J."""
    I_world = obj.rotation @ obj.inertia_body @ obj.rotation.T
    return 0.5 * obj.mass * float(obj.velocity @ obj.velocity) + 0.5 * float(
        obj.omega @ I_world @ obj.omega
    )


def bench_substeps(rounds: int) -> list[dict]:
    g = np.array([0.0, 0.0, -9.81])
    ground = [Surface("ground", (0.0, 0.0, 1.0), -0.025, Material(2000.0, 5.0, 0.6, 0.5))]
    away = (np.array([[0.0, 0.0, 1.0]]), np.zeros((1, 3)))  # the finger touches nothing
    compiled: dict = {}

    def tick(c: SceneObject, surfaces: list[Surface], k: int) -> Renderer:
        """The renderer's tick (its one call, compiled) of ``c`` with gravity, one finger
        far away (one actuated direction: allocation in the call too): contact, forces and
        allocation of nothing, and the object's step."""
        one = [(1.0, 0.0, 0.0)]
        r = Renderer(Scene(c, surfaces, g, k), [0.008], Actuation([one], "world"), "pinv")
        if not compiled:
            compiled.update(jit.compile_kernels(r.kernel_names))
        r.use_kernels(compiled)
        return r

    rows = []
    times: dict[int, list[float]] = {k: [] for k in (1, 2, 4, 8)}
    drift: dict[int, float] = {}
    creep: dict[int, float] = {}

    def cube(z: float, spin: bool) -> SceneObject:
        return SceneObject(
            ConvexShape.box(np.full(3, 0.05)),
            Material(200.0),
            np.array([0.0, 0.0, z]),
            np.eye(3),
            fixed=False,
            mass=0.06,
            omega=np.array([3.0, 1.0, 0.5]) if spin else np.zeros(3),
        )

    for _ in range(rounds):
        for k in times:
            # Free fall with a tumble, no contact: total energy must stay constant.
            c = cube(0.0, True)
            r = tick(c, [], k)
            e0 = kinetic_energy(c) - c.mass * float(g @ c.position)
            clock = time.perf_counter
            worst = 0.0
            for _ in range(1000):
                t0 = clock()
                r.step(*away)
                times[k].append(clock() - t0)
                e = kinetic_energy(c) - c.mass * float(g @ c.position)
                worst = max(worst, abs(e - e0))
            drift[k] = worst
            # Resting on the ground: it must not creep or jitter.
            c = cube(-0.06 * 9.81 / (4 * 2000.0), False)
            z0 = c.position.copy()
            r = tick(c, ground, k)
            for _ in range(1000):
                r.step(*away)
            creep[k] = float(np.linalg.norm(c.position - z0))
    base = None
    for k in times:
        med, p99 = stats(times[k])
        base = base or med
        rows.append(
            {
                "substeps": k,
                "median_us": med,
                "p99_us": p99,
                "ratio": med / base,
                "fall_drift_j": drift[k],
                "rest_creep_m": creep[k],
            }
        )
    return rows


def plot(path: Path, effects: list[dict], meshes: list[dict], subs: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    ax = axes[0]
    names = [r["set"] for r in effects]
    y = np.arange(len(names))
    for off, k, color in ((-0.2, "python", "tab:blue"), (0.2, "compiled", "tab:green")):
        ax.barh(
            y + off,
            [r[k]["median_us"] for r in effects],
            0.4,
            color=color,
            label=f"{k} median",
        )
        ax.scatter(
            [r[k]["p99_us"] for r in effects],
            y + off,
            color="tab:red",
            marker="|",
            s=100,
            label="p99" if k == "python" else None,
        )
    ax.set_yticks(range(len(names)), names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("renderer tick time (us)")
    ax.set_title("effect sets (lift trajectory)")
    ax.legend(fontsize=8)
    ax = axes[1]
    spheres = [r for r in meshes if r["error_mm"] > 0]
    ax.loglog([r["error_mm"] for r in spheres], [r["median_us"] for r in spheres], "o-")
    for r in spheres:
        ax.annotate(r["shape"], (r["error_mm"], r["median_us"]), fontsize=7)
    ax.set_xlabel("surface-distance error vs a 25 mm sphere (mm)")
    ax.set_ylabel("median tick time (us)")
    ax.set_title("mesh resolution: time against accuracy")
    ax.grid(True, which="both", alpha=0.3)
    ax = axes[2]
    sub = [r for r in subs if isinstance(r["substeps"], int)]
    ax.loglog([r["fall_drift_j"] for r in sub], [r["median_us"] for r in sub], "o-")
    for r in sub:
        ax.annotate(f"{r['substeps']} substeps", (r["fall_drift_j"], r["median_us"]), fontsize=8)
    ax.set_xlabel("energy drift of a tumbling free fall over 1 s (J)")
    ax.set_ylabel("median dynamics time per tick (us)")
    ax.set_title("integration substeps: time against drift")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description="Scene benchmark: accuracy beside time.")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument(
        "--plot",
        type=Path,
        default=DEFAULT_PLOT,
        metavar="PATH",
        help=f"save the plot here (default {DEFAULT_PLOT})",
    )
    args = ap.parse_args()
    import tempfile

    effects = bench_effects(args.rounds)
    with tempfile.TemporaryDirectory() as tmp:
        meshes = bench_meshes(args.rounds, Path(tmp))
    subs = bench_substeps(args.rounds)
    print(
        "| effect set | stages in the plan | python median / p99 us | compiled median / p99 us "
        "| python / compiled | python x fixed frictionless |"
    )
    print("|---|---|---|---|---|---|")
    for r in effects:
        py, co = r["python"], r["compiled"]
        print(
            f"| {r['set']} | {r['stages']} | {py['median_us']:.1f} / {py['p99_us']:.1f} | "
            f"{co['median_us']:.1f} / {co['p99_us']:.1f} | {r['speedup']:.2f} | "
            f"{r['ratio']:.2f} |"
        )
    print("\n| object | median us | p99 us | x box | surface error mm |")
    print("|---|---|---|---|---|")
    for r in meshes:
        print(
            f"| {r['shape']} | {r['median_us']:.1f} | {r['p99_us']:.1f} | {r['ratio']:.2f} | "
            f"{r['error_mm']:.4f} |"
        )
    print(
        "\n| substeps | tick median us | p99 us | x 1 substep | "
        "free-fall energy drift J (1 s) | resting creep m (1 s) |"
    )
    print("|---|---|---|---|---|---|")
    for r in subs:
        print(
            f"| {r['substeps']} | {r['median_us']:.1f} | {r['p99_us']:.1f} | {r['ratio']:.2f} | "
            f"{r['fall_drift_j']:.3g} | {r['rest_creep_m']:.3g} |"
        )
    plot(args.plot, effects, meshes, subs)
    print(f"\nplot: {args.plot}")


if __name__ == "__main__":
    main()
