"""``allocate_many``: allocation of a batch of N grasps, and the checks of its arguments.

Shapes: G (N, 6, 3p), M_a (N, 3p, r) or shared (3p, r), lam (N, 3p) N -> lam_a (N, r) N.
The robust methods run ``general.solve_grasps``, the exact ones ``exact``, grasp by grasp
(docs/allocation.md, "Batches").
"""

from __future__ import annotations

from collections.abc import Callable
from importlib.metadata import entry_points

import numpy as np

from hapticd import params
from hapticd.allocation import exact, general, plugins
from hapticd.allocation.closed import CODES
from hapticd.allocation.robust import DEFAULT_ROBUSTNESS, AllocationError, Robustness

# Declared with the other settable parameters (the control client reads them too).
METHODS: tuple[str, ...] = tuple(params.ALLOCATORS)
ROBUST_METHODS: tuple[str, ...] = CODES
EXACT_METHODS: tuple[str, ...] = tuple(m for m in METHODS if m.endswith("_exact"))
# allocate_many's ``kernel`` for the same code on Python floats, uncompiled.
PYTHON = "python"
# The entry-point group of the kernel compiler the install provides (hapticd's own:
# hapticd.physics.jit.compiled, which caches the machine code on disk and refuses a cache
# another user could have written). Allocation knows only the group's name: the compiler,
# which knows every kernel, sits above it.
COMPILERS = "hapticd.compilers"
_DEFAULT: list[Callable[..., None] | None] = []  # the default kernel, once looked up


def default_kernel() -> Callable[..., None] | None:
    """allocate_many's default kernel: ``allocate_grasps`` compiled by the first compiler of
    the COMPILERS group (compiled once, then loaded from its cache), or None when none is
    installed or it cannot compile (then the same code runs on Python floats)."""
    if not _DEFAULT:
        fn = None
        for ep in sorted(entry_points(group=COMPILERS), key=lambda e: e.name):
            try:
                fn = ep.load()("allocate_grasps")
            except Exception:  # a broken compiler: the uncompiled code gives the same forces
                fn = None
            if fn is not None:
                break
        _DEFAULT.append(fn)
    return _DEFAULT[0]


def check(
    method: str, G: object, M_a: object, lam: object, alpha: object, one: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """allocate_many's arguments as float arrays, and alpha per grasp (N,); else
    AllocationError naming what is wrong. ``one``: allocate()'s batch of one, whose
    messages show the one grasp's shapes."""
    if not (isinstance(method, str) and plugins.is_known(method)):
        raise AllocationError(plugins.unknown(method))
    G = np.asarray(G, dtype=float)
    M = np.asarray(M_a, dtype=float)
    lam_arr = np.asarray(lam, dtype=float)
    k = 1 if one else 0  # leading axes not shown
    if G.ndim != 3 or G.shape[1] != 6 or G.shape[2] % 3:
        raise AllocationError(f"G must have shape ({'' if one else 'N, '}6, 3p), got {G.shape[k:]}")
    N, _, n = G.shape
    if M.shape[:-1] not in ((n,), (N, n)):
        want = f"({n}, r)" if one else f"({N}, {n}, r) or shared ({n}, r)"
        raise AllocationError(f"M_a must have shape {want} to match G {G.shape[k:]}, got {M.shape}")
    if lam_arr.shape != (N, n):
        raise AllocationError(
            f"lam must have shape {(N, n)[k:]} to match G {G.shape[k:]}, got {lam_arr.shape[k:]}"
        )
    a = np.zeros(N)  # other methods ignore alpha
    if method == "adaptive":
        a = np.asarray(alpha, dtype=float)
        if a.shape not in ((), (N,)):
            raise AllocationError(f"alpha must be a scalar or have shape ({N},), got {a.shape}")
        if not np.all((a >= 0.0) & (a <= 1.0)):  # False for NaN too
            raise AllocationError("adaptive alpha must be in [0, 1] (and finite)")
        a = np.broadcast_to(a, (N,)).astype(float)
    for name, arr in (("G", G), ("lam", lam_arr), ("M_a", M)):
        if not np.isfinite(arr).all():
            g = np.argmax(~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1))  # the first grasp
            where = "" if one or (arr is M and M.ndim == 2) else f" (grasp {g})"
            raise AllocationError(f"{name} contains NaN or inf{where}; refusing to compute a force")
    return G, M, lam_arr, a


