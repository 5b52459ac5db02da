"""The robust allocators' general path, in plain loops that numba compiles.

One grasp at a time on a float64 workspace ``w`` the caller preallocates (``work_shape``;
row offsets ``layout``): G (6, n), M_a (n, r), lam (n,) N in, lam_a (r,) N out, n = 3p.
Nothing is allocated, so the servo loop's kernel runs it every tick. The formulas
(filtered pseudoinverses on Gram matrices, the soft internal projector, IF's projector
form): docs/allocation.md, "Batches".
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.allocation.closed import ADAPTIVE, EF, PINV, adaptive_mix, two_contact

_SWEEPS = 64  # Jacobi sweeps at most (a 15 x 15 converges in under 10)
# Eigenvalues of G G^T below this share of the largest are G's null space (accuracy):
# the Gram matrix holds s^2 to rounding of the largest, so a rank cut on s itself at
# numpy's tolerance would keep rounding noise of exactly collinear contacts.
_RANK_SHARE = 1e-13


# Indices into ``layout``'s offsets: B0 (the first of the rows after the grasp and its
# products: an allocator plugin's scratch), lam (n,), a scratch vector, lam_a (r,).
B0_ROW, LAM_ROW, T1_ROW, XO_ROW = 6, 2, 15, 19


def work_shape(n: int, r: int) -> tuple[int, int]:
    """The workspace's shape (rows, cols) for up to n force components and r directions."""
    return 3 * n + 5 * r + 37, max(n, r, 6)


def layout(n: int, r: int) -> tuple[int, ...]:
    """Row offsets of the workspace's blocks for n force components and r directions: G0,
    M0, LAM, GM, A3, V3, B0, KB, VB, PP, MP, K2, V2, A6, V6, T1, T2, Y, X1, XO, C."""
    m0 = 6
    lam = m0 + n
    gm = lam + 1
    a3 = gm + 3
    v3 = a3 + 3
    b0 = v3 + 3
    kb = b0 + n
    vb = kb + r
    pp = vb + r
    mp = pp + r
    k2 = mp + n
    v2 = k2 + r
    a6 = v2 + r
    v6 = a6 + 6
    t1 = v6 + 6
    return (0, m0, lam, gm, a3, v3, b0, kb, vb, pp, mp, k2, v2, a6, v6, t1, t1 + 1, t1 + 2,
            t1 + 3, t1 + 4, t1 + 5)  # fmt: skip


def _rotation(app: float, aqq: float, apq: float) -> tuple[float, float]:
    """(cos, sin) of the Jacobi rotation that zeroes apq of [[app, apq], [apq, aqq]]."""
    theta = (aqq - app) / (2.0 * apq)
    if abs(theta) > 1e150:  # theta^2 would overflow: t = 1 / (2 theta)
        t = 0.5 / theta
    else:
        t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
        if theta < 0.0:
            t = -t
    c = 1.0 / math.sqrt(t * t + 1.0)
    return c, t * c


def _jacobi(w: np.ndarray, a: int, v: int, k: int) -> None:
    """Eigendecomposition of the symmetric k x k matrix in rows a.. of w, in place (cyclic
    Jacobi): eigenvalues on its diagonal, eigenvectors in the columns of rows v.."""
    for i in range(k):
        for j in range(k):
            w[v + i, j] = 1.0 if i == j else 0.0
    for _ in range(_SWEEPS):
        off = 0.0
        diag = 0.0
        for i in range(k):
            diag += w[a + i, i] * w[a + i, i]
            for j in range(i + 1, k):
                off += w[a + i, j] * w[a + i, j]
        if off <= 1e-32 * diag or off == 0.0:  # off: 0.0 for a 1 x 1
            return
        for p in range(k - 1):
            for q in range(p + 1, k):
                apq = w[a + p, q]
                if apq == 0.0:
                    continue
                c, s = _rotation(w[a + p, p], w[a + q, q], apq)
                for i in range(k):  # columns p, q
                    x, y = w[a + i, p], w[a + i, q]
                    w[a + i, p], w[a + i, q] = c * x - s * y, s * x + c * y
                for i in range(k):  # rows p, q
                    x, y = w[a + p, i], w[a + q, i]
                    w[a + p, i], w[a + q, i] = c * x - s * y, s * x + c * y
                w[a + p, q] = 0.0
                w[a + q, p] = 0.0
                for i in range(k):
                    x, y = w[v + i, p], w[v + i, q]
                    w[v + i, p], w[v + i, q] = c * x - s * y, s * x + c * y


