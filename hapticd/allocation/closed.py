"""Closed forms for one contact, and for two contacts with one direction each.

Equal to the general path to rounding and much cheaper; compiled into the servo loop's
kernel. Vectors are 3-tuples of floats: offsets r (m) from G's reference point, unit
directions d, forces l (N). Theory: docs/allocation.md.
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.allocation.robust import _TINY, contact_offsets

Sym2 = tuple[float, float, float]  # the symmetric 2 x 2 [[a, b], [b, c]] as (a, b, c)
V3 = tuple[float, float, float]


def _dot(u: V3, v: V3) -> float:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _cross(u: V3, v: V3) -> V3:
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _finv2(a: float, b: float, c: float, eps2: float) -> Sym2:
    """F(K) of the symmetric PSD K = [[a, b], [b, c]], F(l) = 1/max(l, eps2)."""
    mean = 0.5 * (a + c)
    half = 0.5 * (a - c)
    rad = math.sqrt(half * half + b * b)
    l2 = mean - rad
    if l2 >= eps2:
        det = a * c - b * b
        return c / det, -b / det, a / det
    l1 = mean + rad
    h2 = 1.0 / eps2
    h1 = 1.0 / l1 if l1 >= eps2 else h2
    if h1 == h2:
        return h2, 0.0, h2
    # f(K) = h2 I + (h1 - h2) P1 with the spectral projector P1 = (K - l2 I) / (l1 - l2).
    s = (h1 - h2) / (l1 - l2)
    return h2 + s * (a - l2), s * b, h2 + s * (c - l2)


def _gain(k: float, eps2: float) -> float:
    """Filtered gain 1/k (k >= eps2) or 1/eps2 of a squared length k."""
    return 1.0 / k if k >= eps2 else 1.0 / eps2


def adaptive_mix(x_if: float, x_ef: float, alpha: float) -> float:
    """The adaptive allocator: (1 - alpha) IF + alpha EF, alpha in [0, 1]."""
    return (1.0 - alpha) * x_if + alpha * x_ef


def smoothstep(x: float) -> float:
    """3x^2 - 2x^3 on [0, 1], clamped: a switch with zero slope at both ends."""
    x = 0.0 if x < 0.0 else (1.0 if x > 1.0 else x)
    return x * x * (3.0 - 2.0 * x)


def _apply(m: Sym2, v0: float, v1: float) -> tuple[float, float]:
    return m[0] * v0 + m[1] * v1, m[1] * v0 + m[2] * v1


def two_contact_pinv(d1: V3, d2: V3, l1: V3, l2: V3, eps: float) -> tuple[float, float]:
    """Robust pinv for two fingers with one unit direction each."""
    eps2 = eps * eps
    g1 = _gain(_dot(d1, d1), eps2)
    g2 = _gain(_dot(d2, d2), eps2)
    return g1 * _dot(d1, l1), g2 * _dot(d2, l2)


def two_contact_ef(
    r1: V3, r2: V3, d1: V3, d2: V3, l1: V3, l2: V3, eps: float
) -> tuple[float, float]:
    """Robust EF for two fingers with one direction each."""
    m1, m2 = _cross(r1, d1), _cross(r2, d2)
    f = (l1[0] + l2[0], l1[1] + l2[1], l1[2] + l2[2])
    t1, t2 = _cross(r1, l1), _cross(r2, l2)
    t = (t1[0] + t2[0], t1[1] + t2[1], t1[2] + t2[2])
    K = (_dot(d1, d1) + _dot(m1, m1), _dot(d1, d2) + _dot(m1, m2), _dot(d2, d2) + _dot(m2, m2))
    y0 = _dot(d1, f) + _dot(m1, t)
    y1 = _dot(d2, f) + _dot(m2, t)
    return _apply(_finv2(*K, eps * eps), y0, y1)


def one_contact_pinv(d: V3, lam: V3, eps: float) -> float:
    """Robust pinv (and IF: with one contact N(G) = {0}) for one contact with one direction."""
    eps2 = eps * eps
    k = _dot(d, d)
    return _dot(d, lam) / (k if k >= eps2 else eps2)


def one_contact_ef(r: V3, d: V3, lam: V3, eps: float) -> float:
    """Robust EF for one contact with one direction: matches the contact's wrench."""
    eps2 = eps * eps
    m = _cross(r, d)
    K = _dot(d, d) + _dot(m, m)
    return (_dot(d, lam) + _dot(m, _cross(r, lam))) / (K if eps2 <= K else eps2)


# The robust methods by code (compiled code has no strings).
CODES = ("pinv", "if", "ef", "adaptive")
PINV, IF, EF, ADAPTIVE = 0, 1, 2, 3


def one_contact(code: int, r: V3, d: V3, lam: V3, eps: float, alpha: float) -> float:
    """lam_a N for one contact with one direction by robust method ``code`` (CODES);
    ``alpha`` adaptive's external weight. With one contact N(G) = {0}: IF is pinv."""
    if code == EF:
        return one_contact_ef(r, d, lam, eps)
    x = one_contact_pinv(d, lam, eps)
    if code == ADAPTIVE and alpha != 0.0:
        return adaptive_mix(x, one_contact_ef(r, d, lam, eps), alpha)
    return x


