"""Actuation matrix M_a: which force directions each finger's device renders.

Underactuation is simulated in software: finger i renders only along its
unit directions d_i1..d_ik (0 to 3 of them). M_a is (3F, r), block diagonal,
column j of finger i holding d_ij in rows 3i..3i+2; r is the total number of
actuated directions. Directions are given in the world frame or in the grasp
frame (x from the first finger to the second, z as close to world up as
possible, y = z cross x), which follows the fingers.
"""

from __future__ import annotations

import math

import numpy as np

V3 = tuple[float, float, float]
_DEGENERATE = 1e-9


def grasp_axes(p0: V3, p1: V3) -> tuple[V3, V3, V3]:
    """Grasp frame axes (x, y, z) in world, for fingers at p0 and p1 (m).

    x = unit(p1 - p0); z = world up made orthogonal to x; y = z cross x.
    Degenerate cases fall back to world axes: coincident points use world x; a
    vertical grasp line uses world x in place of up.
    """
    ex, ey, ez = p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]
    n = math.sqrt(ex * ex + ey * ey + ez * ez)
    x = (ex / n, ey / n, ez / n) if n > _DEGENERATE else (1.0, 0.0, 0.0)
    ref = (0.0, 0.0, 1.0) if abs(x[2]) < 1.0 - 1e-6 else (1.0, 0.0, 0.0)
    c = ref[0] * x[0] + ref[1] * x[1] + ref[2] * x[2]
    z = (ref[0] - c * x[0], ref[1] - c * x[1], ref[2] - c * x[2])
    nz = math.sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2])
    z = (z[0] / nz, z[1] / nz, z[2] / nz)
    y = (z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0])
    return x, y, z


def grasp_frame(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) whose columns are the grasp frame's axes in world (see grasp_axes)."""
    x, y, z = grasp_axes(tuple(map(float, p0)), tuple(map(float, p1)))
    return np.array([x, y, z]).T


class Actuation:
    """Per-finger actuated directions and the layout of M_a's columns."""

    def __init__(self, directions: list[list[V3]] | list[np.ndarray], frame: str = "world") -> None:
        if frame not in ("world", "grasp"):
            raise ValueError(f"actuation frame must be 'world' or 'grasp', got {frame!r}")
        if frame == "grasp" and len(directions) < 2:
            raise ValueError("the grasp frame needs at least two fingers")
        self.frame = frame
        self.local: list[list[V3]] = [
            [tuple(map(float, d)) for d in np.asarray(ds, dtype=float).reshape(-1, 3)]
            for ds in directions
        ]
        self.n_fingers = len(self.local)
        self.counts = [len(d) for d in self.local]
        starts = [0]
        for c in self.counts:
            starts.append(starts[-1] + c)
        self.columns = [range(starts[i], starts[i + 1]) for i in range(self.n_fingers)]
        self.n_actuators = starts[-1]
        self._world_fixed = self.local if frame == "world" else None

    def world_directions(self, finger_pos: list[V3]) -> list[list[V3]]:
        """Unit directions per finger in world, for fingers at ``finger_pos`` (m)."""
        if self._world_fixed is not None:
            return self._world_fixed
        x, y, z = grasp_axes(finger_pos[0], finger_pos[1])
        return [
            [
                (
                    x[0] * d[0] + y[0] * d[1] + z[0] * d[2],
                    x[1] * d[0] + y[1] * d[1] + z[1] * d[2],
                    x[2] * d[0] + y[2] * d[1] + z[2] * d[2],
                )
                for d in ds
            ]
            for ds in self.local
        ]

    def submatrix(self, world: list[list[V3]], fingers: list[int]) -> tuple[np.ndarray, list[int]]:
        """M_a restricted to ``fingers`` (3p, r_sub) and the global indices of its columns."""
        cols = [c for i in fingers for c in self.columns[i]]
        M = np.zeros((3 * len(fingers), len(cols)))
        j = 0
        for row, i in enumerate(fingers):
            for d in world[i]:
                M[3 * row : 3 * row + 3, j] = d
                j += 1
        return M, cols

    def matrix(self, finger_pos: np.ndarray) -> np.ndarray:
        """The full M_a (3F, r) for fingers at ``finger_pos`` (F, 3) m."""
        world = self.world_directions([tuple(map(float, p)) for p in finger_pos])
        return self.submatrix(world, list(range(self.n_fingers)))[0]