def _gram(w: np.ndarray, src: int, m: int, k: int, dst: int, rows: bool) -> None:
    """A^T A (k x k) into rows dst.. of w, A (m x k) in rows src..; A A^T for A (k x m)
    there if ``rows``."""
    for i in range(k):
        for j in range(i, k):
            s = 0.0
            if rows:
                for t in range(m):
                    s += w[src + i, t] * w[src + j, t]
            else:
                for t in range(m):
                    s += w[src + t, i] * w[src + t, j]
            w[dst + i, j] = s
            w[dst + j, i] = s


def _t_apply(w: np.ndarray, src: int, m: int, k: int, vec: int, out: int) -> None:
    """A^T v (k,) into row ``out``: A (m x k) in rows src.., v (m,) in row ``vec``."""
    for j in range(k):
        s = 0.0
        for t in range(m):
            s += w[src + t, j] * w[vec, t]
        w[out, j] = s


def _finv_apply(w: np.ndarray, a: int, v: int, k: int, vec: int, eps2: float, tmp: int) -> None:
    """F(K) y in place of y (row ``vec``), F(l) = 1/max(l, eps2), K as ``_jacobi`` left it
    in rows a.. and v..; row ``tmp`` scratch."""
    for j in range(k):
        s = 0.0
        for t in range(k):
            s += w[v + t, j] * w[vec, t]
        lj = w[a + j, j]
        w[tmp, j] = s / (lj if lj >= eps2 else eps2)
    for t in range(k):
        s = 0.0
        for j in range(k):
            s += w[v + t, j] * w[tmp, j]
        w[vec, t] = s


def _pinv_apply(
    w: np.ndarray, src: int, m: int, k: int, y: int, out: int, a: int, v: int, eps2: float, tmp: int
) -> None:
    """The filtered pseudoinverse F(A^T A) A^T y (k,) into row ``out``: A (m x k) in rows
    src.., y (m,) in row ``y``; A^T A's eigendecomposition left in rows a.. and v.."""
    _gram(w, src, m, k, a, False)
    _jacobi(w, a, v, k)
    _t_apply(w, src, m, k, y, out)
    _finv_apply(w, a, v, k, out, eps2, tmp)


def _pinv_solve(
    w: np.ndarray, src: int, m: int, k: int, y: int, out: int, a: int, v: int, eps2: float, tmp: int
) -> None:
    """``_pinv_apply``'s F(A^T A) A^T y (k,) into row ``out``, by Cholesky where every
    eigenvalue of K = A^T A is at least eps2, so that F(K) is K^-1 (the same function, to
    rounding, without the eigensolver: two thirds of EF's time). Certified without the
    eigenvalues: lambda_min >= det K / (tr K / (k - 1))^(k - 1) (AM-GM on the other k - 1),
    det K the product of the Cholesky pivots. Otherwise ``_pinv_apply``. Rows a.. hold K,
    rows v.. its Cholesky factor L (lower) after, not an eigendecomposition."""
    _gram(w, src, m, k, a, False)
    trace = 0.0
    for i in range(k):
        trace += w[a + i, i]
    scale = trace / (k - 1) if k > 1 else 1.0
    bound = scale  # det K / scale^(k - 1), as a running product of pivot / scale
    ok = trace > 0.0
    for j in range(k):
        if not ok:
            break
        d = w[a + j, j]
        for p in range(j):
            d -= w[v + j, p] * w[v + j, p]
        if not d > 0.0:  # not positive definite (or NaN)
            ok = False
            break
        bound *= d / scale
        ljj = math.sqrt(d)
        w[v + j, j] = ljj
        for i in range(j + 1, k):
            x = w[a + i, j]
            for p in range(j):
                x -= w[v + i, p] * w[v + j, p]
            w[v + i, j] = x / ljj
    # A margin far above the pivots' rounding (cond K x 1e-16 relative, cond K < 1 / eps2).
    if not (ok and bound >= eps2 * (1.0 + 1e-6)):
        _pinv_apply(w, src, m, k, y, out, a, v, eps2, tmp)
        return
    _t_apply(w, src, m, k, y, out)  # A^T y, then L L^T x = A^T y in place
    for i in range(k):
        x = w[out, i]
        for p in range(i):
            x -= w[v + i, p] * w[out, p]
        w[out, i] = x / w[v + i, i]
    for i in range(k - 1, -1, -1):
        x = w[out, i]
        for p in range(i + 1, k):
            x -= w[v + p, i] * w[out, p]
        w[out, i] = x / w[v + i, i]


