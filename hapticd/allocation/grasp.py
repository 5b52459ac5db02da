"""Grasp matrix and its subspaces for hard-finger (point) contacts.

Conventions (see docs/math.md):
- contact points are stacked row-wise, shape (p, 3), in metres, world frame;
- force vectors ``lam`` are stacked per contact, shape (3p,), in newtons;
- ``G`` is (6, 3p): rows 0-2 force, rows 3-5 moment about ``center`` (N m);
  block i is [I3; S(c_i - center)], so w = G @ lam is the net wrench of ``lam``.

Pure functions: numpy in, numpy out.
"""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix S(v), shape (3, 3), with S(v) @ u == cross(v, u)."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def grasp_matrix(points: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Grasp matrix G (6, 3p) of p hard-finger contacts about ``center``.

    points: (p, 3) contact points in m; center: (3,) reference point in m.
    Columns 3i..3i+2 belong to contact i, in the order given.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    c = np.asarray(center, dtype=float).reshape(3)
    p = pts.shape[0]
    G = np.zeros((6, 3 * p))
    for i in range(p):
        G[0:3, 3 * i : 3 * i + 3] = np.eye(3)
        G[3:6, 3 * i : 3 * i + 3] = skew(pts[i] - c)
    return G


def _rank_tol(s: np.ndarray, shape: tuple[int, ...]) -> float:
    """numpy's default rank tolerance for singular values ``s`` of a matrix of ``shape``."""
    if s.size == 0:
        return 0.0
    return float(s.max()) * max(shape) * np.finfo(float).eps


def null_space_basis(A: np.ndarray) -> np.ndarray:
    """Orthonormal basis of N(A), shape (n, n - rank A), from the SVD.

    The rank uses numpy's default tolerance (max(s) * max(shape) * eps).
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    m, n = A.shape
    if m == 0:
        return np.eye(n)
    _, s, vt = np.linalg.svd(A, full_matrices=True)
    rank = int(np.sum(s > _rank_tol(s, A.shape)))
    return vt[rank:].T.copy()


def internal_projector(G: np.ndarray) -> np.ndarray:
    """Orthogonal projector onto N(G), the internal (self-balanced) forces, (3p, 3p)."""
    N = null_space_basis(G)
    return N @ N.T


def decompose(G: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split ``lam`` (3p,) into (internal, external) parts: N(G) and R(G^T) components."""
    P = internal_projector(G)
    lam = np.asarray(lam, dtype=float)
    internal = P @ lam
    return internal, lam - internal
