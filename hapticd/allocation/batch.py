"""Allocation on stacks of grasps: which definition each grasp runs, and its checks.

Shapes: G (N, 6, 3p), M_a (N, 3p, r) or shared (3p, r), lam (N, 3p) -> lam_a (N, r);
forces in N, lengths in m. Pure: numpy in, numpy out. ``allocate()`` is this with
N = 1; ``allocate_many`` runs it on a batch (in chunks).

- two contacts with one direction each run the closed forms of
  ``hapticd.allocation.closed``, elementwise over the batch (the same code the
  kernel compiles, on arrays);
- every other grasp takes the general path, ``hapticd.allocation.general`` (the
  filtered pseudoinverses on Gram matrices, the soft internal projector, IF's
  projector form: the same function the servo loop's kernel calls for three or
  more contacts): on the whole batch elementwise (each workspace entry an (N,)
  array), on floats for one grasp, or compiled grasp by grasp with ``kernel``
  (``hapticd.kernels.allocate_grasps``);
- the exact (seed) methods call ``hapticd.allocation.exact`` grasp by grasp.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hapticd import params
from hapticd.allocation import exact, general
from hapticd.allocation.closed import CODES, adaptive_mix, two_contact
from hapticd.allocation.robust import (
    DEFAULT_ROBUSTNESS,
    AllocationError,
    Robustness,
)

# Declared with the other settable parameters (the control client reads them too).
METHODS: tuple[str, ...] = tuple(params.ALLOCATORS)
ROBUST_METHODS: tuple[str, ...] = CODES  # the robust methods, by code (closed.CODES)
EXACT_METHODS: tuple[str, ...] = tuple(m for m in METHODS if m.endswith("_exact"))
CHUNK = 1024  # grasps per internal pass of allocate_many
# From this many grasps on, the general path runs on the whole batch elementwise; fewer run
# one by one on floats (cheaper below about 10 grasps here: the elementwise pass costs 2-20
# ms whatever the batch, a grasp on floats 0.3-2 ms).
STACK_MIN = 10

# -- validation -------------------------------------------------------------------------------


def check(
    method: str, G: object, M_a: object, lam: object, alpha: object, one: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """allocate_many's arguments as float arrays, and alpha per grasp (N,), or
    AllocationError naming what is wrong; ``one``: allocate()'s batch of one, whose
    messages name the one grasp's shapes."""
    if method not in METHODS:
        raise AllocationError(f"unknown allocator {method!r}; expected one of {list(METHODS)}")
    G = np.asarray(G, dtype=float)
    M = np.asarray(M_a, dtype=float)
    lam_arr = np.asarray(lam, dtype=float)
    k = 1 if one else 0  # leading axes not shown
    if G.ndim != 3 or G.shape[1] != 6 or G.shape[2] % 3:
        raise AllocationError(f"G must have shape ({'' if one else 'N, '}6, 3p), got {G.shape[k:]}")
    N, _, n = G.shape
    if not (M.ndim == 2 and M.shape[0] == n) and not (M.ndim == 3 and M.shape[:2] == (N, n)):
        want = f"({n}, r)" if one else f"({N}, {n}, r) or shared ({n}, r)"
        raise AllocationError(f"M_a must have shape {want} to match G {G.shape[k:]}, got {M.shape}")
    if lam_arr.shape != (N, n):
        raise AllocationError(
            f"lam must have shape {(N, n)[k:]} to match G {G.shape[k:]}, got {lam_arr.shape[k:]}"
        )
    a = np.zeros(N)  # other methods ignore alpha
    if method == "adaptive":
        a = np.asarray(alpha, dtype=float)
        if a.ndim > 1 or (a.ndim == 1 and a.shape != (N,)):
            raise AllocationError(f"alpha must be a scalar or have shape ({N},), got {a.shape}")
        if not np.all((a >= 0.0) & (a <= 1.0)):  # False for NaN too
            raise AllocationError("adaptive alpha must be in [0, 1] (and finite)")
        a = np.broadcast_to(a, (N,)).astype(float)
    for name, arr in (("G", G), ("lam", lam_arr), ("M_a", M)):
        if not np.isfinite(arr).all():
            g = np.argmax(~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1))  # the first grasp
            where = "" if one or (arr.ndim == 2 and arr is M) else f" (grasp {g})"
            raise AllocationError(f"{name} contains NaN or inf{where}; refusing to compute a force")
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


# -- the general path: hapticd.allocation.general's, grasp by grasp --------------------------


def _items(a: np.ndarray) -> memoryview:
    """A C-contiguous float64 array as a memoryview of its memory and shape: its items are
    Python floats, several times quicker in the interpreter's loops than numpy's scalars."""
    return memoryview(a).cast("B").cast("d", a.shape)


