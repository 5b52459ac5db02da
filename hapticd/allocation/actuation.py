"""Actuation matrix M_a: which force directions each finger's device renders.

Underactuation is simulated in software: finger i renders only along its
unit directions d_i1..d_ik (0 to 3 of them). M_a is (3F, r), block diagonal,
column j of finger i holding d_ij in rows 3i..3i+2; r is the total number of
actuated directions. Directions are given in the world frame or in the grasp
frame (x from the first finger to the second, z as close to world up as
possible, y = z cross x), which follows the fingers.
"""

from __future__ import annotations

import numpy as np

from hapticd.allocation import kernels

V3 = tuple[float, float, float]


def grasp_axes(p0: V3, p1: V3) -> tuple[V3, V3, V3]:
    """Grasp frame axes (x, y, z) in world, for fingers at p0 and p1 (m): the tick's own
    (hapticd.allocation.kernels.grasp_axes). x = unit(p1 - p0); z = world up made orthogonal
    to x; y = z cross x. Degenerate cases fall back to world axes: coincident points use
    world x; a vertical grasp line uses world x in place of up."""
    a = kernels.grasp_axes(p0[0], p0[1], p0[2], p1[0], p1[1], p1[2])
    return (a[0], a[1], a[2]), (a[3], a[4], a[5]), (a[6], a[7], a[8])


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