def _grasp_line(r1: V3, r2: V3, min_sep: float) -> tuple[V3, float]:
    """Unit grasp line e (first to second contact) and the blend w toward all opposing pairs."""
    dx, dy, dz = r2[0] - r1[0], r2[1] - r1[1], r2[2] - r1[2]
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    w = 1.0 - (dist / min_sep) ** 2 if dist < min_sep else 0.0
    if dist > _TINY:
        return (dx / dist, dy / dist, dz / dist), w
    return (1.0, 0.0, 0.0), 1.0  # coincident: w = 1 makes e irrelevant


def _soft_line(e: V3, w: float, v: V3) -> V3:
    """(1 - w)(e.v) e + w v: the soft internal projector's action on an opposing pair."""
    s = (1.0 - w) * _dot(e, v)
    return (s * e[0] + w * v[0], s * e[1] + w * v[1], s * e[2] + w * v[2])


def two_contact_if(
    r1: V3, r2: V3, d1: V3, d2: V3, l1: V3, l2: V3, eps: float, min_sep: float
) -> tuple[float, float]:
    """Robust IF for two fingers with one direction each (the projector form)."""
    eps2 = eps * eps
    e, w = _grasp_line(r1, r2, min_sep)
    # B's columns are +-(1/2)[a_k; -a_k]; P_int lam = (1/2)[s; -s].
    a1, a2 = _soft_line(e, w, d1), _soft_line(e, w, d2)
    s = _soft_line(e, w, (l1[0] - l2[0], l1[1] - l2[1], l1[2] - l2[2]))
    KB = (0.5 * _dot(a1, a1), -0.5 * _dot(a1, a2), 0.5 * _dot(a2, a2))
    FB = _finv2(*KB, eps2)
    x0, x1 = _apply(FB, 0.5 * _dot(a1, s), -0.5 * _dot(a2, s))
    # P = I - F(K_B) K_B (symmetric: F and K commute).
    p0 = 1.0 - (FB[0] * KB[0] + FB[1] * KB[1])
    p1 = -(FB[0] * KB[1] + FB[1] * KB[2])
    p2 = 1.0 - (FB[1] * KB[1] + FB[2] * KB[2])
    # Residual after the internal task, seen by the actuators: M^T (lam - M x).
    k1, k2 = _dot(d1, d1), _dot(d2, d2)
    m0 = _dot(d1, l1) - x0 * k1
    m1 = _dot(d2, l2) - x1 * k2
    # x2 = P F(P K_M P) P M^T r, K_M = diag(k1, k2).
    P = (p0, p1, p2)
    FP = _finv2(
        p0 * k1 * p0 + p1 * k2 * p1, p0 * k1 * p1 + p1 * k2 * p2, p1 * k1 * p1 + p2 * k2 * p2, eps2
    )
    v0, v1 = _apply(P, m0, m1)
    v0, v1 = _apply(FP, v0, v1)
    v0, v1 = _apply(P, v0, v1)
    return x0 + v0, x1 + v1


def two_contact_structure(G: np.ndarray, M_a: np.ndarray) -> tuple[V3, V3, V3, V3] | None:
    """(r1, r2, d1, d2) if G has two contacts and M_a one direction per finger, else None."""
    if G.shape[1] != 6 or M_a.shape[1] != 2 or np.any(M_a[3:6, 0]) or np.any(M_a[0:3, 1]):
        return None
    r1, r2 = (tuple(r) for r in contact_offsets(G).tolist())
    return r1, r2, tuple(M_a[0:3, 0].tolist()), tuple(M_a[3:6, 1].tolist())


def two_contact(
    code: int,
    r1: V3,
    r2: V3,
    d1: V3,
    d2: V3,
    l1: V3,
    l2: V3,
    eps: float,
    min_sep: float,
    alpha: float,
) -> tuple[float, float]:
    """(x1, x2) N for two contacts with one direction each by robust method ``code``
    (CODES); ``alpha`` adaptive's external weight (the others ignore it)."""
    if code == PINV:
        return two_contact_pinv(d1, d2, l1, l2, eps)
    if code == EF:
        return two_contact_ef(r1, r2, d1, d2, l1, l2, eps)
    x0, x1 = two_contact_if(r1, r2, d1, d2, l1, l2, eps, min_sep)
    if code == ADAPTIVE and alpha != 0.0:
        y0, y1 = two_contact_ef(r1, r2, d1, d2, l1, l2, eps)
        return adaptive_mix(x0, y0, alpha), adaptive_mix(x1, y1, alpha)
    return x0, x1


# What compiled code calls (hapticd.physics.jit compiles them into the kernels).
KERNEL_HELPERS = (
    _dot,
    _cross,
    _apply,
    _soft_line,
    _finv2,
    _gain,
    _grasp_line,
    two_contact_pinv,
    two_contact_ef,
    two_contact_if,
    one_contact_pinv,
    one_contact_ef,
    adaptive_mix,
    smoothstep,
    one_contact,
    two_contact,
)
