#!/usr/bin/env python3
"""Draw the frames of docs/hardware.md's two-device rig: a top view (world x, y) of the
object, each device's frame (its x and y axes, from its mount) and workspace, and a side
view (world x, z).

The mounts are read from the guide's own example (its ```yaml fingers: block), so the
figure shows what the example says. Usage:
    python scripts/plot_rig_frames.py [--guide docs/hardware.md] [--out FILE.png]
(the default output is in a temporary folder; docs/img/rig-frames.png is the committed one).
"""

from __future__ import annotations

import argparse
import re
import tempfile
from pathlib import Path

import numpy as np
import yaml

from hapticd.loop.mount import Mount

ROOT = Path(__file__).resolve().parent.parent
CUBE_M = 0.05  # the bundled grasp's cube, m
WORKSPACE_M = 0.075  # an omega.3's workspace radius, m
AXIS_M = 0.03  # drawn length of a device's axes, m
COLOURS = {"thumb": "tab:blue", "index": "tab:orange"}


def mounts_from_guide(guide: Path) -> dict[str, Mount]:
    """Each finger's mount in the guide's example profile block."""
    block = re.search(r"```yaml\n(fingers:.*?)```", guide.read_text(), re.S)
    if block is None:
        raise SystemExit(f"{guide}: no ```yaml fingers: block")
    out = {}
    for f in yaml.safe_load(block.group(1))["fingers"]:
        m = f["device"].get("mount", {})
        out[f["name"]] = Mount.from_rpy(
            m.get("position_m", [0, 0, 0]),
            m.get("orientation_rpy_rad", [0, 0, 0]),
            m.get("workspace_scale", 1.0),
        )
    return out


def draw(mounts: dict[str, Mount], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Rectangle

    fig, (top, side) = plt.subplots(1, 2, figsize=(11, 5.2), gridspec_kw={"width_ratios": [3, 2]})
    mm = 1e3
    h = CUBE_M / 2 * mm
    for ax, (a, b), labels in (
        (top, (0, 1), ("world x (mm)", "world y (mm)")),
        (side, (0, 2), ("world x (mm)", "world z (mm), up")),
    ):
        ax.add_patch(Rectangle((-h, -h), 2 * h, 2 * h, color="0.75", label="object (50 mm cube)"))
        # The world's axes, drawn in a corner; its origin is the object's centre.
        ox, oy = -140.0, 55.0
        ax.annotate("", xy=(ox + 22, oy), xytext=(ox, oy), arrowprops={"arrowstyle": "->", "lw": 2})
        ax.annotate("", xy=(ox, oy + 22), xytext=(ox, oy), arrowprops={"arrowstyle": "->", "lw": 2})
        ax.text(ox + 24, oy - 3, "x world", fontsize=9, weight="bold")
        ax.text(ox - 3, oy + 25, "y world" if b == 1 else "z world (up)", fontsize=9, weight="bold")
        ax.plot([0], [0], "k+", ms=10)
        ax.text(0, -h - 8, "world origin: object centre", fontsize=7, ha="center")
        for name, m in mounts.items():
            c = COLOURS.get(name, "k")
            t = m.position * mm
            r = m.scale * WORKSPACE_M * mm
            ax.add_patch(
                Circle((t[a], t[b]), r, fill=False, ls="--", color=c, label=f"{name}: workspace")
            )
            for axis, style in ((0, "-"), (1, ":"), (2, "-.")):
                tip = m.rotation[:, axis] * AXIS_M * mm
                if abs(tip[a]) + abs(tip[b]) < 1.0:  # mm
                    continue  # seen end on
                ax.annotate(
                    "",
                    xy=(t[a] + tip[a], t[b] + tip[b]),
                    xytext=(t[a], t[b]),
                    arrowprops={"arrowstyle": "->", "color": c, "lw": 1.8, "ls": style},
                )
                ax.text(
                    t[a] + 1.25 * tip[a],
                    t[b] + 1.25 * tip[b] - 3,
                    f"{'xyz'[axis]}_dev",
                    color=c,
                    fontsize=8,
                    ha="center",
                )
            ax.plot([t[a]], [t[b]], "o", color=c, ms=5)
            if b == 1:
                ax.text(t[a], t[b] + 6, f"{name}\ndevice", color=c, fontsize=8, ha="center")
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        ax.set_aspect("equal")
        ax.set_xlim(-150, 150)
        ax.set_ylim(-95, 95)
        ax.grid(alpha=0.3)
    top.set_title("top view: x_world = s R x_dev + t; force to the device R^T f")
    side.set_title("side view")
    handles, names = top.get_legend_handles_labels()
    top.legend(handles, names, fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--guide", type=Path, default=ROOT / "docs" / "hardware.md")
    ap.add_argument(
        "--out", type=Path, default=Path(tempfile.gettempdir()) / "hapticd-rig-frames.png"
    )
    args = ap.parse_args()
    mounts = mounts_from_guide(args.guide)
    draw(mounts, args.out)
    for name, m in mounts.items():
        axes = ", ".join(
            f"{'xyz'[i]}_dev -> world {np.round(m.rotation[:, i], 3).tolist()}" for i in range(3)
        )
        print(f"{name}: origin {np.round(m.position, 4).tolist()} m; {axes}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
