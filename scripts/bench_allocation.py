#!/usr/bin/env python3
"""What accuracy costs in time: every allocator variant on the same problems, in one run.

Workloads: (1) every in-contact tick of the bundled grasp trajectory (the
profile's geometry, grasp-frame actuation), (2) sweeps through every kind of
singular configuration (hapticd.allocation_cases). Variants:

- numpy seed   : the seed's formulas in plain numpy with np.linalg.pinv (the baseline)
- robust general: the robust allocators' general path (allocate_many's, a batch of one)
- robust closed: the robust allocators through allocate(), two-contact closed form
- loop closed  : the closed form called as the servo loop calls it (floats in, floats out)
- cached 0.5 mm: the robust map lam -> lam_a (r x 3p) kept while no contact point moves
                 more than 0.5 mm and M_a changes less than 1e-3; then one matrix-vector
                 product per tick, at the cost of stale geometry

Per variant and workload: median and p99 time per allocation over repeated
rounds (variants interleaved, so machine noise hits all alike), the speed-up
against the baseline, the mean internal and external residual, the worst
amplification |M_a lam_a| / |lam|, and the largest step of lam_a between
consecutive problems. Prints a Markdown table and saves a plot of accuracy
against time.

Usage: python scripts/bench_allocation.py [--rounds 5] [--plot PATH]
(the plot goes to the system temp dir unless --plot names a file; the docs'
figure: --plot docs/img/bench-allocation.png)
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hapticd import recording
from hapticd.allocation import (
    DEFAULT_ROBUSTNESS,
    accuracy,
    allocate,
    two_contact_ef,
    two_contact_if,
    two_contact_pinv,
    two_contact_structure,
)
from hapticd.allocation.actuation import Actuation
from hapticd.allocation.cases import SWEEPS, sweep
from hapticd.allocation.grasp import grasp_matrix
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile

ROOT = Path(__file__).resolve().parent.parent
# Outside the repository: a run never overwrites the docs' figure unless asked to.
DEFAULT_PLOT = Path(tempfile.gettempdir()) / "hapticd-bench-allocation.png"
PROFILE = ROOT / "configs" / "grasp-stiffness.yaml"
EPS, SEP = DEFAULT_ROBUSTNESS.eps, DEFAULT_ROBUSTNESS.min_separation_m

Problem = tuple[np.ndarray, np.ndarray, np.ndarray]


def trajectory_problems(tmp: Path) -> list[Problem]:
    """(G, M_a, lam) of every tick with both fingers in contact, from an unpaced run."""
    path = tmp / "bench-trajectory.hrec"
    prof = load_profile(PROFILE)
    build_session(prof, paced=False, record_path=path).run()
    rec = recording.read(path)
    radii = [f.radius_m for f in prof.fingers]
    act = Actuation(
        [list(f.actuated_directions) for f in prof.fingers], prof.rendering.actuation_frame
    )
    center = np.array(prof.scene.object.position_m)
    out = []
    both = np.all(rec["in_contact"] == 1, axis=1)
    for k in np.flatnonzero(both):
        lam = rec["contact_force"][k]
        normals = lam / np.linalg.norm(lam, axis=1, keepdims=True)
        pts = rec["proxy_pos"][k] - np.array(radii)[:, None] * normals
        world = act.world_directions([tuple(p) for p in rec["device_pos"][k]])
        M, _ = act.submatrix(world, [0, 1])
        out.append((grasp_matrix(pts, center), M, lam.reshape(-1)))
    path.unlink()
    return out


@dataclass
class Variant:
    name: str
    method: str
    prepare: Callable[[list[Problem]], list[tuple]]
    call: Callable[..., object]
    applies: Callable[[list[Problem]], bool] = lambda probs: True


def _api(method: str, fast: bool) -> tuple[Callable, Callable]:
    return (lambda probs: [(G, M, lam) for G, M, lam in probs]), (
        lambda G, M, lam: allocate(method, G, M, lam, fast=fast)
    )


def _loop_args(probs: list[Problem]) -> list[tuple]:
    out = []
    for G, M, lam in probs:
        r1, r2, d1, d2 = two_contact_structure(G, M)
        out.append((r1, r2, d1, d2, tuple(map(float, lam[:3])), tuple(map(float, lam[3:]))))
    return out


def _two_simple(probs: list[Problem]) -> bool:
    return all(two_contact_structure(G, M) is not None for G, M, _ in probs)


def variants() -> list[Variant]:
    out = []
    for method in ("pinv", "if", "ef"):
        prep, call = _api(method + "_exact", True)
        out.append(Variant("numpy seed", method, prep, call))
        prep, call = _api(method, False)
        out.append(Variant("robust general", method, prep, call))
        prep, call = _api(method, True)
        out.append(Variant("robust closed", method, prep, call, _two_simple))
    loop = {
        "pinv": lambda r1, r2, d1, d2, l1, l2: two_contact_pinv(d1, d2, l1, l2, EPS),
        "if": lambda r1, r2, d1, d2, l1, l2: two_contact_if(r1, r2, d1, d2, l1, l2, EPS, SEP),
        "ef": lambda r1, r2, d1, d2, l1, l2: two_contact_ef(r1, r2, d1, d2, l1, l2, EPS),
    }
    for method, fn in loop.items():
        out.append(Variant("loop closed", method, _loop_args, fn, _two_simple))

    for method in ("pinv", "if", "ef"):
        prep, _ = _api(method, True)
        out.append(Variant("cached 0.5 mm", method, prep, CachedMap(method, 5e-4, 1e-3)))
    return out


class CachedMap:
    """Robust allocation as a cached linear map, recomputed when the geometry moves."""

    def __init__(self, method: str, point_tol_m: float, m_tol: float) -> None:
        self.method, self.point_tol, self.m_tol = method, point_tol_m, m_tol
        self.G: np.ndarray | None = None
        self.M: np.ndarray | None = None
        self.A = np.zeros((0, 0))

    def __call__(self, G: np.ndarray, M: np.ndarray, lam: np.ndarray) -> np.ndarray:
        stale = (
            self.G is None
            or self.G.shape != G.shape
            or self.M.shape != M.shape
            or np.abs(G[3:] - self.G[3:]).max() > self.point_tol
            or np.abs(M - self.M).max() > self.m_tol
        )
        if stale:
            eye = np.eye(G.shape[1])
            self.A = np.column_stack([allocate(self.method, G, M, e) for e in eye])
            self.G, self.M = G.copy(), M.copy()
        return self.A @ lam


def to_vec(x: object) -> np.ndarray:
    return np.asarray(x, dtype=float).reshape(-1)


def measure(
    vs: list[Variant], probs: list[Problem], segments: list[int], rounds: int
) -> dict[tuple[str, str], dict]:
    """Times per call (interleaved rounds) and accuracy of each applicable variant."""
    active = [v for v in vs if v.applies(probs)]
    args = {id(v): v.prepare(probs) for v in active}
    times: dict[int, list[float]] = {id(v): [] for v in active}
    clock = time.perf_counter
    for _ in range(rounds):
        for v in active:
            call, ts = v.call, times[id(v)]
            for a in args[id(v)]:
                t0 = clock()
                call(*a)
                ts.append(clock() - t0)
    results = {}
    for v in active:
        outs = [to_vec(v.call(*a)) for a in args[id(v)]]
        acc = [accuracy(G, M, lam, x) for (G, M, lam), x in zip(probs, outs, strict=True)]
        jumps = [
            float(np.abs(outs[k] - outs[k - 1]).max())
            for k in range(1, len(outs))
            if segments[k] == segments[k - 1]
        ]
        ts = sorted(times[id(v)])
        results[(v.name, v.method)] = {
            "median_us": statistics.median(ts) * 1e6,
            "p99_us": ts[min(len(ts) - 1, int(0.99 * len(ts)))] * 1e6,
            "internal": float(np.mean([a.internal for a in acc])),
            "external": float(np.mean([a.external for a in acc])),
            "total": float(np.mean([a.total for a in acc])),
            "amplification": float(max(a.amplification for a in acc)),
            "jump": max(jumps) if jumps else 0.0,
            "finite": bool(all(np.all(np.isfinite(x)) for x in outs)),
        }
    return results


def table(workload: str, res: dict[tuple[str, str], dict]) -> list[str]:
    lines = []
    for method in ("pinv", "if", "ef"):
        base = res.get(("numpy seed", method))
        for (name, m), r in res.items():
            if m != method:
                continue
            speed = base["median_us"] / r["median_us"] if base else float("nan")
            amp = f"{r['amplification']:.3g}" if r["finite"] else "inf/NaN"
            lines.append(
                f"| {workload} | {method} | {name} | {r['median_us']:.1f} | {r['p99_us']:.1f} | "
                f"{speed:.1f}x | {r['internal']:.3g} | {r['external']:.3g} | {amp} | "
                f"{r['jump']:.3g} |"
            )
    return lines


OBJECTIVE = {"pinv": "total", "if": "internal", "ef": "external"}


def plot(path: Path, all_res: dict[str, dict]) -> None:
    """Per workload: time against each method's own objective residual, and amplification."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted({name for res in all_res.values() for name, _ in res})
    colors = {n: plt.cm.tab10(i) for i, n in enumerate(names)}
    markers = {"pinv": "o", "if": "s", "ef": "^"}
    fig, axes = plt.subplots(2, len(all_res), figsize=(5 * len(all_res), 7.5), squeeze=False)
    for col, (workload, res) in enumerate(all_res.items()):
        for (name, method), r in res.items():
            y0 = max(r[OBJECTIVE[method]], 1e-16)
            y1 = r["amplification"] if r["finite"] else np.nan
            for row, y in ((0, y0), (1, y1)):
                axes[row, col].scatter(
                    r["median_us"], y, color=colors[name], marker=markers[method], s=45
                )
        for row, label in (
            (0, "mean residual of the method's objective (N)"),
            (1, "worst amplification"),
        ):
            ax = axes[row, col]
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("median time per allocation (us)")
            ax.set_ylabel(label)
            ax.grid(True, which="both", alpha=0.3)
        axes[0, col].set_title(workload)
    handles = [plt.Line2D([], [], color=colors[n], marker="o", ls="", label=n) for n in names]
    handles += [plt.Line2D([], [], color="k", marker=m, ls="", label=k) for k, m in markers.items()]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8)
    fig.suptitle(
        "Allocation: accuracy against time (objective: pinv total, if internal, ef external)"
    )
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description="Allocation benchmark: accuracy beside time.")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds")
    ap.add_argument(
        "--plot",
        type=Path,
        default=DEFAULT_PLOT,
        metavar="PATH",
        help=f"save the plot here (default {DEFAULT_PLOT})",
    )
    ap.add_argument("--sweep-points", type=int, default=401, help="points per singular sweep")
    args = ap.parse_args()

    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        traj = trajectory_problems(Path(tmp))
    vs = variants()
    all_res = {f"trajectory ({len(traj)} ticks)": measure(vs, traj, [0] * len(traj), args.rounds)}
    groups = {
        "singular sweeps": [n for n in SWEEPS if n != "M_a loses rank"],
        "M_a rank sweep": ["M_a loses rank"],
    }
    for label, names in groups.items():
        probs: list[Problem] = []
        segs: list[int] = []
        for i, name in enumerate(names):
            part = sweep(name, n=args.sweep_points)
            probs += part
            segs += [i] * len(part)
        all_res[f"{label} ({len(probs)} problems)"] = measure(vs, probs, segs, args.rounds)
    print(
        "| workload | method | variant | median us | p99 us | speed-up vs seed | "
        "internal residual N | external residual N | worst amplification | largest jump N |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for workload, res in all_res.items():
        for line in table(workload.split(" (")[0], res):
            print(line)
    plot(args.plot, all_res)
    print(f"\nplot: {args.plot}")


if __name__ == "__main__":
    main()
