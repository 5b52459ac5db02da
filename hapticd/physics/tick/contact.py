"""The Contact stage: god-object (proxy) contact of spherical fingertips with convex
obstacles (the object, the ground, walls), after Zilles & Salisbury (1995). Its
declaration, the object's planes in the world (``world_planes``) and its kernel
(``contact_step``), split into the proxy's push-out, its slide toward the device and the
finger's outputs.

Units: positions m, velocities m/s, stiffness N/m, damping N s/m, forces N.
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.physics.tick.layout import Declaration

# object, 1...: the surfaces in order), its first and past-last rows, and a surface's
# stiffness (N/m) and damping (N s/m) (zeros for the object's rows)
PLANE_COLUMNS = 9
# contact_step's state columns per finger: the proxy (3, m; the stage's one copy), the
# fingertip radius (m), the active planes (3: rows of ``planes``, -1 past the last) and
# their multipliers (3, m: proxy - device = sum mu n over them), then work space: planes
# pushed through (3), right-hand sides (3)
CONTACT_STATE = 16
_C_RADIUS, _C_ACTIVE, _C_MU, _C_PUSHED, _C_RHS = 3, 4, 7, 10, 13
# contact_step's outcomes: done; not taken (a non-finite plane, device sample, proxy or
# radius: nothing written; the stage says which and refuses the tick).
CONTACT_DONE, CONTACT_NOT_TAKEN = 0, 1
# A point within this distance (m) of a plane counts as on it. A proxy that slides on a
# face lies on its plane only to rounding (some 1e-17 m at hand scale, whatever the face's
# orientation), and so does the projection of the device onto it: a path between two such
# points lies on the plane, it does not enter the object through it.
_ON_PLANE = 1e-13
# Segment parameters closer than this count as touching, not entering: keeps a path that
# grazes an edge from capturing the proxy there.
_T_EPS = 1e-12
# Active planes at most (face, edge, corner).
_MAX_CONSTRAINTS = 3
# Proxy moves per tick: each face a fast finger crosses on a convex mesh takes two (slide
# off, re-enter), and 2 cm per tick over a sphere of 5 mm faces took up to 14.
_MAX_ITER = 16
# A proxy within this distance (m) of an obstacle still touches it.
_FREE_TOL = 1e-12
# Below this Gram determinant (two planes: sin^2 of their angle, within 3e-5 rad of
# parallel; three: the squared volume their normals span) the Gram system counts as
# singular and ``_gram_mu`` takes its minimum-norm rule instead of the inverse.
_GRAM_MIN = 1e-9


def _along(planes: np.ndarray, kk: int, m: float, x0: float, x1: float, x2: float) -> tuple:
    """x + m n (m) for the unit normal n of row kk of ``planes``."""
    return x0 + m * planes[kk, 0], x1 + m * planes[kk, 1], x2 + m * planes[kk, 2]


def _gap(planes: np.ndarray, kk: int, r: float, x0: float, x1: float, x2: float) -> float:
    """How far (m) x lies outside row kk of ``planes`` moved out by r (< 0: inside)."""
    return (planes[kk, 0] * x0 + planes[kk, 1] * x1 + planes[kk, 2] * x2) - (planes[kk, 3] + r)


def _project(
    planes: np.ndarray, state: np.ndarray, i: int, base: int, k: int, r: float, x: tuple
) -> tuple:
    """The point (3,) m nearest x on finger i's k planes (rows state[i, base:base + k])
    moved out by r, x plus sum mu n: solves the multipliers into state[i, _C_MU:]."""
    x0, x1, x2 = x
    for q in range(k):
        state[i, _C_RHS + q] = -_gap(planes, int(state[i, base + q]), r, x0, x1, x2)
    _gram_mu(planes, state, i, k, base)
    for q in range(k):
        x0, x1, x2 = _along(planes, int(state[i, base + q]), state[i, _C_MU + q], x0, x1, x2)
    return x0, x1, x2


def _gram_mu(planes: np.ndarray, state: np.ndarray, i: int, k: int, base: int) -> None:
    """The multipliers state[i, _C_MU:_C_MU + k] solving G mu = rhs for the Gram matrix
    G = N N^T of the k (1 to 3) unit normals whose rows in ``planes`` are
    state[i, base:base + k], rhs = state[i, _C_RHS:_C_RHS + k] (m).

    Plain float sums in a fixed order: the 2 x 2 and 3 x 3 systems by their adjugates
    (Cramer's rule), the unit diagonal taken as exactly 1 (one plane: mu = rhs). A singular
    system (determinant <= ``_GRAM_MIN``) takes a closed-form minimum-norm rule instead of
    an inverse that would throw the proxy far away:

    - two (nearly) parallel or antiparallel planes (cosine c, s its sign): G's
      pseudo-inverse with its small eigenvalue 1 - |c| dropped, mu = (m, s m) with
      m = (r0 + s r1) / (2 (1 + |c|)) (numpy's ``lstsq`` for exactly parallel planes).
      Parallel planes share the push; antiparallel ones (a finger between two faces
      that face each other) get multipliers of opposite signs, so one is released;
    - three planes of which two, u and v, are (nearly) parallel: those two act as one
      plane (normal n_u, right-hand side (r_u + s r_v) / 2), solved with the third;
      their multiplier a is split evenly, (a / 2, s a / 2). All three parallel: the
      rank-one pseudo-inverse, mu_i = s_i (sum_j s_j r_j) / 9;
    - three pairwise distinct normals in (nearly) one plane: the best-conditioned
      pair (the largest 2 x 2 determinant, the first on a tie), the third's multiplier 0.

    Multipliers keep their meaning: mu_i > 0 where plane i pushes outward.
    """
    r0 = state[i, _C_RHS]
    if k == 1:
        state[i, _C_MU] = r0
        return
    q0 = int(state[i, base])
    q1 = int(state[i, base + 1])
    n0x, n0y, n0z = planes[q0, 0], planes[q0, 1], planes[q0, 2]
    n1x, n1y, n1z = planes[q1, 0], planes[q1, 1], planes[q1, 2]
    r1 = state[i, _C_RHS + 1]
    a = n0x * n1x + n0y * n1y + n0z * n1z
    if k == 2:
        if 1.0 - a * a > _GRAM_MIN:
            state[i, _C_MU], state[i, _C_MU + 1] = _solve2(a, r0, r1)
        else:
            s = 1.0 if a >= 0.0 else -1.0
            m = (r0 + s * r1) / (2.0 * (1.0 + abs(a)))
            state[i, _C_MU], state[i, _C_MU + 1] = m, s * m
        return
    q2 = int(state[i, base + 2])
    n2x, n2y, n2z = planes[q2, 0], planes[q2, 1], planes[q2, 2]
    r2 = state[i, _C_RHS + 2]
    b = n0x * n2x + n0y * n2y + n0z * n2z
    c = n1x * n2x + n1y * n2y + n1z * n2z
    a00 = 1.0 - c * c
    a11 = 1.0 - b * b
    a22 = 1.0 - a * a
    a01 = b * c - a
    a02 = a * c - b
    a12 = a * b - c
    det = a00 + a * a01 + b * a02
    if det > _GRAM_MIN:
        state[i, _C_MU] = (a00 * r0 + a01 * r1 + a02 * r2) / det
        state[i, _C_MU + 1] = (a01 * r0 + a11 * r1 + a12 * r2) / det
        state[i, _C_MU + 2] = (a02 * r0 + a12 * r1 + a22 * r2) / det
        return
    # The pair (u, v) the rule keeps or merges and the third plane w, by the pairs' 2 x 2
    # determinants (a22: planes 0 and 1, a11: 0 and 2, a00: 1 and 2): with two (nearly)
    # parallel planes the smallest, else the largest (the smallest of their negatives).
    two = a22 <= _GRAM_MIN or a11 <= _GRAM_MIN or a00 <= _GRAM_MIN
    g = 1.0 if two else -1.0
    if g * a22 <= g * a11 and g * a22 <= g * a00:
        u, v, w, cuv, cuw = 0, 1, 2, a, b
    elif g * a11 <= g * a00:
        u, v, w, cuv, cuw = 0, 2, 1, b, a
    else:
        u, v, w, cuv, cuw = 1, 2, 0, c, a
    ru, rv, rw = state[i, _C_RHS + u], state[i, _C_RHS + v], state[i, _C_RHS + w]
    mu_w = 0.0
    if not two:
        mu_u, mu_v = _solve2(cuv, ru, rv)
    else:
        s = 1.0 if cuv >= 0.0 else -1.0
        rm = (ru + s * rv) / 2.0
        if 1.0 - cuw * cuw > _GRAM_MIN:
            am, mu_w = _solve2(cuw, rm, rw)
            mu_u, mu_v = am / 2.0, s * am / 2.0
        else:
            t = 1.0 if cuw >= 0.0 else -1.0
            mu_u = (ru + s * rv + t * rw) / 9.0
            mu_v, mu_w = s * mu_u, t * mu_u
    state[i, _C_MU + u], state[i, _C_MU + v], state[i, _C_MU + w] = mu_u, mu_v, mu_w


def _solve2(c: float, r0: float, r1: float) -> tuple[float, float]:
    """mu (2,) solving [[1, c], [c, 1]] mu = (r0, r1) (two unit normals' Gram system, c
    their cosine) by Cramer's rule."""
    det = 1.0 - c * c
    return (r0 - c * r1) / det, (r1 - c * r0) / det


def _finite(
    device_pos: np.ndarray, device_vel: np.ndarray, planes: np.ndarray, state: np.ndarray
) -> bool:
    """Whether the planes' normals and offsets, the device samples, the proxies and the radii
    are all finite (contact takes nothing else)."""
    for kk in range(planes.shape[0]):
        for col in range(4):
            if not math.isfinite(planes[kk, col]):
                return False
    for i in range(device_pos.shape[0]):
        for col in range(3):
            if not (math.isfinite(device_pos[i, col]) and math.isfinite(device_vel[i, col])):
                return False
        for col in range(_C_RADIUS + 1):  # the proxy and the radius
            if not math.isfinite(state[i, col]):
                return False
    return True


def _deepest(
    planes: np.ndarray, lo: int, hi: int, r: float, p0: float, p1: float, p2: float
) -> tuple[float, int]:
    """How far (m, < 0) p lies inside the obstacle of rows lo to hi inflated by r, and the
    row of its nearest plane; a distance >= 0 when p is outside or on one of its planes."""
    best = -math.inf
    arg = lo
    for kk in range(lo, hi):
        v = (planes[kk, 0] * p0 + planes[kk, 1] * p1 + planes[kk, 2] * p2) - (planes[kk, 3] + r)
        if v >= 0.0:  # outside (or on) this plane: not inside the obstacle
            best = v
            break
        if v > best:
            best = v
            arg = kk
    return best, arg


def _push_out(
    planes: np.ndarray, state: np.ndarray, i: int, r: float, n_obst: int
) -> tuple[float, float, float]:
    """Finger i's proxy out of every obstacle it is inside: through the nearest plane, or
    onto the projection on the planes pushed through where they all push (a crease)."""
    n_planes = planes.shape[0]
    p0, p1, p2 = state[i, 0], state[i, 1], state[i, 2]
    s = (p0, p1, p2)
    npushed = 0
    for _ in range(n_obst + 1):
        moved = False
        lo = 0
        while lo < n_planes:
            hi = int(planes[lo, 6])
            best, arg = _deepest(planes, lo, hi, r, p0, p1, p2)
            if best < 0.0:
                moved = True
                found = False
                for q in range(npushed):
                    if int(state[i, _C_PUSHED + q]) == arg:
                        found = True
                if not found and npushed < _MAX_CONSTRAINTS:
                    state[i, _C_PUSHED + npushed] = arg
                    npushed += 1
                x = _along(planes, arg, -best, p0, p1, p2)
                if npushed > 1:
                    y = _project(planes, state, i, _C_PUSHED, npushed, r, s)
                    mn = state[i, _C_MU]
                    for q in range(1, npushed):
                        if state[i, _C_MU + q] < mn:
                            mn = state[i, _C_MU + q]
                    if mn >= 0.0:
                        x = y
                p0, p1, p2 = x
            lo = hi
        if not moved:
            break
    return p0, p1, p2


def _entry(
    planes: np.ndarray,
    lo: int,
    hi: int,
    r: float,
    p: tuple[float, float, float],
    e: tuple[float, float, float],
) -> tuple[bool, float, int]:
    """Whether the path p + t e (t in [0, 1)) enters the obstacle of rows lo to hi inflated
    by r, when (t) and through which plane (-1: p is inside every plane). A path whose two
    ends are outside or on one plane never enters; a crossing time is computed only on the
    segment (no ratio of two rounding errors); a path grazing an edge does not enter."""
    p0, p1, p2 = p
    e0, e1, e2 = e
    t_enter = 0.0
    t_exit = math.inf
    plane = -1
    for kk in range(lo, hi):
        nx, ny, nz = planes[kk, 0], planes[kk, 1], planes[kk, 2]
        num = (planes[kk, 3] + r) - (nx * p0 + ny * p1 + nz * p2)
        denom = nx * e0 + ny * e1 + nz * e2
        if num <= _ON_PLANE:
            if num - denom <= _ON_PLANE:
                return False, t_enter, plane
            if num < 0.0:
                tt = num / denom
                if tt > t_enter:
                    t_enter = tt
                    plane = kk
            elif plane < 0:
                plane = kk
        elif denom > num:
            tt = num / denom
            if tt < t_exit:
                t_exit = tt
    grazes = plane >= 0 and t_exit <= t_enter + _T_EPS
    return not grazes, t_enter, plane


def _first_entry(
    planes: np.ndarray, r: float, p: tuple[float, float, float], e: tuple[float, float, float]
) -> tuple[float, int]:
    """The first obstacle the path p + t e enters: when (t) and the plane's row (-1: none);
    inside every plane of one (a push-out could not clear another obstacle): in at once,
    through the nearest."""
    n_planes = planes.shape[0]
    p0, p1, p2 = p
    bt = 0.0
    bk = -1
    lo = 0
    while lo < n_planes:
        hi = int(planes[lo, 6])
        enters, t_enter, plane = _entry(planes, lo, hi, r, p, e)
        if enters and (bk < 0 or t_enter < bt):
            bt = t_enter
            bk = plane
            if plane < 0:  # inside every plane: through the nearest
                bk = lo
                best = -math.inf
                for kk in range(lo, hi):
                    v = _gap(planes, kk, r, p0, p1, p2)
                    if v > best:
                        best = v
                        bk = kk
        lo = hi
    return bt, bk


def _still_held(
    planes: np.ndarray, state: np.ndarray, i: int, nact: int, r: float, p0: float, p1: float,
    p2: float,
) -> int:  # fmt: skip
    """Keep those of finger i's nact active planes whose obstacle still holds the proxy at
    p (within ``_FREE_TOL``) and that push (mu >= 0); how many are kept."""
    w = 0
    for q in range(nact):
        qq = int(state[i, _C_ACTIVE + q])
        dist = -math.inf
        for kk in range(int(planes[qq, 5]), int(planes[qq, 6])):
            v = (planes[kk, 0] * p0 + planes[kk, 1] * p1 + planes[kk, 2] * p2) - (planes[kk, 3] + r)
            if v > dist:
                dist = v
                if v > _FREE_TOL:  # off this obstacle: the rest cannot change that
                    break
        m = state[i, _C_MU + q]
        if dist <= _FREE_TOL and m >= 0.0:
            state[i, _C_ACTIVE + w] = qq
            state[i, _C_MU + w] = m
            w += 1
    return w


def _slide(
    planes: np.ndarray,
    state: np.ndarray,
    i: int,
    r: float,
    d: tuple[float, float, float],
    p: tuple[float, float, float],
) -> tuple[float, float, float, int, bool]:
    """Finger i's proxy from p toward the device d, stopping where the path enters an
    obstacle and sliding on up to three active planes (state[i, _C_ACTIVE:]), releasing
    those it slid off: the proxy, how many planes are active, and whether they hold it (it
    reached its projection on them)."""
    d0, d1, d2 = d
    p0, p1, p2 = p
    nact = 0
    for _ in range(_MAX_ITER):
        t0, t1, t2 = d0, d1, d2
        if nact == 1:  # _project's point, without its calls (quicker uncompiled)
            qq = int(state[i, _C_ACTIVE])
            state[i, _C_MU] = m = -_gap(planes, qq, r, d0, d1, d2)
            t0, t1, t2 = _along(planes, qq, m, d0, d1, d2)
        elif nact > 1:
            t0, t1, t2 = _project(planes, state, i, _C_ACTIVE, nact, r, (d0, d1, d2))
        e0, e1, e2 = t0 - p0, t1 - p1, t2 - p2
        bt, bk = _first_entry(planes, r, (p0, p1, p2), (e0, e1, e2))
        if bk >= 0:
            p0, p1, p2 = p0 + bt * e0, p1 + bt * e1, p2 + bt * e2
            again = False
            for q in range(nact):
                if int(state[i, _C_ACTIVE + q]) == bk:
                    again = True
            if again or nact == _MAX_CONSTRAINTS:
                break  # numerically stuck in a corner: stay at the contact point
            state[i, _C_ACTIVE + nact] = bk
            nact += 1
            continue
        p0, p1, p2 = t0, t1, t2
        if nact == 0:
            break
        # Slid off an obstacle into free space: its planes no longer hold the proxy.
        w = _still_held(planes, state, i, nact, r, p0, p1, p2)
        if w == nact:
            return p0, p1, p2, nact, True
        nact = w
    return p0, p1, p2, nact, False


def _pushing(
    planes: np.ndarray,
    state: np.ndarray,
    i: int,
    r: float,
    d: tuple[float, float, float],
    p: tuple[float, float, float],
    nact: int,
    held: bool,
) -> int:
    """Finger i's active planes that push, how many: held, those with mu > 0; stopped
    short of a projection, those the device is inside of (the others do not push), their
    multipliers from p - device."""
    d0, d1, d2 = d
    w = 0
    for q in range(nact):
        qq = int(state[i, _C_ACTIVE + q])
        if (state[i, _C_MU + q] > 0.0) if held else (_gap(planes, qq, r, d0, d1, d2) < 0.0):
            state[i, _C_ACTIVE + w] = qq
            state[i, _C_MU + w] = state[i, _C_MU + q]
            w += 1
    nact = w
    if not held and nact > 0:
        f0, f1, f2 = p[0] - d0, p[1] - d1, p[2] - d2
        for q in range(nact):
            qq = int(state[i, _C_ACTIVE + q])
            state[i, _C_RHS + q] = f0 * planes[qq, 0] + f1 * planes[qq, 1] + f2 * planes[qq, 2]
        _gram_mu(planes, state, i, nact, _C_ACTIVE)
    return nact


def _surfaces_force(
    planes: np.ndarray, state: np.ndarray, i: int, nact: int, v: tuple[float, float, float]
) -> tuple[float, float, float, int, int]:
    """The surfaces' force (N) on finger i moving at v (m/s): each active surface plane's
    max(k mu - b v . n, 0) along n; and how many of its active planes are the object's,
    and the first of them."""
    v0, v1, v2 = v
    g0, g1, g2 = 0.0, 0.0, 0.0
    n_obj = 0
    first = -1
    for q in range(nact):
        qq = int(state[i, _C_ACTIVE + q])
        if planes[qq, 4] == 0.0:
            first = qq if n_obj == 0 else first
            n_obj += 1
            continue
        vn = planes[qq, 0] * v0 + planes[qq, 1] * v1 + planes[qq, 2] * v2
        mag = planes[qq, 7] * state[i, _C_MU + q] - planes[qq, 8] * vn
        if mag < 0.0:  # max(mag, 0.0): NaN stays, as with Python's max
            mag = 0.0
        g0, g1, g2 = _along(planes, qq, mag, g0, g1, g2)
    return g0, g1, g2, n_obj, first


def _on_object(
    planes: np.ndarray,
    state: np.ndarray,
    i: int,
    nact: int,
    d: tuple[float, float, float],
    n_obj: int,
    first: int,
) -> tuple[float, float, float, float, float, float]:
    """Finger i in contact with the object (n_obj of its nact active planes, the first of
    them ``first``): the device moved out by the object's planes alone, and the contact
    normal (the first plane's, or along the push when several)."""
    d0, d1, d2 = d
    x0, x1, x2 = d0, d1, d2
    for q in range(nact):
        qq = int(state[i, _C_ACTIVE + q])
        if planes[qq, 4] == 0.0:
            x0, x1, x2 = _along(planes, qq, state[i, _C_MU + q], x0, x1, x2)
    n0, n1, n2 = planes[first, 0], planes[first, 1], planes[first, 2]
    if n_obj > 1:
        u0, u1, u2 = x0 - d0, x1 - d1, x2 - d2
        norm = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        if norm > 1e-15:
            n0, n1, n2 = u0 / norm, u1 / norm, u2 / norm
    return x0, x1, x2, n0, n1, n2


def contact_step(
    device_pos: np.ndarray,
    device_vel: np.ndarray,
    planes: np.ndarray,
    state: np.ndarray,
    proxy_pos: np.ndarray,
    in_contact: np.ndarray,
    surface_point: np.ndarray,
    contact_point: np.ndarray,
    contact_normal: np.ndarray,
    env_force: np.ndarray,
) -> int:
    """One tick of god-object (proxy) contact for F spherical fingertips against convex
    obstacles (the object, the ground, walls): the Contact stage's physics.

    The proxy is the sphere centre the finger *should* have: it follows the device but
    never enters an obstacle inflated by the radius. A proxy inside one (a first tick, a
    moved object) is first pushed out through the nearest plane (onto the projection on
    the planes pushed through, in a crease). Then it moves toward the device, stops where
    the path first enters an obstacle and slides on up to three active planes (face,
    edge, corner; of any obstacles), after Zilles & Salisbury (1995), releasing planes
    that would pull and obstacles it slid off. A fast finger cannot pop through a thin
    part; the proxy ends on the device's projection onto its active planes, so proxy -
    device is their multipliers times their normals and frictionless contact is
    conservative on any face. A path that runs along a plane to rounding (within
    ``_ON_PLANE``) does not enter through it. Any number of planes per obstacle.

    ``device_pos``, ``device_vel`` (F, 3) m, m/s. ``planes`` (P, PLANE_COLUMNS): the
    object's planes (n . x <= d, unit outward n) then each surface's, as declared above;
    each finger inflates the offsets by its radius. ``state`` (F, CONTACT_STATE): the
    proxies (read, overwritten), the radii, the active planes and multipliers (written),
    work space. Writes the frame's ``proxy_pos``, ``in_contact`` (u1: touching the
    object), ``surface_point`` (the device moved out by the object's planes alone),
    ``contact_point``, ``contact_normal`` and, with surfaces, ``env_force`` (N: each
    active surface plane's max(k mu - b v . n, 0) along n). Returns CONTACT_DONE, or
    CONTACT_NOT_TAKEN for a non-finite input, having written nothing.
    """
    if not _finite(device_pos, device_vel, planes, state):
        return CONTACT_NOT_TAKEN
    n_obst = int(planes[planes.shape[0] - 1, 4]) + 1
    for i in range(device_pos.shape[0]):
        r = state[i, _C_RADIUS]
        d = (device_pos[i, 0], device_pos[i, 1], device_pos[i, 2])
        p = _push_out(planes, state, i, r, n_obst)
        p0, p1, p2, nact, held = _slide(planes, state, i, r, d, p)
        nact = _pushing(planes, state, i, r, d, (p0, p1, p2), nact, held)
        # -- this finger's outputs: the proxy, its active planes (-1 past the last), the
        # surfaces' forces
        state[i, 0], state[i, 1], state[i, 2] = p0, p1, p2
        for q in range(nact, _MAX_CONSTRAINTS):
            state[i, _C_ACTIVE + q] = -1.0
        proxy_pos[i, 0], proxy_pos[i, 1], proxy_pos[i, 2] = p0, p1, p2
        v = (device_vel[i, 0], device_vel[i, 1], device_vel[i, 2])
        g0, g1, g2, n_obj, first = _surfaces_force(planes, state, i, nact, v)
        if n_obst > 1:
            env_force[i, 0], env_force[i, 1], env_force[i, 2] = g0, g1, g2
        # In contact: the device moved out by the object's planes alone; else the proxy.
        x0, x1, x2 = p0, p1, p2
        n0, n1, n2 = 0.0, 0.0, 0.0
        if n_obj > 0:
            x0, x1, x2, n0, n1, n2 = _on_object(planes, state, i, nact, d, n_obj, first)
        in_contact[i] = 1 if n_obj > 0 else 0
        surface_point[i, 0], surface_point[i, 1], surface_point[i, 2] = x0, x1, x2
        contact_normal[i, 0], contact_normal[i, 1], contact_normal[i, 2] = n0, n1, n2
        contact_point[i, 0] = x0 - r * n0
        contact_point[i, 1] = x1 - r * n1
        contact_point[i, 2] = x2 - r * n2
    return CONTACT_DONE


def world_planes(
    rotation: np.ndarray,
    position: np.ndarray,
    body_normals: np.ndarray,
    body_offsets: np.ndarray,
    planes: np.ndarray,
) -> None:
    """The object's M face planes at its pose (``rotation`` (3, 3), ``position`` (3,) m)
    from the body frame's ``body_normals`` (M, 3) and ``body_offsets`` (M,) m into the first
    M rows of ``planes``: columns 0-2 the unit normal R n, column 3 d + (R n) . x (m)."""
    x0, x1, x2 = position[0], position[1], position[2]
    r00, r01, r02 = rotation[0, 0], rotation[0, 1], rotation[0, 2]
    r10, r11, r12 = rotation[1, 0], rotation[1, 1], rotation[1, 2]
    r20, r21, r22 = rotation[2, 0], rotation[2, 1], rotation[2, 2]
    for i in range(body_offsets.shape[0]):
        a, b, c = body_normals[i, 0], body_normals[i, 1], body_normals[i, 2]
        n0 = a * r00 + b * r01 + c * r02
        n1 = a * r10 + b * r11 + c * r12
        n2 = a * r20 + b * r21 + c * r22
        planes[i, 0], planes[i, 1], planes[i, 2] = n0, n1, n2
        planes[i, 3] = body_offsets[i] + (n0 * x0 + n1 * x1 + n2 * x2)


DECLARATION = Declaration(
    "contact",
    reads=("device_pos", "device_vel"),
    fields=(
        "device_pos",
        "device_vel",
        "frictionless_proxy",
        "frictionless_point",
        "frictionless_contact_point",
        "contact_normal",
        "env_force",
    ),
    state=(("contact", lambda n, d: (n, CONTACT_STATE)),),
    blocks=(("planes", True), ("normals", True), ("offsets", False)),
    helpers=(
        "_gram_mu",
        "_solve2",
        "_along",
        "_gap",
        "_project",
        "_finite",
        "_deepest",
        "_push_out",
        "_entry",
        "_first_entry",
        "_still_held",
        "_slide",
        "_pushing",
        "_surfaces_force",
        "_on_object",
        "contact_step",
        "world_planes",
    ),
)
