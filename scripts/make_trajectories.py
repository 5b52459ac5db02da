#!/usr/bin/env python3
"""Generate the bundled replay trajectories from the motion model (hapticd.loop.trajectory).

Writes hapticd/data/trajectories/*.hrec. Deterministic: running it again gives the same
files to 1e-15 m (a test checks this). Usage: python scripts/make_trajectories.py [--out DIR]
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np

from hapticd import recording
from hapticd.loop.trajectory import Hold, MinJerk, Segment, Squeeze, two_finger

DATA = Path(__file__).resolve().parent.parent / "hapticd" / "data" / "trajectories"
RATE_HZ = 500.0
Vec = tuple[float, float, float]  # below the loop rate on purpose: the replay device interpolates


CONTACT_X = 0.025 + 0.008  # cube half size + fingertip radius: where contact starts, m


def key_points(sign: float, dy: float, dz: float, depth: float) -> tuple[Vec, Vec, Vec]:
    """A finger's far, near (3 mm before contact) and pinch (``depth`` in) points, m."""
    far = (sign * 0.070, dy, dz)
    near = (sign * (CONTACT_X + 0.003), dy, dz)
    pinch = (sign * (CONTACT_X - depth), dy, dz)
    return far, near, pinch


def metadata(doc: str | None, phases: dict[str, list[float]]) -> dict:
    return {
        "description": (doc or "").split("\n")[0],
        "model": "minimum-jerk segments; see docs/trajectories.md",
        "rate_hz": RATE_HZ,
        "phases_s": phases,
    }


# Per finger: the side it comes from (thumb -x, index +x), and its y and z offsets, m.
GRASP_FINGERS = ((-1.0, 0.0, 0.0), (1.0, -0.001, 0.002))  # the index 2 mm higher, 1 mm off
LIFT_FINGERS = ((-1.0, 0.0, 0.0), (1.0, -0.001, 0.0))


def both_fingers(
    fingers: tuple[tuple[float, float, float], ...],
    plan: Callable[[float, float, float], tuple[Vec, list[Segment]]],
) -> tuple[np.ndarray, np.ndarray]:
    """Times (N,) s and positions (N, F, 3) m of each finger's ``plan(sign, dy, dz)``: its
    start and its segments."""
    starts, plans = [], []
    for sign, dy, dz in fingers:
        start, segments = plan(sign, dy, dz)
        starts.append(np.array(start))
        plans.append(segments)
    return two_finger(starts, plans, RATE_HZ)


def grasp_stiffness() -> tuple[np.ndarray, np.ndarray, dict]:
    """Seed experiment 1: approach a fixed 50 mm cube, pinch, explore 3 s, release.

    Thumb on -x, index on +x; fingertip radius 8 mm, so contact starts at
    |x| = 33 mm. The pinch presses 15 mm in (0.9 N at 60 N/m), then squeezes
    +/-4 mm at 1.2 Hz for 3 s (the seed's 3 s exploration). The index finger is
    2 mm higher and 1 mm off the thumb's line, as real fingers are.
    """

    def plan(sign: float, dy: float, dz: float) -> tuple[Vec, list[Segment]]:
        far, near, pinch = key_points(sign, dy, dz, 0.015)
        return far, [
            Hold(0.5),
            MinJerk(1.2, near),
            MinJerk(0.8, pinch),
            Squeeze(3.0, (-sign, 0.0, 0.0), 0.004, 1.2),
            MinJerk(0.8, near),
            MinJerk(1.0, far),
            Hold(0.5),
        ]

    t, x = both_fingers(GRASP_FINGERS, plan)
    phases = {
        "approach": [0.5, 1.7],
        "pinch": [1.7, 2.5],
        "hold": [2.5, 5.5],
        "release": [5.5, 6.3],
        "retreat": [6.3, 7.3],
    }
    return t, x, metadata(grasp_stiffness.__doc__, phases)


