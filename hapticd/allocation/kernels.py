"""The allocation's kernels, written once in the subset of Python numba compiles (float
arithmetic, ``math``, loops over preallocated numpy arrays, no objects, no allocation):
``allocation_step`` (one tick of F fingers: which contacts, contact onset, which
definition), which the tick's one call (hapticd.physics.kernels.tick_step) compiles in and
ContactAllocator runs, and ``allocate_grasps`` (allocate_many's batch). ``uncompiled`` runs
a kernel as plain Python. The actuation frame's axes (``grasp_axes``) are here too: the
actuated directions (hapticd.allocation.actuation) follow them.

Units: positions m, forces N.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np

from hapticd.allocation import closed, general
from hapticd.allocation.accuracy import one_contact_residuals, two_contact_residuals
from hapticd.allocation.closed import one_contact, two_contact
from hapticd.allocation.general import (
    B0_ROW,
    LAM_ROW,
    T1_ROW,
    XO_ROW,
    layout,
    residuals,
    soft_apply,
    soft_prepare,
    solve_grasps,
)
from hapticd.allocation.general import general as general_path


@functools.cache
def python_form(fn: Callable[..., object]) -> Callable[..., object]:
    """Kernel ``fn`` as plain Python (what ``rendering.kernels=python`` runs): the same
    function, given its arrays as memoryviews (``items``), whose items are Python's floats
    and ints: several times quicker in the interpreter than numpy's scalars, and the same
    IEEE arithmetic as the compiled code (an overflow gives inf, a division by zero raises
    as numba's does). One function per kernel."""

    @functools.wraps(fn)
    def run(*args: object) -> object:
        views = [items(a) for a in args]
        if any(type(a) is np.ndarray for a in views):
            # An array with no such view: numpy's scalars, which would warn on the loop.
            with np.errstate(all="ignore"):
                return fn(*views)
        return fn(*views)

    return run


def uncompiled(name: str) -> Callable[..., object]:
    """Kernel ``name`` of this module as plain Python (``python_form``)."""
    return python_form(globals()[name])


# The memoryviews ``items`` made, by the id of their array (kept alive beside them):
# the stages hand the kernels the same arrays every tick.
_VIEWS: dict[int, tuple[np.ndarray, memoryview]] = {}


def items(a: object) -> object:
    """A C-contiguous numpy array as a memoryview of the same memory and shape (read and
    written in place); anything else as it is."""
    if type(a) is not np.ndarray:
        return a
    hit = _VIEWS.get(id(a))
    if hit is not None and hit[0] is a:
        return hit[1]
    try:
        # Through bytes: numpy exports a record's unaligned fields as "=d", which a
        # memoryview does not index.
        view = memoryview(a).cast("B").cast(a.dtype.char, a.shape)
    except (TypeError, ValueError):  # not C-contiguous, or a format it cannot take
        return a
    if len(_VIEWS) >= 256:
        _VIEWS.clear()
    _VIEWS[id(a)] = (a, view)
    return view


# allocation_step's params: method (ALLOCATION_METHODS' index), eps, min_separation_m,
# contact_onset_n, grasp frame (1.0) or world frame (0.0), the grasp's reference point (3),
# the adaptive allocator's ratio_low, ratio_high and its gain per tick (min(1, dt /
# time_constant_s), 1 without a lag), an allocator plugin's handle (hapticd.allocation.plugins),
# the address of its compiled form (0: none; hapticd.allocation.native) and its last status
# (PLUGIN_*, written by the kernel)
ALLOCATION_PARAMS = 14
PLUGIN_HANDLE, PLUGIN_ADDRESS, PLUGIN_STATUS = 11, 12, 13
# allocation_step's carried state: the adaptive allocator's external weight alpha (0..1)
ALLOCATION_STATE = 1
# The robust allocators allocation_step computes (the closed forms for one or two contacts
# with one direction each, hapticd.allocation.general for any other grasp).
ALLOCATION_METHODS = closed.CODES
# allocation_step's outcomes: allocated; a non-finite contact point, direction or force; a
# non-finite actuator force (nothing written, alpha unchanged, either way).
ALLOCATED, NON_FINITE_INPUT, NON_FINITE_OUTPUT = 0, 2, 3
ACCURACY = 4  # allocation_step's accuracy: internal, external, total, amplification
# params[0] for an allocator plugin (after the robust methods' codes).
PLUGIN = len(ALLOCATION_METHODS)
# A plugin's statuses: allocated; it raised; its result is not (r,); not finite; absurd
# (beyond PLUGIN_GAIN |lam| + PLUGIN_SLACK_N); compiled kernels without its compiled form.
PLUGIN_OK, PLUGIN_RAISED, PLUGIN_SHAPE, PLUGIN_NON_FINITE, PLUGIN_ABSURD = 0, 1, 2, 3, 4
PLUGIN_UNAVAILABLE = 5
PLUGIN_GAIN, PLUGIN_SLACK_N = 1e4, 1.0


def allocation_work_shape(n_fingers: int, n_directions: int) -> tuple[int, int]:
    """allocation_step's workspace (float64, the caller's) for F fingers with D actuated
    directions in all: hapticd.allocation.general's rows, each direction in the world,
    then one row for the rest's allocation and the accuracy."""
    rows, cols = general.work_shape(3 * n_fingers, n_directions)
    return rows + n_directions + 1, cols


def allocate_grasps(
    code: int,
    G: np.ndarray,
    M: np.ndarray,
    lam: np.ndarray,
    alpha: np.ndarray,
    eps: float,
    min_sep: float,
    fast: bool,
    out: np.ndarray,
    work: np.ndarray,
) -> None:
    """hapticd.allocation.general.solve_grasps as a kernel (``allocate_many``'s robust
    methods compiled): G (N, 6, n), M (N or 1, n, r), lam (N, n) N, alpha (N,) into out
    (N, r) N."""
    solve_grasps(code, G, M, lam, alpha, eps, min_sep, fast, out, work)


def _dirs(work: np.ndarray, counts: np.ndarray) -> int:
    """The first of ``work``'s rows holding the D actuated directions in the world (after
    general's rows; ``counts`` (F,): each finger's number)."""
    d = 0
    for i in range(counts.shape[0]):
        d += int(counts[i])
    return work.shape[0] - d - 1


def _fill_grasp(
    in_contact: np.ndarray,
    points: np.ndarray,
    forces: np.ndarray,
    counts: np.ndarray,
    params: np.ndarray,
    skip: int,
    k: int,
    r: int,
    work: np.ndarray,
) -> None:
    """The grasp of the k fingers in contact but ``skip``, with r directions, into ``work``:
    general's G, M_a (their world directions, from ``work``'s rows after general's) and lam."""
    dirs = _dirs(work, counts)
    m0, lam = 6, 6 + 3 * k
    for t in range(3 * k):
        for j in range(r):
            work[m0 + t, j] = 0.0
    j = 0
    col = 0
    start = 0
    for i in range(in_contact.shape[0]):
        c = int(counts[i])
        if in_contact[i] != 0 and i != skip:
            x = points[i, 0] - params[5]
            y = points[i, 1] - params[6]
            z = points[i, 2] - params[7]
            for row in range(3):
                for q in range(3):
                    work[row, j + q] = 1.0 if row == q else 0.0
            work[3, j], work[3, j + 1], work[3, j + 2] = 0.0, -z, y
            work[4, j], work[4, j + 1], work[4, j + 2] = z, 0.0, -x
            work[5, j], work[5, j + 1], work[5, j + 2] = -y, x, 0.0
            for q in range(3):
                work[lam, j + q] = forces[i, q]
            for d in range(c):
                for q in range(3):
                    work[m0 + j + q, col] = work[dirs + start + d, q]
                col += 1
            j += 3
        start += c


def _task_alpha(
    in_contact: np.ndarray,
    points: np.ndarray,
    forces: np.ndarray,
    counts: np.ndarray,
    params: np.ndarray,
    alpha: float,
    work: np.ndarray,
) -> float:
    """The adaptive allocator's alpha after this tick (hapticd.allocation.AdaptiveState):
    moved by params' gain toward smoothstep((rho - ratio_low) / (ratio_high - ratio_low)) of
    the task's external ratio rho = |net force| / (|net force| + squeeze); unchanged when
    rho is not finite. The squeeze: none for one contact, the force along the grasp line
    for two, |P_int lam| / sqrt(2) for more."""
    n_fingers = in_contact.shape[0]
    k = 0
    r = 0
    n0, n1, n2 = 0.0, 0.0, 0.0
    for i in range(n_fingers):
        if in_contact[i] != 0:
            n0 += forces[i, 0]
            n1 += forces[i, 1]
            n2 += forces[i, 2]
            k += 1
            r += int(counts[i])
    squeeze = 0.0
    if k == 2:
        c0, c1 = _nth(in_contact, -1, 0), _nth(in_contact, -1, 1)
        e0 = points[c1, 0] - points[c0, 0]
        e1 = points[c1, 1] - points[c0, 1]
        e2 = points[c1, 2] - points[c0, 2]
        ne = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        q0 = forces[c0, 0] - forces[c1, 0]
        q1 = forces[c0, 1] - forces[c1, 1]
        q2 = forces[c0, 2] - forces[c1, 2]
        if ne > 0:
            squeeze = abs(e0 * q0 + e1 * q1 + e2 * q2) / (2.0 * ne)
    elif k > 2:
        _fill_grasp(in_contact, points, forces, counts, params, -1, k, r, work)
        n = 3 * k
        eps = params[1]
        soft_prepare(work, n, eps, params[2])
        lay = layout(n, 0)  # T1: a scratch row
        out = lay[T1_ROW]
        soft_apply(work, n, eps * eps, lay[LAM_ROW], out)
        s = 0.0
        for t in range(n):
            s += work[out, t] * work[out, t]
        squeeze = math.sqrt(s) / math.sqrt(2.0)
    net = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    total = net + squeeze
    rho = net / total if total > 0.0 else 0.0
    if not math.isfinite(rho):
        return alpha
    z = (rho - params[8]) / (params[9] - params[8])
    return alpha + params[10] * (closed.smoothstep(z) - alpha)


def allocation_step(
    in_contact: np.ndarray,
    device_pos: np.ndarray,
    points: np.ndarray,
    forces: np.ndarray,
    local: np.ndarray,
    counts: np.ndarray,
    params: np.ndarray,
    state: np.ndarray,
    lam_a: np.ndarray,
    rendered: np.ndarray,
    acc: np.ndarray,
    work: np.ndarray,
) -> int:
    """One tick's allocation for F fingers by a robust method, with contact onset
    (``_allocate_contacts``), its accuracy and M_a lam_a per finger: the one definition,
    which ``hapticd.allocation.contacts.ContactAllocator`` and the tick's one call run. The
    adaptive allocator's alpha (``state``) follows this tick's task first.

    The frame's ``in_contact`` (F,) u1, ``device_pos`` (F, 3) m (the grasp frame's axes
    come from fingers 0 and 1), ``points`` (F, 3) m and ``forces`` (F, 3) N. ``local``
    (D, 3): the D actuated unit directions in the actuation's frame, finger by finger;
    ``counts`` (F,): how many each finger has. ``params`` (ALLOCATION_PARAMS,), ``state``
    (ALLOCATION_STATE,), ``work`` (allocation_work_shape(F, D)). Writes ``lam_a`` (D,) N,
    ``rendered`` (F, 3) N (zero out of contact), ``acc`` (ACCURACY,) and alpha and returns
    ALLOCATED; any other outcome writes nothing.
    """
    n_fingers = in_contact.shape[0]
    alpha = state[0]
    if int(params[0]) == closed.ADAPTIVE:
        alpha = _task_alpha(in_contact, points, forces, counts, params, alpha, work)
    n = 0
    r = 0
    for i in range(n_fingers):
        if in_contact[i] != 0:
            n += 1
            r += int(counts[i])
    dirs = _dirs(work, counts)
    xk = work.shape[0] - 1
    if n > 0:
        # Every direction in the world into ``work`` (the actuation frame's axes: the
        # world's, or the grasp frame's), then the grasp's allocation.
        ax0, ax1, ax2, ay0, ay1, ay2, az0, az1, az2 = _axes(device_pos, params[4] != 0.0)
        for j in range(local.shape[0]):
            p0, p1, p2 = local[j, 0], local[j, 1], local[j, 2]
            work[dirs + j, 0] = ax0 * p0 + ay0 * p1 + az0 * p2
            work[dirs + j, 1] = ax1 * p0 + ay1 * p1 + az1 * p2
            work[dirs + j, 2] = ax2 * p0 + ay2 * p1 + az2 * p2
        outcome = _allocate_contacts(in_contact, points, forces, counts, params, alpha, work)
        if outcome != ALLOCATED:
            return outcome
    for i in range(ACCURACY):
        acc[i] = work[xk, i] if n > 0 else 0.0
    xo = layout(3 * n, r)[XO_ROW]
    s = 0
    start = 0
    for i in range(n_fingers):
        c = int(counts[i])
        r0, r1, r2 = 0.0, 0.0, 0.0
        for d in range(c):
            x = 0.0
            if in_contact[i] != 0:
                x = work[xo, s]
                s += 1
                r0 = r0 + x * work[dirs + start + d, 0]
                r1 = r1 + x * work[dirs + start + d, 1]
                r2 = r2 + x * work[dirs + start + d, 2]
            lam_a[start + d] = x
        rendered[i, 0], rendered[i, 1], rendered[i, 2] = r0, r1, r2
        start += c
    state[0] = alpha
    return ALLOCATED


def _allocate_contacts(
    in_contact: np.ndarray,
    points: np.ndarray,
    forces: np.ndarray,
    counts: np.ndarray,
    params: np.ndarray,
    alpha: float,
    work: np.ndarray,
) -> int:
    """allocation_step's grasp (this tick's alpha; the world directions in ``work``):
    ``_solve_grasp`` on the contacts, blended by ``onset_beta`` with the grasp without its
    weakest contact. Writes lam_a of the contacts' directions in general's row XO and the
    accuracy in ``work``'s last row; returns an outcome (nothing written outside ``work``)."""
    dirs = _dirs(work, counts)
    xk = work.shape[0] - 1  # the rest's share, by the grasp's columns; then the accuracy
    s = 0.0
    n = 0
    r = 0
    ones = True  # every contact has one direction: the closed forms
    weak = -1
    weakest = 0.0
    w0 = 0  # the weakest's first column
    start = 0
    for i in range(in_contact.shape[0]):
        c = int(counts[i])
        start += c
        if in_contact[i] == 0:
            continue
        n += 1
        ones = ones and c == 1
        for q in range(3):  # 0 x c is 0 for a finite c and NaN otherwise
            s += 0.0 * (points[i, q] - params[5 + q])
            for d in range(start - c, start):
                s += 0.0 * work[dirs + d, q]
            s += 0.0 * forces[i, q]
        f0, f1, f2 = forces[i, 0], forces[i, 1], forces[i, 2]
        f = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
        if weak < 0 or f < weakest:
            weak, weakest, w0 = i, f, r
        r += c
    if not math.isfinite(s):
        return NON_FINITE_INPUT
    beta = onset_beta(weakest, n, params[3])
    if beta < 1.0:  # the rest alone; none of the weakest's columns w0 .. w1 - 1
        xo = _solve_grasp(in_contact, points, forces, counts, params, weak, alpha, work)
        if xo < 0:  # a plugin failed (its status in params)
            return NON_FINITE_OUTPUT
        w1 = w0 + int(counts[weak])
        for j in range(r):
            x = 0.0 if w0 <= j < w1 else work[xo, j if j < w0 else j - w1 + w0]
            work[xk, j] = (1.0 - beta) * x
    xo = _solve_grasp(in_contact, points, forces, counts, params, -1, alpha, work)
    if xo < 0:
        return NON_FINITE_OUTPUT
    for j in range(r):
        x = work[xo, j]
        if beta < 1.0:
            x = beta * x + work[xk, j]
        work[xo, j] = x
        if not math.isfinite(x):
            return NON_FINITE_OUTPUT
    if n > 2 or not ones:  # the grasp _solve_grasp left in work
        acc = residuals(work, 3 * n, r)
    elif n == 1:
        r1, d1, l1 = _contact(points, forces, counts, params, work, _nth(in_contact, -1, 0))
        acc = one_contact_residuals(r1, d1, l1, work[xo, 0])
    else:
        r1, d1, l1 = _contact(points, forces, counts, params, work, _nth(in_contact, -1, 0))
        r2, d2, l2 = _contact(points, forces, counts, params, work, _nth(in_contact, -1, 1))
        acc = two_contact_residuals(r1, r2, d1, d2, l1, l2, work[xo, 0], work[xo, 1])
    work[xk, 0], work[xk, 1], work[xk, 2], work[xk, 3] = acc
    return ALLOCATED


def onset_beta(weakest: float, n: int, onset: float) -> float:
    """Contact onset: the weight (0..1) of the grasp of ``n`` contacts whose weakest force is
    ``weakest`` N, for ``onset`` N (the grasp without that contact weighs 1 - beta):
    smoothstep(weakest / onset) for two contacts or more, else 1. A contact being made or
    broken so joins the grasp gradually: else the grasp matrix (and IF's squeeze) would jump
    when it appears or leaves."""
    return closed.smoothstep(weakest / onset) if n > 1 and onset > 0.0 else 1.0


def _nth(in_contact: np.ndarray, skip: int, s: int) -> int:
    """The finger of contact ``s`` (0, 1, ...) among those in contact but ``skip``."""
    for i in range(in_contact.shape[0]):
        if in_contact[i] != 0 and i != skip:
            if s == 0:
                return i
            s -= 1
    return -1


def _contact(
    points: np.ndarray,
    forces: np.ndarray,
    counts: np.ndarray,
    params: np.ndarray,
    work: np.ndarray,
    i: int,
) -> tuple[closed.V3, closed.V3, closed.V3]:
    """Finger ``i``'s contact: its offset r from the grasp's reference point (m), its first
    world direction d and its force l (N)."""
    row = _dirs(work, counts)
    for f in range(i):
        row += int(counts[f])
    r = (points[i, 0] - params[5], points[i, 1] - params[6], points[i, 2] - params[7])
    d = (work[row, 0], work[row, 1], work[row, 2])
    return r, d, (forces[i, 0], forces[i, 1], forces[i, 2])


def _solve_grasp(
    in_contact: np.ndarray,
    points: np.ndarray,
    forces: np.ndarray,
    counts: np.ndarray,
    params: np.ndarray,
    skip: int,
    alpha: float,
    work: np.ndarray,
) -> int:
    """lam_a of the contacts but ``skip`` into general's row XO, which it returns: the closed
    forms of hapticd.allocation.closed for one or two contacts with one direction each, the
    general path for any other grasp (which ``_fill_grasp`` puts into ``work``); an
    allocator plugin on that grasp (-1 when it fails: ``_plugin``)."""
    method = int(params[0])
    eps, min_sep = params[1], params[2]
    k = 0
    r = 0
    ones = True
    for i in range(in_contact.shape[0]):
        if in_contact[i] != 0 and i != skip:
            k += 1
            r += int(counts[i])
            ones = ones and counts[i] == 1.0
    xo = layout(3 * k, r)[XO_ROW]
    if method == PLUGIN:
        _fill_grasp(in_contact, points, forces, counts, params, skip, k, r, work)
        return xo if r == 0 or _plugin(work, 3 * k, r, params) == PLUGIN_OK else -1
    if k > 2 or not ones:
        _fill_grasp(in_contact, points, forces, counts, params, skip, k, r, work)
        general_path(method, work, 3 * k, r, eps, min_sep, alpha)
        return xo
    r1, d1, l1 = _contact(points, forces, counts, params, work, _nth(in_contact, skip, 0))
    if k == 1:
        work[xo, 0] = one_contact(method, r1, d1, l1, eps, alpha)
    else:
        r2, d2, l2 = _contact(points, forces, counts, params, work, _nth(in_contact, skip, 1))
        work[xo, 0], work[xo, 1] = two_contact(method, r1, r2, d1, d2, l1, l2, eps, min_sep, alpha)
    return xo


def _plugin(work: np.ndarray, n: int, r: int, params: np.ndarray) -> int:
    """An allocator plugin (params' handle and address) on the grasp ``_fill_grasp`` left in
    ``work`` (n force components, r directions): lam_a into general's row XO, checked
    finite and bounded (``_plugin_bounded``); its status, also into params[PLUGIN_STATUS]."""
    lay = layout(n, r)
    xo = lay[XO_ROW]
    status = plugin_call(work, n, r, params[PLUGIN_HANDLE], params[PLUGIN_ADDRESS], lay[B0_ROW], xo)
    if status == PLUGIN_OK:
        status = _plugin_bounded(work, n, r, xo)
    params[PLUGIN_STATUS] = float(status)
    return status


def _plugin_bounded(work: np.ndarray, n: int, r: int, xo: int) -> int:
    """PLUGIN_OK when the plugin's lam_a (row XO) is finite and at most PLUGIN_GAIN |lam| +
    PLUGIN_SLACK_N (N), lam the grasp's forces (general's row LAM); else why not."""
    out = 0.0
    for j in range(r):
        x = work[xo, j]
        if not math.isfinite(x):
            return PLUGIN_NON_FINITE
        out += x * x
    lam = 0.0
    for t in range(n):
        lam += work[6 + n, t] * work[6 + n, t]
    if math.sqrt(out) > PLUGIN_GAIN * math.sqrt(lam) + PLUGIN_SLACK_N:
        return PLUGIN_ABSURD
    return PLUGIN_OK


def plugin_call(
    work: np.ndarray, n: int, r: int, handle: float, address: float, scratch: int, xo: int
) -> int:
    """The allocator plugin of ``handle`` on the grasp in general's rows of ``work`` (G rows
    0-5, M_a rows 6 to 6 + n - 1, lam row 6 + n; n force components, r directions), its
    lam_a into row ``xo``; a PLUGIN_ status. Python's form (the plugin's Python function,
    ``register_plugin``'s); compiled code runs hapticd.physics.native's, which calls the
    plugin compiled at ``address`` on a copy in the rows from ``scratch``."""
    w = np.asarray(work)
    G, M, lam = w[0:6, :n].copy(), w[6 : 6 + n, :r].copy(), w[6 + n, :n].copy()
    try:
        with np.errstate(all="ignore"):
            lam_a = np.asarray(_PLUGINS[int(handle)](G, M, lam), dtype=float)
    except Exception:  # a plugin may fail in any way: a fault naming it, not a crash
        return PLUGIN_RAISED
    if lam_a.shape != (r,):
        return PLUGIN_SHAPE
    w[xo, :r] = lam_a
    return PLUGIN_OK


# The allocator plugins' Python functions by handle (``register_plugin``): append only, so
# a handle in a kernel's params stays valid.
_PLUGINS: list[Callable[..., object]] = []


def register_plugin(fn: Callable[..., object]) -> int:
    """The handle of an allocator plugin's Python function ``fn`` (registered once)."""
    for i, f in enumerate(_PLUGINS):
        if f is fn:
            return i
    _PLUGINS.append(fn)
    return len(_PLUGINS) - 1


def plugin_function(handle: int) -> Callable[..., object]:
    """The Python function of the allocator plugin ``handle``."""
    return _PLUGINS[handle]


def _axes(device_pos: np.ndarray, grasp: bool) -> tuple[float, ...]:
    """The actuation frame's axes x, y, z in the world (9 floats): the world's, or the grasp
    frame of fingers 0 and 1 (``grasp_axes``)."""
    if not grasp:
        return 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
    return grasp_axes(
        device_pos[0, 0], device_pos[0, 1], device_pos[0, 2],
        device_pos[1, 0], device_pos[1, 1], device_pos[1, 2],
    )  # fmt: skip


def grasp_axes(
    p0: float, p1: float, p2: float, q0: float, q1: float, q2: float
) -> tuple[float, ...]:
    """The grasp frame's axes x, y, z in the world (9 floats) for fingers at p and q (m):
    x = unit(q - p); z = world up made orthogonal to x; y = z cross x. Degenerate cases
    fall back to world axes: coincident (or non-finite) points use world x; a vertical
    grasp line uses world x in place of up. (hapticd.allocation.actuation.grasp_axes is this.)"""
    ax0, ax1, ax2 = 1.0, 0.0, 0.0
    ex, ey, ez = q0 - p0, q1 - p1, q2 - p2
    nx = math.sqrt(ex * ex + ey * ey + ez * ez)
    if nx > 1e-9:
        ax0, ax1, ax2 = ex / nx, ey / nx, ez / nx
    f0, f1, f2 = (0.0, 0.0, 1.0) if abs(ax2) < 1.0 - 1e-6 else (1.0, 0.0, 0.0)
    c = f0 * ax0 + f1 * ax1 + f2 * ax2
    az0, az1, az2 = f0 - c * ax0, f1 - c * ax1, f2 - c * ax2
    nz = math.sqrt(az0 * az0 + az1 * az1 + az2 * az2)
    az0, az1, az2 = az0 / nz, az1 / nz, az2 / nz
    ay0, ay1, ay2 = az1 * ax2 - az2 * ax1, az2 * ax0 - az0 * ax2, az0 * ax1 - az1 * ax0
    return ax0, ax1, ax2, ay0, ay1, ay2, az0, az1, az2


# Functions this module's kernels call (everything else a kernel does is inline): its own
# and the allocation's closed forms and general path (hapticd.allocation.closed, general
# and accuracy, written once for the loop, allocate() and allocate_many). The compiler
# (hapticd.physics.jit) compiles them into the kernels that call them.
KERNEL_HELPERS: tuple[Callable[..., object], ...] = (
    *closed.KERNEL_HELPERS,
    *general.KERNEL_HELPERS,
    one_contact_residuals,
    two_contact_residuals,
    _dirs,
    _fill_grasp,
    _task_alpha,
    _nth,
    _contact,
    _solve_grasp,
    _allocate_contacts,
    onset_beta,
    _plugin,
    _plugin_bounded,
    plugin_call,
    allocation_step,
    _axes,
    grasp_axes,
)
# The sources whose code or constants this module's kernels compile in: numba's cache
# knows only this file's, so the compiler keys its record of compiled kernels on all.
SOURCES = (
    __file__,
    closed.__file__,
    general.__file__,
    one_contact_residuals.__code__.co_filename,
)
