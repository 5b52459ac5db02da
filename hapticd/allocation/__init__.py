"""Force allocation: contact forces ``lam`` onto the actuated directions ``M_a``.

Solves lam ~= M_a @ lam_a for the actuator forces lam_a. Shapes: G (6, 3p),
M_a (3p, r), lam (3p,), lam_a (r,); forces in N. ``lam`` may be the force on
the object (the seed's convention) or on the finger (hapticd's): every
allocator is linear, so flipping its sign flips lam_a.

Methods (see docs/allocation.md):

- ``pinv``, ``if``, ``ef``: singularity-robust versions of the seed's
  allocators (Meli & Prattichizzo). Equal to the seed's formulas wherever the
  problem is well-conditioned (every singular value involved is 0 or >= eps
  and contacts are at least ``min_separation_m`` apart); near and at
  singularities finite, bounded and continuous.
- ``pinv_exact``, ``if_exact``, ``ef_exact``: the seed's formulas with numpy's
  default pseudoinverse, for comparison. They blow up or jump at singularities.
- ``adaptive``: (1 - alpha) * if + alpha * ef, alpha in [0, 1] from the task
  (0 squeezing a supported object, 1 lifting it); see ``AdaptiveState``.

Robustness scheme: every pseudoinverse is a *filtered* one. A singular value
sigma gets the gain 1/sigma when sigma >= eps and sigma/eps^2 below (damped
least squares with the variable damping mu^2 = eps^2 - sigma^2, which vanishes
away from the singularity). The gain is continuous, zero at sigma = 0 and at
most 1/eps. Trade: below eps the allocation renders less than the exact
formula asks for (which there is unbounded), and two directions that are
nearly dependent share the force smoothly instead of opposing each other.

IF uses the projector form lam_a = x1 + P (M_a P)^+ (lam - M_a x1),
x1 = B^+ P_int lam, B = P_int M_a, P = I - B^+ B, which is continuous when
B changes rank; P_int, the projector onto the internal forces N(G), is also
softened as two contacts approach each other (N(G) grows from the grasp line
to all opposing pairs when they coincide).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hapticd.grasp import null_space_basis

METHODS: tuple[str, ...] = ("pinv", "if", "ef", "adaptive", "pinv_exact", "if_exact", "ef_exact")
ROBUST_METHODS: tuple[str, ...] = ("pinv", "if", "ef", "adaptive")
EXACT_METHODS: tuple[str, ...] = ("pinv_exact", "if_exact", "ef_exact")

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

    Exact (N N^T) when no two contacts are closer than min_separation_m; as
    contacts approach, directions whose moment lever vanishes blend in
    continuously. Computed from G about the contacts' centroid with moments
    weighted by 1/L (N(G) depends on neither).
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


# -- the seed's exact formulas ----------------------------------------------------------------


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


# -- two contacts, one direction each: closed form in plain floats --------------------------
#
# Everything reduces to symmetric 2x2 matrices [[a, b], [b, c]], stored as (a, b, c).

Sym2 = tuple[float, float, float]
V3 = tuple[float, float, float]


def _dot(u: V3, v: V3) -> float:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _cross(u: V3, v: V3) -> V3:
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _finv2(a: float, b: float, c: float, eps2: float) -> Sym2:
    """Filtered inverse of [[a, b], [b, c]] (symmetric PSD): eigenvalues l -> 1/l or 1/eps2."""
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


def _mul2(x: Sym2, y: Sym2) -> tuple[float, float, float, float]:
    """x @ y for symmetric x, y, as a general 2x2 (r00, r01, r10, r11)."""
    return (
        x[0] * y[0] + x[1] * y[1],
        x[0] * y[1] + x[1] * y[2],
        x[1] * y[0] + x[2] * y[1],
        x[1] * y[1] + x[2] * y[2],
    )


def _sandwich(p: Sym2, k: Sym2) -> Sym2:
    """p @ k @ p for symmetric p, k."""
    r00, r01, r10, r11 = _mul2(p, k)
    return (
        r00 * p[0] + r01 * p[1],
        r00 * p[1] + r01 * p[2],
        r10 * p[1] + r11 * p[2],
    )


def _apply(m: Sym2, v0: float, v1: float) -> tuple[float, float]:
    return m[0] * v0 + m[1] * v1, m[1] * v0 + m[2] * v1


def two_contact_pinv(d1: V3, d2: V3, l1: V3, l2: V3, eps: float) -> tuple[float, float]:
    """Robust pinv for two fingers with one unit direction each."""
    eps2 = eps * eps
    k1, k2 = _dot(d1, d1), _dot(d2, d2)
    g1 = 1.0 / k1 if k1 >= eps2 else 1.0 / eps2
    g2 = 1.0 / k2 if k2 >= eps2 else 1.0 / eps2
    return g1 * _dot(d1, l1), g2 * _dot(d2, l2)


def two_contact_ef(
    r1: V3, r2: V3, d1: V3, d2: V3, l1: V3, l2: V3, eps: float
) -> tuple[float, float]:
    """Robust EF for two fingers: r_i contact offsets from the reference point (m)."""
    m1, m2 = _cross(r1, d1), _cross(r2, d2)
    f = (l1[0] + l2[0], l1[1] + l2[1], l1[2] + l2[2])
    t1, t2 = _cross(r1, l1), _cross(r2, l2)
    t = (t1[0] + t2[0], t1[1] + t2[1], t1[2] + t2[2])
    K = (_dot(d1, d1) + _dot(m1, m1), _dot(d1, d2) + _dot(m1, m2), _dot(d2, d2) + _dot(m2, m2))
    y0 = _dot(d1, f) + _dot(m1, t)
    y1 = _dot(d2, f) + _dot(m2, t)
    return _apply(_finv2(*K, eps * eps), y0, y1)


def one_contact(method: str, r: V3, d: V3, lam: V3, eps: float, alpha: float = 0.0) -> float:
    """Robust allocation for one contact with one direction (closed form of the general path).

    With one contact N(G) = {0}, so IF is pinv; EF matches the contact's wrench.
    """
    eps2 = eps * eps
    k = _dot(d, d)
    x_pinv = _dot(d, lam) / (k if k >= eps2 else eps2)
    if method in ("pinv", "if") or (method == "adaptive" and alpha == 0.0):
        return x_pinv
    m = _cross(r, d)
    K = k + _dot(m, m)
    x_ef = (_dot(d, lam) + _dot(m, _cross(r, lam))) / (K if eps2 <= K else eps2)
    if method == "ef":
        return x_ef
    return (1.0 - alpha) * x_pinv + alpha * x_ef


def one_contact_accuracy(r: V3, d: V3, lam: V3, x: float) -> Accuracy:
    """``accuracy`` for one contact with one direction: no internal forces exist."""
    q = (lam[0] - x * d[0], lam[1] - x * d[1], lam[2] - x * d[2])
    t = _cross(r, q)
    n_lam = math.sqrt(_dot(lam, lam))
    total = math.sqrt(_dot(q, q))
    external = math.sqrt(_dot(q, q) + _dot(t, t))
    amp = abs(x) * math.sqrt(_dot(d, d)) / n_lam if n_lam > 0 else 0.0
    return Accuracy(0.0, external, total, amp)


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
    """Robust IF for two fingers with one direction each (closed form of ``_if_general``)."""
    eps2 = eps * eps
    e, w = _grasp_line(r1, r2, min_sep)
    # B's columns are +-(1/2)[a_k; -a_k]; P_int lam = (1/2)[s; -s].
    a1, a2 = _soft_line(e, w, d1), _soft_line(e, w, d2)
    s = _soft_line(e, w, (l1[0] - l2[0], l1[1] - l2[1], l1[2] - l2[2]))
    KB = (0.5 * _dot(a1, a1), -0.5 * _dot(a1, a2), 0.5 * _dot(a2, a2))
    FB = _finv2(*KB, eps2)
    x0, x1 = _apply(FB, 0.5 * _dot(a1, s), -0.5 * _dot(a2, s))
    # P = I - F(K_B) K_B (symmetric: F and K commute).
    r00, r01, _, r11 = _mul2(FB, KB)
    P = (1.0 - r00, -r01, 1.0 - r11)
    # Residual after the internal task, seen by the actuators: M^T (lam - M x).
    k1, k2 = _dot(d1, d1), _dot(d2, d2)
    m0 = _dot(d1, l1) - x0 * k1
    m1 = _dot(d2, l2) - x1 * k2
    # x2 = P F(P K_M P) P M^T r, K_M = diag(k1, k2).
    FP = _finv2(*_sandwich(P, (k1, 0.0, k2)), eps2)
    v0, v1 = _apply(P, m0, m1)
    v0, v1 = _apply(FP, v0, v1)
    v0, v1 = _apply(P, v0, v1)
    return x0 + v0, x1 + v1


def two_contact_structure(G: np.ndarray, M_a: np.ndarray) -> tuple[V3, V3, V3, V3] | None:
    """(r1, r2, d1, d2) if G has two contacts and M_a one direction per finger, else None."""
    if G.shape[1] != 6 or M_a.shape[1] != 2:
        return None
    if np.any(M_a[3:6, 0]) or np.any(M_a[0:3, 1]):
        return None
    off = contact_offsets(G)
    r1 = (float(off[0, 0]), float(off[0, 1]), float(off[0, 2]))
    r2 = (float(off[1, 0]), float(off[1, 1]), float(off[1, 2]))
    d1 = (float(M_a[0, 0]), float(M_a[1, 0]), float(M_a[2, 0]))
    d2 = (float(M_a[3, 1]), float(M_a[4, 1]), float(M_a[5, 1]))
    return r1, r2, d1, d2


# -- public API ---------------------------------------------------------------------------


def _check(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> None:
    if G.ndim != 2 or G.shape[0] != 6 or G.shape[1] % 3:
        raise AllocationError(f"G must have shape (6, 3p), got {G.shape}")
    n = G.shape[1]
    if M_a.ndim != 2 or M_a.shape[0] != n:
        raise AllocationError(f"M_a must have shape ({n}, r) to match G {G.shape}, got {M_a.shape}")
    if lam.shape != (n,):
        raise AllocationError(f"lam must have shape ({n},) to match G {G.shape}, got {lam.shape}")
    for name, arr in (("G", G), ("M_a", M_a), ("lam", lam)):
        if not np.all(np.isfinite(arr)):
            raise AllocationError(f"{name} contains NaN or inf; refusing to compute a force")


_GENERAL: dict[str, Callable[..., np.ndarray]] = {
    "pinv": _pinv_general,
    "if": _if_general,
    "ef": _ef_general,
}
_EXACT: dict[str, Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]] = {
    "pinv_exact": pinv_exact,
    "if_exact": if_exact,
    "ef_exact": ef_exact,
}


def _robust(
    method: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray, robust: Robustness, fast: bool
) -> np.ndarray:
    st = two_contact_structure(G, M) if fast else None
    if st is None:
        return _GENERAL[method](G, M, lam, robust)
    r1, r2, d1, d2 = st
    l1 = (float(lam[0]), float(lam[1]), float(lam[2]))
    l2 = (float(lam[3]), float(lam[4]), float(lam[5]))
    if method == "pinv":
        out = two_contact_pinv(d1, d2, l1, l2, robust.eps)
    elif method == "ef":
        out = two_contact_ef(r1, r2, d1, d2, l1, l2, robust.eps)
    else:
        out = two_contact_if(r1, r2, d1, d2, l1, l2, robust.eps, robust.min_separation_m)
    return np.array(out)


def allocate(
    method: str,
    G: np.ndarray,
    M_a: np.ndarray,
    lam: np.ndarray,
    *,
    robust: Robustness = DEFAULT_ROBUSTNESS,
    alpha: float = 0.0,
    fast: bool = True,
) -> np.ndarray:
    """Actuator forces lam_a (r,) N for contact forces ``lam`` (3p,) N with ``method``.

    ``alpha`` (0..1) is the external-force weight of ``adaptive``. ``fast``
    allows the closed form for two contacts with one direction each (equal to
    the general path to rounding). Raises AllocationError on an unknown method,
    mismatched shapes or NaN/inf input.
    """
    if method not in METHODS:
        raise AllocationError(f"unknown allocator {method!r}; expected one of {list(METHODS)}")
    G = np.asarray(G, dtype=float)
    M_a = np.asarray(M_a, dtype=float)
    lam = np.asarray(lam, dtype=float).reshape(-1)
    _check(G, M_a, lam)
    if M_a.shape[1] == 0:
        return np.zeros(0)
    if method in _EXACT:
        return _EXACT[method](G, M_a, lam)
    if method == "adaptive":
        if not (0.0 <= alpha <= 1.0):
            raise AllocationError(f"adaptive alpha must be in [0, 1], got {alpha}")
        x_if = _robust("if", G, M_a, lam, robust, fast)
        if alpha == 0.0:
            return x_if
        return (1.0 - alpha) * x_if + alpha * _robust("ef", G, M_a, lam, robust, fast)
    return _robust(method, G, M_a, lam, robust, fast)


# -- accuracy measures ----------------------------------------------------------------------


@dataclass(frozen=True)
class Accuracy:
    """How well M_a lam_a renders lam. Residuals in N (external: N and N m stacked).

    internal: |P_N(G) (lam - M_a lam_a)|, the squeeze error; external:
    |G lam - G M_a lam_a|, the net wrench error; total: |lam - M_a lam_a|;
    amplification: |M_a lam_a| / |lam| (0 when lam = 0).
    """

    internal: float
    external: float
    total: float
    amplification: float


def accuracy(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray, lam_a: np.ndarray) -> Accuracy:
    """Accuracy measures of an allocation, with exact subspaces."""
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


def two_contact_accuracy(
    r1: V3, r2: V3, d1: V3, d2: V3, l1: V3, l2: V3, x0: float, x1: float
) -> Accuracy:
    """``accuracy`` for two contacts with one direction each, in closed form."""
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
    return Accuracy(internal, external, total, rendered / n_lam if n_lam > 0 else 0.0)


# -- the task-adaptive allocator's state ----------------------------------------------------


def smoothstep(x: float) -> float:
    """3x^2 - 2x^3 on [0, 1], clamped: a switch with zero slope at both ends."""
    x = 0.0 if x < 0.0 else (1.0 if x > 1.0 else x)
    return x * x * (3.0 - 2.0 * x)


def external_ratio(net_force_n: float, squeeze_n: float) -> float:
    """Share of external force in the task: |net force| / (|net force| + squeeze), 0..1."""
    total = net_force_n + squeeze_n
    return net_force_n / total if total > 0.0 else 0.0


@dataclass
class AdaptiveState:
    """External-force weight alpha of the ``adaptive`` allocator, following the task.

    The target is smoothstep((rho - ratio_low) / (ratio_high - ratio_low)) of the
    external ratio rho (0 while the object is supported); alpha follows it with
    a first-order lag of ``time_constant_s`` so that no switch is a jolt.
    """

    ratio_low: float = 0.2
    ratio_high: float = 0.6
    time_constant_s: float = 0.1
    alpha: float = 0.0

    def target(self, rho: float, supported: bool = False) -> float:
        if supported:
            return 0.0
        return smoothstep((rho - self.ratio_low) / (self.ratio_high - self.ratio_low))

    def update(self, rho: float, dt: float, supported: bool = False) -> float:
        """Advance alpha by ``dt`` (s) toward the target for ``rho``; returns alpha."""
        gain = 1.0 if self.time_constant_s <= 0 else min(1.0, dt / self.time_constant_s)
        self.alpha += gain * (self.target(rho, supported) - self.alpha)
        return self.alpha
