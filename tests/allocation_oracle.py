"""An independent oracle for the robust allocators: their definition by singular value
decompositions, one grasp at a time (docs/allocation.md), written from the SVD rather
than from hapticd.allocation.batch's Gram matrices and closed forms. Tests only.

Shapes: G (6, 3p), M_a (3p, r), lam (3p,); forces in N, lengths in m.
"""

from __future__ import annotations

import numpy as np

from hapticd.allocation import Robustness


def filtered_gain(s: np.ndarray, eps: float) -> np.ndarray:
    """Gain per singular value: 1/s for s >= eps, s/eps^2 below (continuous, <= 1/eps)."""
    s = np.asarray(s, dtype=float)
    return np.where(s >= eps, 1.0 / np.where(s >= eps, s, 1.0), s / (eps * eps))


def svd_pinv(A: np.ndarray, eps: float) -> np.ndarray:
    """Filtered pseudoinverse sum g(s_i) v_i u_i^T of A (m, n), (n, m)."""
    if A.size == 0:
        return np.zeros((A.shape[1], A.shape[0]))
    u, s, vt = np.linalg.svd(A, full_matrices=False)
    return (vt.T * filtered_gain(s, eps)) @ u.T


def svd_internal_projector(G: np.ndarray, robust: Robustness) -> np.ndarray:
    """V diag(1 - min(1, s^2 / eps^2)) V^T of G about the contacts' centroid, moments / L."""
    n = G.shape[1]
    pts = np.array([[G[5, 3 * i + 1], G[3, 3 * i + 2], G[4, 3 * i]] for i in range(n // 3)])
    pts = (pts - pts.mean(axis=0)) / robust.length_scale_m
    Gw = np.zeros((6, n))
    for i, (x, y, z) in enumerate(pts):
        Gw[0:3, 3 * i : 3 * i + 3] = np.eye(3)
        Gw[3:6, 3 * i : 3 * i + 3] = [[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]
    _, s, vt = np.linalg.svd(Gw, full_matrices=True)
    keep = np.ones(n)
    keep[: s.size] = 1.0 - np.minimum(1.0, (s / robust.eps) ** 2)
    return (vt.T * keep) @ vt


def robust_allocation(
    method: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray, robust: Robustness, alpha=0.0
) -> np.ndarray:
    """lam_a (r,) N of robust ``method`` (pinv, if, ef, adaptive with weight ``alpha``)."""
    eps = robust.eps
    if method == "pinv":
        return svd_pinv(M, eps) @ lam
    if method == "ef":
        return svd_pinv(G @ M, eps) @ (G @ lam)
    if method == "adaptive":
        x_if = robust_allocation("if", G, M, lam, robust)
        return (1.0 - alpha) * x_if + alpha * robust_allocation("ef", G, M, lam, robust)
    P_int = svd_internal_projector(G, robust)
    B = P_int @ M
    B_pinv = svd_pinv(B, eps)
    x1 = B_pinv @ (P_int @ lam)
    P = np.eye(M.shape[1]) - B_pinv @ B
    P = 0.5 * (P + P.T)
    return x1 + P @ (svd_pinv(M @ P, eps) @ (lam - M @ x1))