def soft_prepare(w: np.ndarray, n: int, eps: float, min_sep: float) -> None:
    """The soft internal projector's parts from G: Gm (3 x n), the moment rows about the
    contacts' centroid weighted by 1/L, in rows GM; Gm Gm^T's eigendecomposition in A3, V3."""
    lay = layout(n, 1)
    gm, a3, v3 = lay[3], lay[4], lay[5]
    p = n // 3
    mx, my, mz = 0.0, 0.0, 0.0
    for i in range(p):  # the contact offsets, read off G's moment rows
        mx += w[5, 3 * i + 1]
        my += w[3, 3 * i + 2]
        mz += w[4, 3 * i]
    mx, my, mz = mx / p, my / p, mz / p
    inv_l = math.sqrt(2.0) * eps / min_sep  # 1 / Robustness.length_scale_m
    for i in range(p):
        x = (w[5, 3 * i + 1] - mx) * inv_l
        y = (w[3, 3 * i + 2] - my) * inv_l
        z = (w[4, 3 * i] - mz) * inv_l
        j = 3 * i
        w[gm, j], w[gm, j + 1], w[gm, j + 2] = 0.0, -z, y
        w[gm + 1, j], w[gm + 1, j + 1], w[gm + 1, j + 2] = z, 0.0, -x
        w[gm + 2, j], w[gm + 2, j + 1], w[gm + 2, j + 2] = -y, x, 0.0
    _gram(w, gm, n, 3, a3, True)
    _jacobi(w, a3, v3, 3)


def soft_apply(w: np.ndarray, n: int, eps2: float, src: int, dst: int) -> None:
    """P_int v into row ``dst`` for v (n,) in row ``src``, after ``soft_prepare``."""
    lay = layout(n, 1)
    gm, a3, v3 = lay[3], lay[4], lay[5]
    p = n // 3
    f0, f1, f2 = 0.0, 0.0, 0.0
    for i in range(p):
        f0 += w[src, 3 * i]
        f1 += w[src, 3 * i + 1]
        f2 += w[src, 3 * i + 2]
    f0, f1, f2 = f0 / p, f1 / p, f2 / p
    g0, g1, g2 = 0.0, 0.0, 0.0  # Gm v
    for t in range(n):
        vt = w[src, t]
        g0 += w[gm, t] * vt
        g1 += w[gm + 1, t] * vt
        g2 += w[gm + 2, t] * vt
    h0, h1, h2 = 0.0, 0.0, 0.0  # F(Gm Gm^T) Gm v
    for j in range(3):
        lj = w[a3 + j, j]
        c = w[v3, j] * g0 + w[v3 + 1, j] * g1 + w[v3 + 2, j] * g2
        c = c / (lj if lj >= eps2 else eps2)
        h0 += w[v3, j] * c
        h1 += w[v3 + 1, j] * c
        h2 += w[v3 + 2, j] * c
    for i in range(p):
        for k in range(3):
            t = 3 * i + k
            f = f0 if k == 0 else (f1 if k == 1 else f2)
            w[dst, t] = w[src, t] - f - (w[gm, t] * h0 + w[gm + 1, t] * h1 + w[gm + 2, t] * h2)


