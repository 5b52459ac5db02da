"""The one definition of the robust allocators' general path, on stacks of grasps.

Shapes: G (N, 6, 3p), M_a (N, 3p, r) or shared (3p, r), lam (N, 3p) -> lam_a (N, r);
forces in N, lengths in m. Pure: numpy in, numpy out. ``allocate()`` is this with
N = 1; ``allocate_many`` runs it on a batch (in chunks); the servo loop's Allocation
stage runs it for the grasps its kernel does not take.

- two contacts with one direction each run the closed forms of
  ``hapticd.allocation.closed``, elementwise over the batch (the same code the
  kernel compiles, on arrays);
- every other grasp takes the general path on Gram matrices: a filtered
  pseudoinverse g(s) = 1/s or s/eps^2 of A is F(A^T A) A^T with F the spectral
  function 1/max(l, eps^2) of the Gram matrix. Where every eigenvalue is at
  least eps^2 (most grasps) F is the plain inverse, by cofactors for r <= 3;
  the rest take a stacked ``eigh`` (never an SVD). The soft internal projector
  is I - (1/p) sum of force blocks - Gm^T F(Gm Gm^T) Gm, since about the
  contacts' centroid the weighted G's Gram matrix is block diagonal
  (p I3, Gm Gm^T);
- the exact (seed) methods call ``hapticd.allocation.exact`` grasp by grasp.
"""

from __future__ import annotations

import numpy as np

from hapticd import params
from hapticd.allocation import exact
from hapticd.allocation.closed import CODES, adaptive_mix, two_contact
from hapticd.allocation.robust import (
    DEFAULT_ROBUSTNESS,
    AllocationError,
    Robustness,
)

_METHODS: tuple[str, ...] = tuple(params.ALLOCATORS)
_EXACT = tuple(m for m in _METHODS if m.endswith("_exact"))
CHUNK = 1024  # grasps per internal pass of allocate_many

# -- validation -------------------------------------------------------------------------------


def _first_bad(arr: np.ndarray) -> int | None:
    """Index of the first grasp (axis 0) holding NaN or inf, or None."""
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(np.sum(arr)):  # NaN and inf propagate into the sum: all finite
            return None
    bad = ~np.isfinite(arr.reshape(arr.shape[0], -1)).all(axis=1)
    return int(np.argmax(bad)) if bad.any() else None