def _path(
    closed: bool,
    method: str,
    G: np.ndarray,
    M: np.ndarray,
    lam: np.ndarray,
    robust: Robustness,
    kernel: Callable[..., None] | None,
) -> np.ndarray:
    """Robust pinv / ef / if on stacks, M (N, n, r) or shared (n, r), every grasp by one
    path: the two-contact closed forms (``closed``: two contacts with one direction each),
    else ``general.general``, compiled grasp by grasp (``kernel``:
    hapticd.kernels.allocate_grasps) or on the whole batch elementwise (fewer than
    STACK_MIN grasps: one by one on floats)."""
    if closed:
        Mb = np.broadcast_to(M, (G.shape[0], 6, 2))
        return np.stack(_two_contact_v(method, G, Mb, lam, robust), -1)
    N, _, n = G.shape
    r = M.shape[-1]
    code = CODES.index(method)
    eps, sep = robust.eps, robust.min_separation_m
    if kernel is None and N >= STACK_MIN:  # the whole batch at once, elementwise
        return general.solve_stack(code, G, M, lam, eps, sep)
    args = [
        np.ascontiguousarray(G),
        np.ascontiguousarray(M if M.ndim == 3 else M[None]),
        np.ascontiguousarray(lam),
        np.zeros(N),
    ]
    out, work = np.zeros((N, r)), np.zeros(general.work_shape(n, r))
    if kernel is not None:
        kernel(code, *args, eps, sep, out, work)
    else:  # a few grasps, one by one on floats (as the kernel runs it)
        general.solve_grasps(code, *map(_items, args), eps, sep, _items(out), _items(work))
    return out


# -- the exact (seed) formulas, grasp by grasp ---------------------------------------------------


def _exact(method: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """The seed's formula (hapticd.allocation.exact's function of that name) on each grasp."""
    fn = getattr(exact, method)
    Ms = np.broadcast_to(M, (G.shape[0], *M.shape[-2:]))
    return np.array([fn(G[k], Ms[k], lam[k]) for k in range(G.shape[0])])


# -- public API -------------------------------------------------------------------------------


def allocate_many(
    method: str,
    G: np.ndarray,
    M_a: np.ndarray,
    lam: np.ndarray,
    *,
    robust: Robustness = DEFAULT_ROBUSTNESS,
    alpha: float | np.ndarray = 0.0,
    kernel: Callable[..., None] | None = None,
) -> np.ndarray:
    """Actuator forces lam_a (N, r) N for a batch of N grasps, equal to ``allocate()`` one by one.

    G (N, 6, 3p) grasp matrices (moments in N m per N), M_a (N, 3p, r) or shared
    (3p, r) actuated directions, lam (N, 3p) contact forces in N. ``alpha`` (a
    scalar or (N,), each in [0, 1]) is the external-force weight of ``adaptive``.
    Raises AllocationError (a ValueError) on an unknown method, a shape that does
    not match, NaN or inf, or alpha outside [0, 1]. ``kernel``: the general path compiled
    (``hapticd.jit.compile_kernels(["allocate_grasps"])["allocate_grasps"]``), far quicker
    on grasps the two-contact closed forms do not take; None: the same code uncompiled.
    """
    G, M, lam, a = check(method, G, M_a, lam, alpha)
    N, _, n = G.shape
    r = M.shape[-1]
    if N == 0 or r == 0 or n == 0:
        return np.zeros((N, r))
    if N <= CHUNK:
        return solve(method, G, M, lam, a, robust, kernel=kernel)
    # In chunks, so that a chunk's temporaries (about 150 arrays of CHUNK floats for the
    # closed forms) stay in cache: one pass over 1e4 grasps costs more per grasp than 1e3.
    out = np.empty((N, r))
    for k in range(0, N, CHUNK):
        s = slice(k, k + CHUNK)
        out[s] = solve(
            method, G[s], M if M.ndim == 2 else M[s], lam[s], a[s], robust, kernel=kernel
        )
    return out


def solve(
    method: str,
    G: np.ndarray,
    M: np.ndarray,
    lam: np.ndarray,
    a: np.ndarray,
    robust: Robustness,
    fast: bool = True,
    kernel: Callable[..., None] | None = None,
) -> np.ndarray:
    """allocate_many on validated input (a: alpha per grasp, (N,)), in one pass: which
    definition each grasp runs. The exact methods: the seed's formula; the robust ones: the
    two-contact closed forms for two contacts with one direction each (``fast`` False:
    never), the general path for the rest; adaptive: IF, mixed with EF where alpha is not 0."""
    if method in EXACT_METHODS:
        return _exact(method, G, M, lam)
    if method == "adaptive":
        out = solve("if", G, M, lam, a, robust, fast, kernel)
        mix = np.flatnonzero(a != 0.0)
        if mix.size:
            Mi = M if M.ndim == 2 else M[mix]
            x_ef = solve("ef", G[mix], Mi, lam[mix], a[mix], robust, fast, kernel)
            out[mix] = adaptive_mix(out[mix], x_ef, a[mix, None])
        return out
    N, _, n = G.shape
    closed = np.zeros(N, dtype=bool)
    if fast and n == 6 and M.shape[-1] == 2:  # one direction per finger, block by block?
        cross = M[..., [3, 4, 5, 0, 1, 2], [0, 0, 0, 1, 1, 1]]  # each column on the other finger
        closed = np.broadcast_to(~cross.any(axis=-1), (N,))
    every = bool(closed.all())
    if every or not closed.any():  # the whole batch one way: no copies
        return _path(every, method, G, M, lam, robust, kernel)
    out = np.empty((N, M.shape[-1]))
    for rows in (np.flatnonzero(closed), np.flatnonzero(~closed)):
        Mr = M if M.ndim == 2 else M[rows]
        out[rows] = _path(bool(closed[rows[0]]), method, G[rows], Mr, lam[rows], robust, kernel)
    return out
