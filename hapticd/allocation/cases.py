"""Allocation problems sweeping through each kind of singular configuration.

Each sweep maps t (singular at t = 0) to (G, M_a, lam) for two contacts 50 mm apart:
for testing and benchmarking an allocator.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hapticd.allocation.grasp import grasp_matrix

Problem = tuple[np.ndarray, np.ndarray, np.ndarray]

_PAIR = np.array([[-0.025, 0.0, 0.0], [0.025, 0.0, 0.0]])


def block_actuation(dirs_per_finger: list[list[tuple[float, float, float]]]) -> np.ndarray:
    """Block-diagonal M_a (3F, r) from per-finger direction lists (normalised here)."""
    r = sum(len(d) for d in dirs_per_finger)
    M = np.zeros((3 * len(dirs_per_finger), r))
    j = 0
    for i, ds in enumerate(dirs_per_finger):
        for d in ds:
            v = np.asarray(d, dtype=float)
            M[3 * i : 3 * i + 3, j] = v / np.linalg.norm(v)
            j += 1
    return M


def _b_rank(t: float) -> Problem:
    # Both actuators turn vertical at t = 0: B = N_G^T M_a loses rank (IF's trap).
    M = block_actuation([[(np.sin(t), 0, np.cos(t))], [(-np.sin(t), 0, np.cos(t))]])
    return grasp_matrix(_PAIR, np.zeros(3)), M, np.array([1.0, 0, 0.2, -1.0, 0, 0.2])


def _gm_rank(t: float) -> Problem:
    # Actuators along the grasp line at t = 0 cancel in every external wrench: G M_a loses rank.
    M = block_actuation([[(1, 0, t)], [(-1, 0, t)]])
    return grasp_matrix(_PAIR, np.zeros(3)), M, np.array([1.0, 0, 0.4, -1.0, 0, 0.4])


def _m_rank(t: float) -> Problem:
    # The thumb's two directions become parallel at t = 0: M_a loses rank.
    M = block_actuation([[(1, 0, 0), (1, t, 0)], [(-1, 0, 0.2)]])
    return grasp_matrix(_PAIR, np.zeros(3)), M, np.array([1.0, 0.5, 0.1, -1.0, 0, 0.1])


def _coincident(t: float) -> Problem:
    # The contacts pass through each other at t = 0: N(G) changes dimension.
    pts = np.array([[0.0, 0, 0], [t, 0.3 * t, 0]])
    M = block_actuation([[(1, 0, 0.5)], [(-1, 0.2, 0.5)]])
    return grasp_matrix(pts, np.array([0, 0, -0.02])), M, np.array([1.0, 0.3, 0.1, -1.0, 0, 0.1])


# name -> (problem at t, the allocator whose exact formula is singular there, or None)
SWEEPS: dict[str, tuple[Callable[[float], Problem], str | None]] = {
    "B loses rank": (_b_rank, "if"),
    "G M_a loses rank": (_gm_rank, "ef"),
    "M_a loses rank": (_m_rank, "pinv"),
    "coincident contacts": (_coincident, "if"),
}


def sweep(name: str, half_width: float = 0.05, n: int = 2001) -> list[Problem]:
    """Problems along sweep ``name`` for t in [-half_width, half_width] (through 0)."""
    make, _ = SWEEPS[name]
    return [make(float(t)) for t in np.linspace(-half_width, half_width, n)]
