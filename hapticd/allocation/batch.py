"""Allocation on stacks of grasps: which definition each grasp runs, and its checks.

Shapes: G (N, 6, 3p), M_a (N, 3p, r) or shared (3p, r), lam (N, 3p) -> lam_a (N, r);
forces in N, lengths in m. Pure: numpy in, numpy out. ``allocate()`` is this with
N = 1; ``allocate_many`` runs it on a batch.

- the robust methods run ``hapticd.allocation.general.solve_grasps`` grasp by grasp:
  the closed forms of ``hapticd.allocation.closed`` for two contacts with one
  direction each, the general path (``general.general``: the filtered
  pseudoinverses on Gram matrices, the soft internal projector, IF's projector form)
  for every other grasp: the same functions the servo loop's kernel calls; on Python
  floats, or compiled with ``kernel`` (``hapticd.physics.kernels.allocate_grasps``);
- the exact (seed) methods call ``hapticd.allocation.exact`` grasp by grasp.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hapticd import params
from hapticd.allocation import exact, general
from hapticd.allocation.closed import CODES
from hapticd.allocation.robust import (
    DEFAULT_ROBUSTNESS,
    AllocationError,
    Robustness,
)

# Declared with the other settable parameters (the control client reads them too).
METHODS: tuple[str, ...] = tuple(params.ALLOCATORS)
ROBUST_METHODS: tuple[str, ...] = CODES  # the robust methods, by code (closed.CODES)
EXACT_METHODS: tuple[str, ...] = tuple(m for m in METHODS if m.endswith("_exact"))

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


def _items(a: np.ndarray) -> memoryview:
    """A C-contiguous float64 array as a memoryview of its memory and shape: its items are
    Python floats, several times quicker in the interpreter's loops than numpy's scalars."""
    return memoryview(a).cast("B").cast("d", a.shape)


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
    not match, NaN or inf, or alpha outside [0, 1]. ``kernel``: the robust methods compiled
    (``hapticd.physics.jit.compile_kernels(["allocate_grasps"])["allocate_grasps"]``), 1-3 us a
    grasp; None: the same code uncompiled, on Python floats (0.05-2 ms a grasp).
    """
    G, M, lam, a = check(method, G, M_a, lam, alpha)
    N, _, n = G.shape
    if N == 0 or M.shape[-1] == 0 or n == 0:
        return np.zeros((N, M.shape[-1]))
    return solve(method, G, M, lam, a, robust, kernel=kernel)


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
    """allocate_many on validated input (a: alpha per grasp, (N,)): the exact methods the
    seed's formula; the robust ones ``general.solve_grasps`` (``fast`` False: never the
    closed forms), compiled (``kernel``: hapticd.physics.kernels.allocate_grasps) or on floats."""
    if method in EXACT_METHODS:
        return _exact(method, G, M, lam)
    N, _, n = G.shape
    args = [
        np.ascontiguousarray(G),
        np.ascontiguousarray(M if M.ndim == 3 else M[None]),
        np.ascontiguousarray(lam),
        np.ascontiguousarray(a),
    ]
    out, work = np.zeros((N, M.shape[-1])), np.zeros(general.work_shape(n, M.shape[-1]))
    code, eps, sep = CODES.index(method), robust.eps, robust.min_separation_m
    if kernel is not None:
        kernel(code, *args, eps, sep, fast, out, work)
    else:
        general.solve_grasps(code, *map(_items, args), eps, sep, fast, _items(out), _items(work))
    return out
