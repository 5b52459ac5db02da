"""The singularity-robust general path: filtered pseudoinverses and the soft internal projector.

Shapes: G (6, 3p), M_a (3p, r), lam (3p,); forces in N, lengths in m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEFAULT_EPS = 0.2
DEFAULT_MIN_SEPARATION_M = 0.005
DEFAULT_CONTACT_ONSET_N = 0.05
_TINY = 1e-300


class AllocationError(ValueError):
    """Raised for malformed or non-finite allocation inputs."""


@dataclass(frozen=True)
class Robustness:
    """Parameters of the robust allocators.

    eps: singular-value threshold (dimensionless: directions are unit vectors,
    moments are in N m per N); below it pseudoinverse gains are damped.
    min_separation_m: contacts closer than this (m) blend the internal subspace
    toward every opposing pair of forces.
    contact_onset_n: a contact whose force is below this (N) joins the grasp
    gradually (the renderer blends the allocations with and without it).
    """

    eps: float = DEFAULT_EPS
    min_separation_m: float = DEFAULT_MIN_SEPARATION_M
    contact_onset_n: float = DEFAULT_CONTACT_ONSET_N

    def __post_init__(self) -> None:
        ok = 0 < self.eps < 1 and 0 < self.min_separation_m < 1 and 0 <= self.contact_onset_n < 10
        if not ok:
            raise ValueError(f"invalid robustness parameters {self}")

    @property
    def length_scale_m(self) -> float:
        """Moment weighting length L: two contacts at min_separation_m give sigma = eps."""
        return self.min_separation_m / (math.sqrt(2.0) * self.eps)


DEFAULT_ROBUSTNESS = Robustness()


# -- general path (numpy, any number of contacts and directions) ---------------------------


def filtered_gain(s: np.ndarray, eps: float) -> np.ndarray:
    """Gain per singular value: 1/s for s >= eps, s/eps^2 below (continuous, <= 1/eps)."""
    s = np.asarray(s, dtype=float)
    out = s / (eps * eps)
    big = s >= eps
    out[big] = 1.0 / s[big]
    return out


def filtered_pinv(A: np.ndarray, eps: float) -> np.ndarray:
    """Filtered pseudoinverse of A (m, n): sum g(s_i) v_i u_i^T, shape (n, m)."""
    A = np.atleast_2d(A)
    if A.size == 0:
        return np.zeros((A.shape[1], A.shape[0]))
    u, s, vt = np.linalg.svd(A, full_matrices=False)
    return (vt.T * filtered_gain(s, eps)) @ u.T


def contact_offsets(G: np.ndarray) -> np.ndarray:
    """Contact points relative to G's reference point, (p, 3) m, read off G's moment rows."""
    p = G.shape[1] // 3
    out = np.empty((p, 3))
    for i in range(p):
        S = G[3:6, 3 * i : 3 * i + 3]
        out[i] = (S[2, 1], S[0, 2], S[1, 0])
    return out


def soft_internal_projector(G: np.ndarray, robust: Robustness = DEFAULT_ROBUSTNESS) -> np.ndarray:
    """Soft projector onto the internal forces N(G), (3p, 3p).

    Exact (N N^T) when every singular value of the weighted G below is 0 or at
    least eps: for two contacts, when they are at least min_separation_m apart;
    three or more contacts also need to be far from collinear (a rotation about
    their near-common line has almost no lever). As contacts approach such a
    configuration, directions whose moment lever vanishes blend in continuously.
    Computed from G about the contacts' centroid with moments weighted by 1/L
    (N(G) depends on neither).
    """
    n = G.shape[1]
    if n == 0:
        return np.zeros((0, 0))
    pts = contact_offsets(G)
    pts = pts - pts.mean(axis=0)
    L = robust.length_scale_m
    Gw = np.zeros((6, n))
    for i, c in enumerate(pts):
        Gw[0:3, 3 * i : 3 * i + 3] = np.eye(3)
        x, y, z = c / L
        Gw[3:6, 3 * i : 3 * i + 3] = [[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]
    _, s, vt = np.linalg.svd(Gw, full_matrices=True)
    keep = np.ones(n)
    k = s.size
    keep[:k] = 1.0 - np.minimum(1.0, (s / robust.eps) ** 2)
    return (vt.T * keep) @ vt


def _pinv_general(G, M, lam, robust: Robustness) -> np.ndarray:
    return filtered_pinv(M, robust.eps) @ lam


def _ef_general(G, M, lam, robust: Robustness) -> np.ndarray:
    return filtered_pinv(G @ M, robust.eps) @ (G @ lam)


def _if_general(G, M, lam, robust: Robustness) -> np.ndarray:
    P_int = soft_internal_projector(G, robust)
    B = P_int @ M
    B_pinv = filtered_pinv(B, robust.eps)
    x1 = B_pinv @ (P_int @ lam)
    P = np.eye(M.shape[1]) - B_pinv @ B
    P = 0.5 * (P + P.T)
    return x1 + P @ (filtered_pinv(M @ P, robust.eps) @ (lam - M @ x1))
