"""How well an allocation renders the contact forces (docs/allocation.md, "Accuracy measures")."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapticd.allocation.closed import V3, _cross, _dot
from hapticd.allocation.grasp import null_space_basis


@dataclass(frozen=True)
class Accuracy:
    """Residuals of res = lam - M_a lam_a in N: internal |N_G^T res| (squeeze), external
    |G res| (net wrench, N and N m stacked), total |res|; amplification |M_a lam_a| / |lam|
    (0 when lam = 0)."""

    internal: float
    external: float
    total: float
    amplification: float


def accuracy(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray, lam_a: np.ndarray) -> Accuracy:
    """``Accuracy`` of lam_a (r,) N for lam (3p,) N, G (6, 3p), M_a (3p, r); exact subspaces."""
    rendered = M_a @ lam_a
    res = lam - rendered
    N = null_space_basis(G)
    n_lam = float(np.linalg.norm(lam))
    return Accuracy(
        internal=float(np.linalg.norm(N.T @ res)),
        external=float(np.linalg.norm(G @ res)),
        total=float(np.linalg.norm(res)),
        amplification=float(np.linalg.norm(rendered)) / n_lam if n_lam > 0 else 0.0,
    )


def two_contact_residuals(
    r1: V3, r2: V3, d1: V3, d2: V3, l1: V3, l2: V3, x0: float, x1: float
) -> tuple[float, float, float, float]:
    """``accuracy`` for two contacts with one direction each, as (internal, external,
    total, amplification); compiled into the loop's kernel."""
    q1 = (l1[0] - x0 * d1[0], l1[1] - x0 * d1[1], l1[2] - x0 * d1[2])
    q2 = (l2[0] - x1 * d2[0], l2[1] - x1 * d2[1], l2[2] - x1 * d2[2])
    diff = (q1[0] - q2[0], q1[1] - q2[1], q1[2] - q2[2])
    dx, dy, dz = r2[0] - r1[0], r2[1] - r1[1], r2[2] - r1[2]
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    if dist > 0.0:
        internal = abs(dx * diff[0] + dy * diff[1] + dz * diff[2]) / dist / math.sqrt(2.0)
    else:  # coincident contacts: every opposing pair is internal
        internal = math.sqrt(_dot(diff, diff) / 2.0)
    f = (q1[0] + q2[0], q1[1] + q2[1], q1[2] + q2[2])
    t1, t2 = _cross(r1, q1), _cross(r2, q2)
    t = (t1[0] + t2[0], t1[1] + t2[1], t1[2] + t2[2])
    external = math.sqrt(_dot(f, f) + _dot(t, t))
    total = math.sqrt(_dot(q1, q1) + _dot(q2, q2))
    n_lam = math.sqrt(_dot(l1, l1) + _dot(l2, l2))
    rendered = math.sqrt(x0 * x0 * _dot(d1, d1) + x1 * x1 * _dot(d2, d2))
    return internal, external, total, rendered / n_lam if n_lam > 0 else 0.0


def one_contact_residuals(r: V3, d: V3, lam: V3, x: float) -> tuple[float, float, float, float]:
    """``accuracy`` for one contact with one direction (no internal forces exist), as
    (internal, external, total, amplification); compiled into the loop's kernel."""
    q = (lam[0] - x * d[0], lam[1] - x * d[1], lam[2] - x * d[2])
    t = _cross(r, q)
    n_lam = math.sqrt(_dot(lam, lam))
    total = math.sqrt(_dot(q, q))
    external = math.sqrt(_dot(q, q) + _dot(t, t))
    amp = abs(x) * math.sqrt(_dot(d, d)) / n_lam if n_lam > 0 else 0.0
    return 0.0, external, total, amp
