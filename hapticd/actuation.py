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

_DEGENERATE = 1e-9


def grasp_frame(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) whose columns are the grasp frame's x, y, z axes in world.

    x = unit(p1 - p0); z = world up made orthogonal to x. Degenerate cases fall
    back to world axes: coincident points use world x; a vertical grasp line
    uses world x in place of up.
    """
    ex, ey, ez = float(p1[0] - p0[0]), float(p1[1] - p0[1]), float(p1[2] - p0[2])
    n = math.sqrt(ex * ex + ey * ey + ez * ez)
    x = (ex / n, ey / n, ez / n) if n > _DEGENERATE else (1.0, 0.0, 0.0)
    ref = (0.0, 0.0, 1.0) if abs(x[2]) < 1.0 - 1e-6 else (1.0, 0.0, 0.0)
    c = ref[0] * x[0] + ref[1] * x[1] + ref[2] * x[2]
    z = (ref[0] - c * x[0], ref[1] - c * x[1], ref[2] - c * x[2])
    nz = math.sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2])
    z = (z[0] / nz, z[1] / nz, z[2] / nz)
    y = (z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0])
    return np.array([[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]])


class Actuation:
    """Per-finger actuated directions and the layout of M_a's columns."""

    def __init__(self, directions: list[np.ndarray], frame: str = "world") -> None:
        if frame not in ("world", "grasp"):
            raise ValueError(f"actuation frame must be 'world' or 'grasp', got {frame!r}")
        if frame == "grasp" and len(directions) < 2:
            raise ValueError("the grasp frame needs at least two fingers")
        self.frame = frame
        self.local = [np.asarray(d, dtype=float).reshape(-1, 3) for d in directions]
        self.n_fingers = len(self.local)
        counts = [d.shape[0] for d in self.local]
        starts = np.concatenate([[0], np.cumsum(counts)]).astype(int)
        self.columns = [slice(int(starts[i]), int(starts[i + 1])) for i in range(self.n_fingers)]
        self.n_actuators = int(starts[-1])
        self._M = np.zeros((3 * self.n_fingers, self.n_actuators))
        if frame == "world":
            self._fill(np.eye(3))

    def _fill(self, R: np.ndarray) -> None:
        for i, d in enumerate(self.local):
            self._M[3 * i : 3 * i + 3, self.columns[i]] = R @ d.T

    def matrix(self, finger_pos: np.ndarray) -> np.ndarray:
        """M_a (3F, r) for fingers at ``finger_pos`` (F, 3) m. Returns an internal buffer."""
        if self.frame == "grasp":
            self._fill(grasp_frame(finger_pos[0], finger_pos[1]))
        return self._M

    def select(self, M: np.ndarray, fingers: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns of M_a for a subset of fingers: (sub-matrix, column indices)."""
        rows = np.concatenate([np.arange(3 * i, 3 * i + 3) for i in fingers])
        cols = np.concatenate(
            [np.arange(self.columns[i].start, self.columns[i].stop) for i in fingers]
        )
        return M[np.ix_(rows, cols)], cols
