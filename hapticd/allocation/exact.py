"""The seed's allocators as published, with numpy's pseudoinverse (docs/math.md).

Kept for comparison: they blow up or jump at singularities.
"""

from __future__ import annotations

import numpy as np

from hapticd.allocation.grasp import null_space_basis


def pinv_exact(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Seed eq. (2): lam_a = M_a^# lam (G unused)."""
    return np.linalg.pinv(M_a) @ lam


def if_exact(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Seed's IF: lam_a = B^# N_G^T lam + N_B (M_a N_B)^# (I - M_a B^# N_G^T) lam, B = N_G^T M_a."""
    N_G = null_space_basis(G)
    B = N_G.T @ M_a
    B_pinv = np.linalg.pinv(B) if B.size else np.zeros((M_a.shape[1], 0))
    first = B_pinv @ (N_G.T @ lam)
    N_B = null_space_basis(B) if B.size else np.eye(M_a.shape[1])
    if N_B.shape[1] == 0:
        return first
    rest = lam - M_a @ first
    return first + N_B @ (np.linalg.pinv(M_a @ N_B) @ rest)


def ef_exact(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Seed's EF: lam_a = (G M_a)^# G lam."""
    return np.linalg.pinv(G @ M_a) @ (G @ lam)