def _pinv_or_ef(code: int, w: np.ndarray, n: int, r: int, eps2: float) -> None:
    """Robust pinv (x = F(M^T M) M^T lam) or EF (x = F(A^T A) A^T G lam, A = G M) into XO."""
    lay = layout(n, r)
    m0, lam, kb, vb, a6, t1, xo = lay[1], lay[2], lay[7], lay[8], lay[13], lay[15], lay[19]
    tmp = lay[20]
    if code == PINV:
        _pinv_solve(w, m0, n, r, lam, xo, kb, vb, eps2, tmp)
        return
    for i in range(6):  # A = G M (6 x r) and G lam
        for j in range(r):
            s = 0.0
            for t in range(n):
                s += w[i, t] * w[m0 + t, j]
            w[a6 + i, j] = s
        s = 0.0
        for t in range(n):
            s += w[i, t] * w[lam, t]
        w[t1, i] = s
    _pinv_solve(w, a6, 6, r, t1, xo, kb, vb, eps2, tmp)


def _internal_first(w: np.ndarray, n: int, r: int, eps: float, min_sep: float) -> None:
    """Robust IF into XO: the projector form with the soft internal projector."""
    lay = layout(n, r)
    m0, lam, b0, kb, vb, pp = lay[1], lay[2], lay[6], lay[7], lay[8], lay[9]
    mp, k2, v2, t1, t2 = lay[10], lay[11], lay[12], lay[15], lay[16]
    y, x1, xo, tmp = lay[17], lay[18], lay[19], lay[20]
    eps2 = eps * eps
    soft_prepare(w, n, eps, min_sep)
    for j in range(r):  # B = P_int M, column by column
        for t in range(n):
            w[t1, t] = w[m0 + t, j]
        soft_apply(w, n, eps2, t1, t2)
        for t in range(n):
            w[b0 + t, j] = w[t2, t]
    soft_apply(w, n, eps2, lam, t1)  # P_int lam
    _pinv_apply(w, b0, n, r, t1, x1, kb, vb, eps2, tmp)  # x1 = B^+ P_int lam
    # P = I - B^+ B = I - V diag(min(1, l / eps^2)) V^T, symmetric: one triangle mirrored.
    for i in range(r):
        for j in range(i, r):
            s = 0.0
            for k in range(r):
                lk = w[kb + k, k] / eps2
                lk = 0.0 if lk < 0.0 else (1.0 if lk > 1.0 else lk)
                s += w[vb + i, k] * lk * w[vb + j, k]
            w[pp + i, j] = (1.0 if i == j else 0.0) - s
            w[pp + j, i] = w[pp + i, j]
    for t in range(n):  # M P, and the rest lam - M x1
        s = w[lam, t]
        for j in range(r):
            s = s - w[m0 + t, j] * w[x1, j]
            q = 0.0
            for k in range(r):
                q += w[m0 + t, k] * w[pp + k, j]
            w[mp + t, j] = q
        w[t2, t] = s
    _pinv_apply(w, mp, n, r, t2, y, k2, v2, eps2, tmp)  # y = (M P)^+ (lam - M x1)
    for i in range(r):  # x1 + P y
        s = w[x1, i]
        for j in range(r):
            s = s + w[pp + i, j] * w[y, j]
        w[xo, i] = s


def general(
    code: int, w: np.ndarray, n: int, r: int, eps: float, min_sep: float, alpha: float
) -> None:
    """lam_a (r,) N into row XO by robust method ``code`` (closed.CODES) for the grasp in
    ``w``; ``alpha`` in [0, 1] is adaptive's external weight (the others ignore it)."""
    lay = layout(n, r)
    xo, x1 = lay[19], lay[18]
    eps2 = eps * eps
    if code in (PINV, EF):
        _pinv_or_ef(code, w, n, r, eps2)
        return
    _internal_first(w, n, r, eps, min_sep)
    if code == ADAPTIVE and alpha != 0.0:
        for j in range(r):
            w[x1, j] = w[xo, j]
        _pinv_or_ef(EF, w, n, r, eps2)
        for j in range(r):
            w[xo, j] = adaptive_mix(w[x1, j], w[xo, j], alpha)