def _items(a: np.ndarray) -> memoryview:
    # Python floats: several times quicker in the interpreter's loops than numpy's scalars.
    return memoryview(a).cast("B").cast("d", a.shape)


def allocate_many(
    method: str,
    G: np.ndarray,
    M_a: np.ndarray,
    lam: np.ndarray,
    *,
    robust: Robustness = DEFAULT_ROBUSTNESS,
    alpha: float | np.ndarray = 0.0,
    kernel: Callable[..., None] | str | None = None,
) -> np.ndarray:
    """Actuator forces lam_a (N, r) N for N grasps, equal to ``allocate()`` one by one.

    G (N, 6, 3p) (moments in N m per N), M_a (N, 3p, r) or shared (3p, r) unit directions,
    lam (N, 3p) N; ``alpha`` (scalar or (N,), in [0, 1]) ``adaptive``'s external-force
    weight. ``kernel``: a compiled ``allocate_grasps`` for the robust methods; None (the
    default) the installed compiler's (``default_kernel``), PYTHON the same code on
    Python floats. Raises AllocationError (a ValueError) on an unknown method, mismatched
    shapes, NaN or inf, or alpha outside [0, 1].
    """
    args = check(method, G, M_a, lam, alpha)
    if isinstance(kernel, str):
        if kernel != PYTHON:
            raise AllocationError(f"kernel must be a compiled kernel, None or {PYTHON!r}")
        return solve(method, *args, robust)
    if kernel is None and method in ROBUST_METHODS and args[0].size:
        kernel = default_kernel()
    return solve(method, *args, robust, kernel=kernel)


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
    """allocate_many on ``check``'s output (a: alpha per grasp, (N,)); ``fast`` False: the
    general path even where a closed form applies."""
    N, _, n = G.shape
    r = M.shape[-1]
    if N == 0 or r == 0 or n == 0:
        return np.zeros((N, r))
    if method not in METHODS:  # an installed plugin, grasp by grasp
        return _plugin_many(method, G, np.broadcast_to(M, (N, n, r)), lam)
    if method in EXACT_METHODS:
        fn = getattr(exact, method)
        Ms = np.broadcast_to(M, (N, n, r))
        return np.array([fn(G[k], Ms[k], lam[k]) for k in range(N)])
    args = [
        np.ascontiguousarray(G),
        np.ascontiguousarray(M if M.ndim == 3 else M[None]),
        np.ascontiguousarray(lam),
        np.ascontiguousarray(a),
    ]
    out, work = np.zeros((N, r)), np.zeros(general.work_shape(n, r))
    code, eps, sep = CODES.index(method), robust.eps, robust.min_separation_m
    if kernel is not None:
        kernel(code, *args, eps, sep, fast, out, work)
    else:
        general.solve_grasps(code, *map(_items, args), eps, sep, fast, _items(out), _items(work))
    return out


def _plugin_many(name: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """The installed allocator ``name`` on each grasp (its Python function); AllocationError
    naming it, its package and the grasp when it raises or returns other than r finite
    forces."""
    plugin = plugins.get(name)
    assert plugin is not None  # check() found it
    fn = plugins.python_function(plugin.obj)
    N, r = len(G), M.shape[-1]
    out = np.zeros((N, r))
    for k in range(N):
        what = None
        try:
            with np.errstate(all="ignore"):
                x = np.asarray(fn(G[k].copy(), M[k].copy(), lam[k].copy()), dtype=float)
        except Exception as exc:  # a plugin may fail in any way: named, not a crash
            what = f"raised {type(exc).__name__}: {exc}"
        else:
            if x.shape != (r,):
                what = f"returned shape {x.shape}, expected ({r},)"
            elif not np.all(np.isfinite(x)):
                what = "returned a NaN or infinite force"
        if what is not None:
            raise AllocationError(
                f"allocator plugin {name!r} (package {plugin.package!r}) {what} (grasp {k})"
            )
        out[k] = x
    return out
