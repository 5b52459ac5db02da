#!/usr/bin/env python3
"""The seed's two examples (Barbagli & Salisbury, section 4) from the pipeline: the numbers
and figures of docs/analysis.md.

1. A point on a frictionless wall tilted by alpha, one actuator (the seed's y),
   k = 60 N/m, 2 mm inside: F_L (eq. 11) and M_A F_L M_S (eq. 12) per allocator
   beside the closed forms; asymmetry and the closed-loop work around the seed's
   triangle (eq. 13, delta = 2 mm) over alpha.
2. Two points pinching a static wall (the 50 mm cube, 8 mm fingertips: x_R = 33 mm),
   one actuator along the line: the linearization in (L, alpha) (eq. 16) and
   M_A F_L M_S (eq. 18), with the seed's printed lower-right entry beside the
   derived one.

Usage: python scripts/analysis_examples.py [--plot FOLDER]
(the figures go to the system temp dir unless --plot names a folder; the
docs' figures: --plot docs/img)
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np

from hapticd.analysis import examples

K = 60.0
DEPTH = 0.002
DELTA = 0.002
# Outside the repository: a run never overwrites the docs' figures unless asked to.
DEFAULT_FOLDER = Path(tempfile.gettempdir()) / "hapticd-analysis-examples"


def fmt(M: np.ndarray) -> str:
    # Entries below 1e-9 are rounding of a zero (the differences' last bits).
    return (
        "["
        + "; ".join(" ".join(f"{(v if abs(v) > 1e-9 else 0.0):9.4f}" for v in row) for row in M)
        + "]"
    )


def rel(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.max(np.abs(got - want)) / max(np.max(np.abs(want)), 1e-300))


def wall_section() -> list[tuple[float, float, float, float, float]]:
    a = math.radians(30.0)
    wall = examples.tilted_wall(a, K)
    res = wall.pipeline.linearize_coordinates(wall.coords, wall.inside(DEPTH), labels=["x", "y"])
    print(f"1. Tilted wall, alpha = 30 deg, k = {K:g} N/m, {DEPTH * 1e3:g} mm inside (N/m)")
    print(f"   seed F_L  (eq. 11)        {fmt(examples.wall_f_l(a, K))}")
    print(f"   seed M_A F_L M_S (eq. 12) {fmt(examples.wall_rendered(a, K))}")
    for name, lin in res.items():
        print(
            f"   {name:<9} K_full {fmt(lin.K_full)}  K_rendered {fmt(lin.K_rendered)}  "
            f"asymmetry {lin.asymmetry:.4f}  k {lin.controllability:g}  o {lin.observability:g}  "
            f"work/area {lin.work_per_area:.4f} J/m^2"
        )
    print(
        f"   relative error, pinv: F_L {rel(res['pinv'].K_full, examples.wall_f_l(a, K)):.1e}, "
        f"M_A F_L M_S {rel(res['pinv'].K_rendered, examples.wall_rendered(a, K)):.1e}"
    )
    print(
        f"\n   over alpha (pinv; closed-loop work around the triangle, delta = {DELTA * 1e3:g} mm)"
    )
    print("   alpha   asymmetry  s/sqrt(2)   work (J)      seed eq. 13 (J)  full-force work (J)")
    rows = []
    for deg in (0, 15, 30, 45, 60, 75, 90):
        a = math.radians(deg)
        wall = examples.tilted_wall(a, K, allocators=["pinv"])
        lin = wall.pipeline.linearize_coordinates(wall.coords, wall.inside(DEPTH))["pinv"]
        work = wall.pipeline.loop_work(wall.triangle(DELTA))["pinv"] if deg < 90 else None
        w = work.rendered if work else 0.0
        seed = examples.wall_work(a, K, DELTA) if deg < 90 else float("nan")
        cells = (f"{w:.6e}  {seed:.6e}     {work.full:.1e}") if work else "(no triangle at 90 deg)"
        print(f"   {deg:>4}   {lin.asymmetry:9.4f}  {math.sin(a) / math.sqrt(2):9.4f}   {cells}")
        rows.append((deg, lin.asymmetry, math.sin(a) / math.sqrt(2), w, seed))
    return rows


def rod_section() -> list[tuple[float, np.ndarray, np.ndarray]]:
    r = examples.rod(K)
    L, a = 0.062, 0.3
    res = r.pipeline.linearize_coordinates(r.coords, [L, a], labels=["L", "alpha"])
    print(
        f"\n2. Rod, k = {K:g} N/m, x_R = {r.x_r * 1e3:g} mm, L = {L * 1e3:g} mm, "
        f"alpha = {a:g} rad (entries: N/m, N/rad, N/rad, N m/rad)"
    )
    print(f"   seed eq. (14) F_g, tau    {examples.rod_forces(L, a, K, r.x_r)}")
    print(f"   seed eq. (16) as printed  {fmt(examples.rod_f_l_printed(L, a, K, r.x_r))}")
    print(f"   eq. (16) derived again    {fmt(examples.rod_f_l(L, a, K, r.x_r))}")
    print(f"   seed eq. (18)             {fmt(examples.rod_rendered(L, a, K, r.x_r))}")
    for name, lin in res.items():
        print(
            f"   {name:<9} Q_full {lin.Q_full}  Q_rendered {lin.Q_rendered}\n"
            f"             K_full {fmt(lin.K_full)}  K_rendered {fmt(lin.K_rendered)}  "
            f"asymmetry {lin.asymmetry:.4f}  k {lin.controllability:g}  o {lin.observability:g}"
        )
    lin = res["pinv"]
    err16 = rel(lin.K_full, examples.rod_f_l(L, a, K, r.x_r))
    print(
        f"   relative error, pinv: eq. 16 (derived) {err16:.1e}, "
        f"eq. 18 {rel(lin.K_rendered, examples.rod_rendered(L, a, K, r.x_r)):.1e}; "
        f"lower-right entry {lin.K_full[1, 1]:.6f} N m/rad against the printed "
        f"{examples.rod_f_l_printed(L, a, K, r.x_r)[1, 1]:.6f}"
    )
    rows = []
    for alpha in np.linspace(-0.5, 0.5, 21):
        lin = examples.rod(K, allocators=["pinv"]).pipeline.linearize_coordinates(
            r.coords, [L, alpha]
        )["pinv"]
        rows.append((float(alpha), lin.K_full, lin.K_rendered))
    return rows


def plot(folder: Path, wall_rows, rod_rows, r_x: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    deg = np.array([w[0] for w in wall_rows])
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    ax1.plot(deg, [w[2] for w in wall_rows], "-", color="0.6", label="sin(alpha)/sqrt(2)")
    ax1.plot(deg, [w[1] for w in wall_rows], "o", label="pipeline (pinv)")
    ax1.set_xlabel("wall tilt alpha (deg)")
    ax1.set_ylabel("asymmetry of M_A F_L M_S")
    ax1.legend()
    fine = np.linspace(0, 89, 90)
    ax2.plot(
        fine,
        [examples.wall_work(math.radians(d), K, DELTA) * 1e6 for d in fine],
        "-",
        color="0.6",
        label="seed eq. (13), k dL^2 sin^2(alpha)/2",
    )
    ok = deg < 90
    ax2.plot(deg[ok], [w[3] * 1e6 for w in wall_rows if w[0] < 90], "o", label="pipeline (pinv)")
    ax2.set_xlabel("wall tilt alpha (deg)")
    ax2.set_ylabel("closed-loop work (uJ)")
    ax2.legend()
    fig.suptitle(f"Point on a tilted wall: k = {K:g} N/m, one actuator, loop dL = 2 mm")
    fig.tight_layout()
    fig.savefig(folder / "analysis-tilted-wall.png", dpi=110)
    plt.close(fig)

    L = 0.062
    alphas = np.array([r[0] for r in rod_rows])
    fine = np.linspace(-0.5, 0.5, 201)
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.6))
    seed = [examples.rod_f_l(L, a, K, r_x) for a in fine]
    printed = [examples.rod_f_l_printed(L, a, K, r_x) for a in fine]
    axes[0].plot(fine, [m[0, 0] for m in seed], "-", color="0.6", label="eq. (16)")
    axes[0].plot(alphas, [r[1][0, 0] for r in rod_rows], "o", ms=4, label="pipeline")
    axes[0].set_title("dF_g/dL (N/m)")
    axes[1].plot(fine, [m[0, 1] for m in seed], "-", color="0.6", label="eq. (16), (18)")
    axes[1].plot(alphas, [r[1][0, 1] for r in rod_rows], "o", ms=4, label="pipeline F_L (1,2)")
    axes[1].plot(alphas, [r[1][1, 0] for r in rod_rows], "x", ms=5, label="pipeline F_L (2,1)")
    axes[1].plot(
        alphas, [r[2][1, 0] for r in rod_rows], "s", ms=3, label="pipeline M_A F_L M_S (2,1)"
    )
    axes[1].set_title("dF_g/dalpha = dtau/dL (N/rad)")
    axes[2].plot(
        fine, [m[1, 1] for m in seed], "-", color="0.6", label="derived: kL(L cos2a/2 - x_R cos a)"
    )
    axes[2].plot(alphas, [r[1][1, 1] for r in rod_rows], "o", ms=4, label="pipeline")
    ax_printed = axes[2].twinx()
    ax_printed.plot(
        fine, [m[1, 1] for m in printed], "--", color="C3", label="as printed (N, right axis)"
    )
    ax_printed.set_ylabel("printed entry (N)", color="C3")
    axes[2].set_title("dtau/dalpha (N m/rad)")
    for ax in axes:
        ax.set_xlabel("alpha (rad)")
    # Legends under the plots: the curves fill the axes.
    for ax, extra in zip(axes, ([], [], [ax_printed]), strict=True):
        handles = [h for a in (ax, *extra) for h in a.get_legend_handles_labels()[0]]
        ax.legend(handles=handles, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2))
    fig.suptitle(f"Two points on a rod: k = {K:g} N/m, x_R = {r_x * 1e3:g} mm, L = {L * 1e3:g} mm")
    fig.tight_layout()
    fig.savefig(folder / "analysis-rod.png", dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument(
        "--plot",
        type=Path,
        default=DEFAULT_FOLDER,
        metavar="FOLDER",
        help=f"save the figures there (default {DEFAULT_FOLDER})",
    )
    args = ap.parse_args()
    np.set_printoptions(precision=6, suppress=True)
    wall_rows = wall_section()
    rod_rows = rod_section()
    args.plot.mkdir(parents=True, exist_ok=True)
    plot(args.plot, wall_rows, rod_rows, examples.rod(K).x_r)
    print(f"\nfigures: {args.plot / 'analysis-tilted-wall.png'}, {args.plot / 'analysis-rod.png'}")


if __name__ == "__main__":
    main()