def _check(
    method: str, G: object, M_a: object, lam: object, alpha: object
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if method not in _METHODS:
        raise AllocationError(f"unknown allocator {method!r}; expected one of {list(_METHODS)}")
    G = np.asarray(G, dtype=float)
    if G.ndim != 3 or G.shape[1] != 6 or G.shape[2] % 3:
        raise AllocationError(f"G must have shape (N, 6, 3p), got {G.shape}")
    N, _, n = G.shape
    M = np.asarray(M_a, dtype=float)
    if not (M.ndim == 2 and M.shape[0] == n) and not (M.ndim == 3 and M.shape[:2] == (N, n)):
        raise AllocationError(
            f"M_a must have shape ({N}, {n}, r) or shared ({n}, r) to match G {G.shape}, "
            f"got {M.shape}"
        )
    lam_arr = np.asarray(lam, dtype=float)
    if lam_arr.shape != (N, n):
        raise AllocationError(
            f"lam must have shape ({N}, {n}) to match G {G.shape}, got {lam_arr.shape}"
        )
    a = np.zeros(N)  # other methods ignore alpha, as allocate() does
    if method == "adaptive":
        a = np.asarray(alpha, dtype=float)
        if a.ndim > 1 or (a.ndim == 1 and a.shape != (N,)):
            raise AllocationError(f"alpha must be a scalar or have shape ({N},), got {a.shape}")
        if not np.all((a >= 0.0) & (a <= 1.0)):  # False for NaN too
            raise AllocationError("adaptive alpha must be in [0, 1] (and finite)")
        a = np.broadcast_to(a, (N,)).astype(float)
    for name, arr in (("G", G), ("lam", lam_arr)):
        k = _first_bad(arr) if arr.size else None
        if k is not None:
            raise AllocationError(
                f"{name} contains NaN or inf (grasp {k}); refusing to compute a force"
            )
    if M.ndim == 2:
        if not np.all(np.isfinite(M)):
            raise AllocationError("M_a contains NaN or inf; refusing to compute a force")
    elif N and M.size and (k := _first_bad(M)) is not None:
        raise AllocationError(f"M_a contains NaN or inf (grasp {k}); refusing to compute a force")
    return G, M, lam_arr, a


# -- the two-contact closed form, elementwise over the batch ---------------------------------
#
# hapticd.allocation.closed's functions themselves, on tuples of arrays (one entry per grasp).


def _two_contact_v(method: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray, robust) -> tuple:
    """(x1, x2) arrays (N,) for two contacts with one direction each, robust ``method``."""
    # Components as contiguous rows (strided columns make every elementwise op slow).
    # contact_offsets: (S[2, 1], S[0, 2], S[1, 0]) of each contact's moment block.
    r = G[:, [5, 3, 4, 5, 3, 4], [1, 2, 0, 4, 5, 3]].T.copy()
    d = M[:, [0, 1, 2, 3, 4, 5], [0, 0, 0, 1, 1, 1]].T.copy()
    f = lam.T.copy()
    if G.shape[0] == 1:  # on floats (what compiled code runs): far quicker for one grasp
        r, d, f = r[:, 0].tolist(), d[:, 0].tolist(), f[:, 0].tolist()
    r1, r2 = (r[0], r[1], r[2]), (r[3], r[4], r[5])
    d1, d2 = (d[0], d[1], d[2]), (d[3], d[4], d[5])
    l1, l2 = (f[0], f[1], f[2]), (f[3], f[4], f[5])
    eps, sep = robust.eps, robust.min_separation_m
    x0, x1 = two_contact(CODES.index(method), r1, r2, d1, d2, l1, l2, eps, sep, 0.0)
    return np.reshape(x0, -1), np.reshape(x1, -1)


# -- the general path on Gram matrices --------------------------------------------------------


def _tr(A: np.ndarray) -> np.ndarray:
    return np.swapaxes(A, -1, -2)


def _gram(A: np.ndarray) -> np.ndarray:
    """A^T A on stacks (a contiguous A^T: matmul is twice as fast as with a transposed view)."""
    return np.ascontiguousarray(_tr(A)) @ A


def _spectral(f: np.ndarray, V: np.ndarray) -> np.ndarray:
    """V diag(f) V^T on stacks."""
    return (V * f[..., None, :]) @ _tr(V)


def _finv_eigh(K: np.ndarray, eps2: float) -> np.ndarray:
    lk, V = np.linalg.eigh(K)
    return _spectral(1.0 / np.maximum(lk, eps2), V)


def _solve_regular(K: np.ndarray, y: np.ndarray, eps2: float) -> tuple[np.ndarray, np.ndarray]:
    """(K^-1 y, regular) for stacks of symmetric K (N, r, r), r <= 3, and y (N, r), by cofactors.

    ``regular`` marks K - eps^2 I positive definite (Sylvester: leading minors > 0),
    where the filtered inverse is the plain inverse; elsewhere the result is garbage.
    """
    N, r, _ = K.shape
    k = K.reshape(N, r * r).T.copy()  # contiguous rows: strided columns are slow
    v = y.T.copy()
    if r == 1:
        return (v[0] / np.maximum(k[0], eps2))[:, None], np.ones(N, dtype=bool)
    if r == 2:
        a, b, d = k[0], k[2], k[3]
        ae = a - eps2
        regular = (ae > 0.0) & (ae * (d - eps2) - b * b > 0.0)
        det = np.where(regular, a * d - b * b, 1.0)
        return np.stack([d * v[0] - b * v[1], a * v[1] - b * v[0]], -1) / det[:, None], regular
    a, b, c, d, e, f = k[0], k[3], k[6], k[4], k[7], k[8]
    ae, de, fe = a - eps2, d - eps2, f - eps2
    m3 = ae * (de * fe - e * e) + b * (c * e - b * fe) + c * (b * e - c * de)
    regular = (ae > 0.0) & (ae * de - b * b > 0.0) & (m3 > 0.0)
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = np.where(regular, a * c00 + b * c01 + c * c02, 1.0)
    x = np.stack(
        [
            c00 * v[0] + c01 * v[1] + c02 * v[2],
            c01 * v[0] + c11 * v[1] + c12 * v[2],
            c02 * v[0] + c12 * v[1] + c22 * v[2],
        ],
        -1,
    )
    return x / det[:, None], regular


def _finv_apply(K: np.ndarray, y: np.ndarray, eps2: float) -> np.ndarray:
    """F(K) y for stacks of symmetric PSD K (N, r, r) or one shared (r, r), y (N, r).

    F is the filtered inverse, eigenvalue l -> 1/max(l, eps^2); F(A^T A) A^T is the
    filtered pseudoinverse sum g(s) v u^T of A, g(s) = 1/s or s/eps^2. Where every
    eigenvalue is >= eps^2, F(K) = K^-1 (cofactors for r <= 3, much cheaper than a
    stacked eigh); the others take the eigendecomposition.
    """
    if K.ndim == 2:
        return y @ _finv_eigh(K, eps2).T
    if K.shape[-1] > 3:
        return _mv(_finv_eigh(K, eps2), y)
    x, regular = _solve_regular(K, y, eps2)
    if not regular.all():
        odd = np.flatnonzero(~regular)
        x[odd] = _mv(_finv_eigh(K[odd], eps2), y[odd])
    return x


def _mv(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A @ x on stacks: A (..., m, n), x (..., n) -> (..., m)."""
    return (A @ x[..., None])[..., 0]


def _soft_internal_projector_v(G: np.ndarray, robust: Robustness) -> np.ndarray:
    """Stacked soft_internal_projector (N, 3p, 3p), from the Gram matrix of the weighted G.

    About the centroid Gw Gw^T = diag(p I3, Gm Gm^T), so the SVD form
    V diag(1 - min(1, s^2/eps^2)) V^T equals I - (1/p) Gf^T Gf - Gm^T F(Gm Gm^T) Gm.
    """
    N, _, n = G.shape
    p = n // 3
    pts = np.stack([G[:, 5, 1::3], G[:, 3, 2::3], G[:, 4, 0::3]], axis=-1)  # (N, p, 3)
    c = (pts - pts.mean(axis=1, keepdims=True)) / robust.length_scale_m
    x, y, z = c[..., 0], c[..., 1], c[..., 2]
    # Moment rows of Gw: block i is S(c_i) = [[0, -z, y], [z, 0, -x], [-y, x, 0]].
    S = np.zeros((N, 3, p, 3))
    S[:, 0, :, 1], S[:, 0, :, 2] = -z, y
    S[:, 1, :, 0], S[:, 1, :, 2] = z, -x
    S[:, 2, :, 0], S[:, 2, :, 1] = -y, x
    Gm = S.reshape(N, 3, n)
    eps2 = robust.eps * robust.eps
    out = np.eye(n) - np.tile(np.eye(3) / p, (p, p))  # minus the mean of the force blocks
    return out - _tr(Gm) @ _finv_eigh(_gram(_tr(Gm)), eps2) @ Gm


def _general(
    method: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray, robust: Robustness
) -> np.ndarray:
    """Robust pinv / ef / if on stacks; M (N, n, r) or shared (n, r)."""
    eps2 = robust.eps * robust.eps
    if method == "pinv":
        # M^T M is the same for every grasp when M_a is shared: one eigh for the batch.
        return _finv_apply(_gram(M), lam @ M if M.ndim == 2 else _mv(_tr(M), lam), eps2)
    if method == "ef":
        A = G @ M
        return _finv_apply(_gram(A), _mv(_tr(A), _mv(G, lam)), eps2)
    if G.shape[-1] == 6 and M.shape[-1] <= 3:
        return _if_two(G, M, lam, robust)
    return _if_soft(G, M, lam, robust)


def _if_soft(G: np.ndarray, M: np.ndarray, lam: np.ndarray, robust: Robustness) -> np.ndarray:
    """Robust IF: lam_a = x1 + P (M_a P)^+ (lam - M_a x1), x1 = B^+ P_int lam, B = P_int M_a,
    P = I - B^+ B, with filtered pseudoinverses and the soft internal projector P_int."""
    eps2 = robust.eps * robust.eps
    P_int = _soft_internal_projector_v(G, robust)
    B = P_int @ M
    lb, VB = np.linalg.eigh(_gram(B))
    FB = _spectral(1.0 / np.maximum(lb, eps2), VB)
    x1 = _mv(FB @ _tr(B), _mv(P_int, lam))
    # P = I - B^+ B = I - phi(B^T B), phi(l) = min(1, l / eps^2): B^+ B's eigenvalues g(s) s.
    P = np.eye(M.shape[-1]) - _spectral(np.clip(lb / eps2, 0.0, 1.0), VB)
    P = 0.5 * (P + _tr(P))
    MP = M @ P
    rest = lam - _mv(M, x1)
    return x1 + _mv(P, _finv_apply(_gram(MP), _mv(_tr(MP), rest), eps2))


def _if_two(G: np.ndarray, M: np.ndarray, lam: np.ndarray, robust: Robustness) -> np.ndarray:
    """Robust IF for two contacts at least min_separation_m apart, any r <= 3 directions.

    There P_int = n n^T with n = (e, -e)/sqrt(2), e the grasp line, so B = n b^T with
    b = M^T n: B's filtered pseudoinverse is h(|b|^2) b n^T and P = I - h(|b|^2) b b^T,
    h(l) = 1/max(l, eps^2). When |b| >= eps, P projects b out, and M P's Gram matrix
    gets b b^T / |b|^2 added (an eigenvalue 1 on b, where nothing is applied) so
    that it can be inverted. Grasps with closer contacts, or a Gram matrix with an
    eigenvalue below eps^2, take ``_if_soft``.
    """
    eps2 = robust.eps * robust.eps
    dvec = np.stack([G[:, 5, 4] - G[:, 5, 1], G[:, 3, 5] - G[:, 3, 2], G[:, 4, 3] - G[:, 4, 0]], -1)
    dist = np.sqrt(np.einsum("ni,ni->n", dvec, dvec))
    apart = dist >= robust.min_separation_m
    e = dvec / np.where(apart, dist, 1.0)[:, None]
    n = np.concatenate([e, -e], axis=-1) * np.sqrt(0.5)
    b = _mv(_tr(M), n)
    bb = np.einsum("ni,ni->n", b, b)
    hb = 1.0 / np.maximum(bb, eps2)
    x1 = (hb * np.einsum("ni,ni->n", n, lam))[:, None] * b
    bbt = b[:, :, None] * b[:, None, :]
    P = np.eye(M.shape[-1]) - hb[:, None, None] * bbt
    MP = M @ P
    K2 = _gram(MP)
    full = bb >= eps2
    K2 = K2 + (full / np.where(full, bb, 1.0))[:, None, None] * bbt
    rest = lam - _mv(M, x1)
    y2, regular = _solve_regular(K2, _mv(_tr(MP), rest), eps2)
    out = x1 + _mv(P, y2)
    odd = np.flatnonzero(~(apart & regular))
    if odd.size:
        out[odd] = _if_soft(G[odd], M if M.ndim == 2 else M[odd], lam[odd], robust)
    return out


# -- the exact (seed) formulas, grasp by grasp ---------------------------------------------------

_SEED = {"pinv_exact": exact.pinv_exact, "if_exact": exact.if_exact, "ef_exact": exact.ef_exact}


def _exact(method: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """The seed's formula (hapticd.allocation.exact) on each grasp."""
    fn = _SEED[method]
    Ms = np.broadcast_to(M, (G.shape[0], *M.shape[-2:]))
    return np.array([fn(G[k], Ms[k], lam[k]) for k in range(G.shape[0])])


def filtered_pinv(A: np.ndarray, eps: float) -> np.ndarray:
    """Filtered pseudoinverse of A (m, n): sum g(s_i) v_i u_i^T, shape (n, m)."""
    A = np.atleast_2d(np.asarray(A, dtype=float))
    if A.size == 0:
        return np.zeros((A.shape[1], A.shape[0]))
    return _finv_eigh(_gram(A), eps * eps) @ A.T


def soft_internal_projector(G: np.ndarray, robust: Robustness = DEFAULT_ROBUSTNESS) -> np.ndarray:
    """Soft projector onto the internal forces N(G), (3p, 3p), of one grasp G (6, 3p).

    Exact (N N^T) when every singular value of the weighted G is 0 or at least eps:
    for two contacts, when they are at least min_separation_m apart; three or more
    contacts also need to be far from collinear (a rotation about their near-common
    line has almost no lever). As contacts approach such a configuration, directions
    whose moment lever vanishes blend in continuously. Computed about the contacts'
    centroid with moments weighted by 1/L (N(G) depends on neither).
    """
    G = np.asarray(G, dtype=float)
    if G.shape[1] == 0:
        return np.zeros((0, 0))
    return _soft_internal_projector_v(G[None], robust)[0]


# -- public API -------------------------------------------------------------------------------


def _robust_many(
    method: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray, robust: Robustness, fast: bool
) -> np.ndarray:
    """Robust pinv / if / ef: the closed form for two contacts with one direction each
    (two_contact_structure's case; ``fast`` False: never), else the general path."""
    N, _, n = G.shape
    r = M.shape[-1]
    if fast and n == 6 and r == 2:
        # two_contact_structure's case: one direction per finger, block by block.
        cross = M[..., [3, 4, 5, 0, 1, 2], [0, 0, 0, 1, 1, 1]]  # each column on the other finger
        simple = np.broadcast_to(~cross.any(axis=-1), (N,))
        if simple.all():
            Mb = np.broadcast_to(M, (N, 6, 2))
            return np.stack(_two_contact_v(method, G, Mb, lam, robust), -1)
        out = np.empty((N, 2))
        idx, rest = np.flatnonzero(simple), np.flatnonzero(~simple)
        if idx.size:
            Ms = np.broadcast_to(M, (N, 6, 2))[idx]
            out[idx] = np.stack(_two_contact_v(method, G[idx], Ms, lam[idx], robust), -1)
        Mr = M if M.ndim == 2 else M[rest]
        out[rest] = _general(method, G[rest], Mr, lam[rest], robust)
        return out
    return _general(method, G, M, lam, robust)


def allocate_many(
    method: str,
    G: np.ndarray,
    M_a: np.ndarray,
    lam: np.ndarray,
    *,
    robust: Robustness = DEFAULT_ROBUSTNESS,
    alpha: float | np.ndarray = 0.0,
) -> np.ndarray:
    """Actuator forces lam_a (N, r) N for a batch of N grasps, equal to ``allocate()`` one by one.

    G (N, 6, 3p) grasp matrices (moments in N m per N), M_a (N, 3p, r) or shared
    (3p, r) actuated directions, lam (N, 3p) contact forces in N. ``alpha`` (a
    scalar or (N,), each in [0, 1]) is the external-force weight of ``adaptive``.
    Raises AllocationError (a ValueError) on an unknown method, a shape that does
    not match, NaN or inf, or alpha outside [0, 1].
    """
    G, M, lam, a = _check(method, G, M_a, lam, alpha)
    N, _, n = G.shape
    r = M.shape[-1]
    if N == 0 or r == 0 or n == 0:
        return np.zeros((N, r))
    if N <= CHUNK:
        return solve(method, G, M, lam, a, robust)
    # In chunks, so that a chunk's temporaries (about 150 arrays of CHUNK floats for the
    # closed forms) stay in cache: one pass over 1e4 grasps costs more per grasp than 1e3.
    out = np.empty((N, r))
    for k in range(0, N, CHUNK):
        s = slice(k, k + CHUNK)
        out[s] = solve(method, G[s], M if M.ndim == 2 else M[s], lam[s], a[s], robust)
    return out


def solve(
    method: str,
    G: np.ndarray,
    M: np.ndarray,
    lam: np.ndarray,
    a: np.ndarray,
    robust: Robustness,
    fast: bool = True,
) -> np.ndarray:
    """allocate_many on validated input (a: alpha per grasp, (N,)), in one pass; ``fast``
    False keeps two contacts with one direction each on the general path too."""
    if method in _EXACT:
        return _exact(method, G, M, lam)
    if method != "adaptive":
        return _robust_many(method, G, M, lam, robust, fast)
    x_if = _robust_many("if", G, M, lam, robust, fast)
    mix = a != 0.0
    if not mix.any():
        return x_if
    idx = np.flatnonzero(mix)
    Mi = M if M.ndim == 2 else M[idx]
    x_ef = _robust_many("ef", G[idx], Mi, lam[idx], robust, fast)
    ai = a[idx, None]
    x_if[idx] = adaptive_mix(x_if[idx], x_ef, ai)
    return x_if