def lift_weight() -> tuple[np.ndarray, np.ndarray, dict]:
    """Seed experiment 2: pinch a free 50 mm cube resting on the ground, lift, hold 3 s, put down.

    Cube centre at the origin, its bottom on the ground at z = -25 mm. The
    fingers pinch 10 mm in (2 N each at 200 N/m), lift 40 mm, hold for the
    seed's 3 s exploration with a small vertical bounce (+/-3 mm at 1 Hz, to
    feel the weight), set the cube down, release and retreat.
    """
    lift = 0.040

    def plan(sign: float, dy: float, dz: float) -> tuple[Vec, list[Segment]]:
        far, near, pinch = key_points(sign, dy, dz, 0.010)
        up = (pinch[0], dy, lift)
        return far, [
            Hold(0.5),
            MinJerk(1.2, near),
            MinJerk(0.8, pinch),
            MinJerk(1.0, up),
            Squeeze(3.0, (0.0, 0.0, 1.0), 0.003, 1.0),
            MinJerk(1.0, pinch),
            Hold(0.3),
            MinJerk(0.8, near),
            MinJerk(1.0, far),
            Hold(0.5),
        ]

    t, x = both_fingers(LIFT_FINGERS, plan)
    phases = {
        "approach": [0.5, 1.7],
        "pinch": [1.7, 2.5],
        "lift": [2.5, 3.5],
        "hold": [3.5, 6.5],
        "put_down": [6.5, 7.5],
        "release": [7.8, 8.6],
        "retreat": [8.6, 9.6],
    }
    return t, x, metadata(lift_weight.__doc__, phases)


def grasp_cycle() -> tuple[np.ndarray, np.ndarray, dict]:
    """A rehearsal hand's grasp, one cycle of a loop: pinch the fixed cube, hold, let go, rest.

    Each fingertip starts and ends 12 mm out of contact (the cycle closes, so a device
    with ``repeat: true`` plays it again seamlessly for as long as the run lasts),
    pinches 15 mm in (0.9 N at 60 N/m) in 0.35 s, holds 0.8 s with a small squeeze
    (+/-2 mm at 2 Hz), lets go in 0.35 s and rests 1 s: a touch every 2.5 s, released
    long enough between touches for an experiment to start a recording and change the
    object (on a busy machine too).
    """

    def plan(sign: float, dy: float, dz: float) -> tuple[Vec, list[Segment]]:
        out = (sign * (CONTACT_X + 0.012), dy, dz)
        pinch = (sign * (CONTACT_X - 0.015), dy, dz)
        return out, [
            MinJerk(0.35, pinch),
            Squeeze(0.8, (-sign, 0.0, 0.0), 0.002, 2.0, ramp_s=0.2),
            MinJerk(0.35, out),
            Hold(1.0),
        ]

    t, x = both_fingers(GRASP_FINGERS, plan)
    phases = {
        "pinch": [0.0, 0.35],
        "hold": [0.35, 1.15],
        "release": [1.15, 1.5],
        "rest": [1.5, 2.5],
    }
    return t, x, metadata(grasp_cycle.__doc__, phases)


def lift_cycle() -> tuple[np.ndarray, np.ndarray, dict]:
    """A rehearsal hand's lift, one cycle of a loop: pinch the resting cube, lift, hold, set
    it down, let go, rest.

    Each fingertip starts and ends 12 mm out of contact (a closed cycle, for ``repeat:
    true``), pinches 10 mm in (2 N at 200 N/m) in 0.4 s, lifts 30 mm in 0.5 s, holds
    0.6 s with a small bounce (+/-3 mm at 2 Hz, to feel the weight), sets the cube down
    in 0.5 s, lets go in 0.4 s and rests 1 s: a lift every 3.6 s.
    """
    lift = 0.030

    def plan(sign: float, dy: float, dz: float) -> tuple[Vec, list[Segment]]:
        out = (sign * (CONTACT_X + 0.012), dy, dz)
        pinch = (sign * (CONTACT_X - 0.010), dy, dz)
        up = (pinch[0], dy, lift)
        return out, [
            MinJerk(0.4, pinch),
            MinJerk(0.5, up),
            Squeeze(0.6, (0.0, 0.0, 1.0), 0.003, 2.0, ramp_s=0.2),
            MinJerk(0.5, pinch),
            Hold(0.2),
            MinJerk(0.4, out),
            Hold(1.0),
        ]

    t, x = both_fingers(LIFT_FINGERS, plan)
    phases = {
        "pinch": [0.0, 0.4],
        "lift": [0.4, 0.9],
        "hold": [0.9, 1.5],
        "put_down": [1.5, 2.0],
        "release": [2.2, 2.6],
        "rest": [2.6, 3.6],
    }
    return t, x, metadata(lift_cycle.__doc__, phases)


TRAJECTORIES = {
    "grasp-stiffness": grasp_stiffness,
    "lift-weight": lift_weight,
    "grasp-cycle": grasp_cycle,
    "lift-cycle": lift_cycle,
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=DATA, help="output folder")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name, make in TRAJECTORIES.items():
        t, x, meta = make()
        path = args.out / f"{name}{recording.SUFFIX}"
        recording.write(
            path,
            {"t": t, "device_pos": x},
            recording.trajectory_fields(x.shape[1]),
            ["thumb", "index"],
            meta,
        )
        print(f"wrote {path} ({len(t)} samples, {t[-1]:.2f} s)")


if __name__ == "__main__":
    main()