def solve_grasps(
    code: int,
    G: np.ndarray,
    M: np.ndarray,
    lam: np.ndarray,
    alpha: np.ndarray,
    eps: float,
    min_sep: float,
    fast: bool,
    out: np.ndarray,
    w: np.ndarray,
) -> None:
    """lam_a (N, r) N into ``out`` by robust method ``code``: G (N, 6, n), M (N or 1, n, r),
    lam (N, n) N, alpha (N,), ``w`` a workspace. ``fast``: the closed form for two contacts
    with one direction each."""
    N, n, r = lam.shape[0], lam.shape[1], out.shape[1]
    lay = layout(n, r)
    m0, row, xo = lay[1], lay[2], lay[19]
    shared = M.shape[0] == 1
    for g in range(N):
        mg = 0 if shared else g
        closed = fast and n == 6 and r == 2
        for t in range(3 if closed else 0):  # each direction on its own finger only?
            if M[mg, 3 + t, 0] != 0.0 or M[mg, t, 1] != 0.0:
                closed = False
        if closed:  # the offsets off G's moment rows, as contact_offsets reads them
            out[g, 0], out[g, 1] = two_contact(
                code,
                (G[g, 5, 1], G[g, 3, 2], G[g, 4, 0]),
                (G[g, 5, 4], G[g, 3, 5], G[g, 4, 3]),
                (M[mg, 0, 0], M[mg, 1, 0], M[mg, 2, 0]),
                (M[mg, 3, 1], M[mg, 4, 1], M[mg, 5, 1]),
                (lam[g, 0], lam[g, 1], lam[g, 2]),
                (lam[g, 3], lam[g, 4], lam[g, 5]),
                eps,
                min_sep,
                alpha[g],
            )
            continue
        for i in range(6):
            for t in range(n):
                w[i, t] = G[g, i, t]
        if g == 0 or not shared:
            for t in range(n):
                for j in range(r):
                    w[m0 + t, j] = M[mg, t, j]
        for t in range(n):
            w[row, t] = lam[g, t]
        general(code, w, n, r, eps, min_sep, alpha[g])
        for j in range(r):
            out[g, j] = w[xo, j]


def residuals(w: np.ndarray, n: int, r: int) -> tuple[float, float, float, float]:
    """``accuracy``'s (internal, external, total, amplification) of lam_a in row XO for the
    grasp in ``w``; G's row space from G G^T's eigenvalues above _RANK_SHARE of the largest."""
    lay = layout(n, r)
    m0, lam, a6, v6, t1, xo = lay[1], lay[2], lay[13], lay[14], lay[15], lay[19]
    total = 0.0
    norm_lam = 0.0
    norm_out = 0.0
    for t in range(n):
        m = 0.0
        for j in range(r):
            m += w[m0 + t, j] * w[xo, j]
        res = w[lam, t] - m
        w[t1, t] = res
        total += res * res
        norm_lam += w[lam, t] * w[lam, t]
        norm_out += m * m
    external = 0.0
    for i in range(6):  # G res, in row T2
        s = 0.0
        for t in range(n):
            s += w[i, t] * w[t1, t]
        w[t1 + 1, i] = s
        external += s * s
    _gram(w, 0, n, 6, a6, True)
    _jacobi(w, a6, v6, 6)
    top = 0.0
    for j in range(6):
        top = w[a6 + j, j] if w[a6 + j, j] > top else top
    coef = t1 + 2  # (G G^T)^+ G res in V's basis, then G^T of it subtracted from res
    for j in range(6):
        lj = w[a6 + j, j]
        c = 0.0
        if lj > _RANK_SHARE * top:
            for i in range(6):
                c += w[v6 + i, j] * w[t1 + 1, i]
            c /= lj
        w[coef, j] = c
    for i in range(6):
        s = 0.0
        for j in range(6):
            s += w[v6 + i, j] * w[coef, j]
        w[coef + 1, i] = s
    internal = 0.0
    for t in range(n):
        s = w[t1, t]
        for i in range(6):
            s = s - w[i, t] * w[coef + 1, i]
        internal += s * s
    amp = math.sqrt(norm_out) / math.sqrt(norm_lam) if norm_lam > 0.0 else 0.0
    return math.sqrt(internal), math.sqrt(external), math.sqrt(total), amp


# What compiled code calls (hapticd.physics.jit makes them callable from a kernel).
KERNEL_HELPERS = (
    _rotation,
    _jacobi,
    _gram,
    _t_apply,
    _finv_apply,
    _pinv_apply,
    _pinv_solve,
    layout,
    soft_prepare,
    soft_apply,
    _pinv_or_ef,
    _internal_first,
    general,
    residuals,
    solve_grasps,
)
