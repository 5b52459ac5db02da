"""The tick's physics, written once in the subset of Python numba compiles: float
arithmetic, ``math``, loops over preallocated numpy arrays, no objects, no allocation.

``tick_step`` is the renderer's whole tick as one call; the stages' physics
(``contact_step``, ``friction_step``, ``forces_step``, ``allocation_step``,
``free_body_step``, ``safety_step``) are compiled into it with ``KERNEL_HELPERS``.
hapticd.physics.jit compiles the entry points (its ``SIGNATURES``); ``uncompiled``
runs the same functions as plain Python. The tick as a picture: docs/architecture.md.

Units: positions m, velocities m/s, angular velocities rad/s, forces N, torques
N m, stiffness N/m, damping N s/m, mass kg, inertia kg m^2, times s.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.lib.stride_tricks import as_strided

from hapticd.allocation import kernels as allocation
from hapticd.allocation.kernels import (
    ACCURACY,
    ALLOCATION_PARAMS,
    ALLOCATION_STATE,
    NON_FINITE_INPUT,
    NON_FINITE_OUTPUT,
    _axes,
    allocation_step,
    allocation_work_shape,
    python_form,
)
from hapticd.physics.passivity import DEPENDENT, authority, control, observe


def uncompiled(name: str) -> Callable[..., object]:
    """Kernel ``name`` of this module as plain Python (hapticd.allocation.kernels'
    ``python_form``: on memoryviews of its arrays). One function per name."""
    return python_form(globals()[name])


SCRATCH_COLUMNS = 13  # per finger: c0 (3), body (3), f0 (3), torsion normal (3), cap (1)
# free_body_step's params: k, mu_t, m, dt, substeps, reach, gravity (3)
PARAMS = 9
# free_body_step's state: x (3), v (3), w (3), R (9, row by row)
STATE = 18
# free_body_step's body rows before the vertices: Ib (3), Ib_inv (3)
BODY_HEAD = 6
# free_body_step's surface columns: normal (3), offset, stiffness, damping, dynamic friction
SURFACE_COLUMNS = 7


def free_body_step(
    in_contact: np.ndarray,
    points: np.ndarray,
    forces: np.ndarray,
    normals: np.ndarray,
    params: np.ndarray,
    state: np.ndarray,
    body: np.ndarray,
    surf: np.ndarray,
    scratch: np.ndarray,
) -> None:
    """Move a free object one tick (``dt`` in ``substeps``) under the fingers' reactions
    (each finger a spring of the object's stiffness, fixed to it over the tick), gravity
    and surfaces; writes ``state`` (STATE,: x, v, w, R row by row) in place.

    The frame's ``in_contact`` (F,) u1, ``points`` (F, 3) m, ``forces`` (F, 3) N on the
    fingers, ``normals`` (F, 3); ``params`` (PARAMS,), ``body`` (BODY_HEAD + V, 3: inertia,
    its inverse, the vertices in the body frame), ``surf`` (S, SURFACE_COLUMNS) as declared
    above; ``scratch`` (F, SCRATCH_COLUMNS).
    """
    k, mu_t, m, dt, steps, reach, gx, gy, gz = params
    substeps = int(steps)
    h = dt / substeps
    x0, x1, x2, v0, v1, v2, w0, w1, w2, r00, r01, r02, r10, r11, r12, r20, r21, r22 = state
    # The pose as a unit quaternion (Shepperd's method).
    tr = r00 + r11 + r22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        qw, qx, qy, qz = 0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        qw, qx, qy, qz = (r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        qw, qx, qy, qz = (r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        qw, qx, qy, qz = (r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s
    # The fingers in contact: springs anchored in the body frame, and torsion caps.
    n_springs = n_tors = 0
    for i in range(in_contact.shape[0]):
        if in_contact[i] == 0:
            continue
        c0, c1, c2 = points[i, 0], points[i, 1], points[i, 2]
        d0, d1, d2 = c0 - x0, c1 - x1, c2 - x2
        scratch[n_springs, 0], scratch[n_springs, 1], scratch[n_springs, 2] = c0, c1, c2
        scratch[n_springs, 3] = r00 * d0 + r10 * d1 + r20 * d2
        scratch[n_springs, 4] = r01 * d0 + r11 * d1 + r21 * d2
        scratch[n_springs, 5] = r02 * d0 + r12 * d1 + r22 * d2
        f0, f1, f2 = forces[i, 0], forces[i, 1], forces[i, 2]
        scratch[n_springs, 6], scratch[n_springs, 7], scratch[n_springs, 8] = -f0, -f1, -f2
        n_springs += 1
        n0, n1, n2 = normals[i, 0], normals[i, 1], normals[i, 2]
        fn = abs(f0 * n0 + f1 * n1 + f2 * n2)
        if mu_t > 0.0 and fn > 0.0:
            scratch[n_tors, 9], scratch[n_tors, 10], scratch[n_tors, 11] = n0, n1, n2
            scratch[n_tors, 12] = mu_t * fn
            n_tors += 1
    for _ in range(substeps):
        Fx, Fy, Fz = 0.0 + m * gx, 0.0 + m * gy, 0.0 + m * gz
        Tx, Ty, Tz = 0.0, 0.0, 0.0
        for j in range(n_springs):
            b0, b1, b2 = scratch[j, 3], scratch[j, 4], scratch[j, 5]
            e0 = r00 * b0 + r01 * b1 + r02 * b2
            e1 = r10 * b0 + r11 * b1 + r12 * b2
            e2 = r20 * b0 + r21 * b1 + r22 * b2
            f0 = scratch[j, 6] - k * (x0 + e0 - scratch[j, 0])
            f1 = scratch[j, 7] - k * (x1 + e1 - scratch[j, 1])
            f2 = scratch[j, 8] - k * (x2 + e2 - scratch[j, 2])
            Fx, Fy, Fz = Fx + f0, Fy + f1, Fz + f2
            Tx = Tx + (e1 * f2 - e2 * f1)
            Ty = Ty + (e2 * f0 - e0 * f2)
            Tz = Tz + (e0 * f1 - e1 * f0)
        if surf.shape[0] > 0:
            # The surfaces' wrench: a penalty spring-damper at each vertex inside a
            # surface, Coulomb friction capped at what stops the vertex in one substep.
            sFx = sFy = sFz = sTx = sTy = sTz = 0.0
            ax = abs(x0) + abs(x1) + abs(x2)
            for js in range(surf.shape[0]):
                n0, n1, n2, d = surf[js, 0], surf[js, 1], surf[js, 2], surf[js, 3]
                nn = abs(n0) + abs(n1) + abs(n2)
                clear = n0 * x0 + n1 * x1 + n2 * x2 - nn * reach - d
                if clear > 1e-9 * (nn * (ax + reach) + abs(d)):
                    continue
                hits = 0
                for jb in range(BODY_HEAD, body.shape[0]):
                    p0, p1, p2 = body[jb, 0], body[jb, 1], body[jb, 2]
                    e0 = r00 * p0 + r01 * p1 + r02 * p2
                    e1 = r10 * p0 + r11 * p1 + r12 * p2
                    e2 = r20 * p0 + r21 * p1 + r22 * p2
                    if d - (n0 * (e0 + x0) + n1 * (e1 + x1) + n2 * (e2 + x2)) > 0.0:
                        hits += 1
                if hits == 0:
                    continue
                share = m / hits
                ks, bs, mus = surf[js, 4], surf[js, 5], surf[js, 6]
                for jb in range(BODY_HEAD, body.shape[0]):
                    p0, p1, p2 = body[jb, 0], body[jb, 1], body[jb, 2]
                    e0 = r00 * p0 + r01 * p1 + r02 * p2
                    e1 = r10 * p0 + r11 * p1 + r12 * p2
                    e2 = r20 * p0 + r21 * p1 + r22 * p2
                    pen = d - (n0 * (e0 + x0) + n1 * (e1 + x1) + n2 * (e2 + x2))
                    if not pen > 0.0:
                        continue
                    u0 = v0 + (w1 * e2 - w2 * e1)
                    u1 = v1 + (w2 * e0 - w0 * e2)
                    u2 = v2 + (w0 * e1 - w1 * e0)
                    vn = u0 * n0 + u1 * n1 + u2 * n2
                    fn = ks * pen - bs * vn
                    if fn <= 0.0:
                        continue
                    f0, f1, f2 = fn * n0, fn * n1, fn * n2
                    if mus > 0.0:
                        t0, t1, t2 = u0 - vn * n0, u1 - vn * n1, u2 - vn * n2
                        speed = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
                        if speed > 1e-12:
                            cap = mus * fn
                            stop = share * speed / h
                            kk = (stop if stop < cap else cap) / speed
                            f0, f1, f2 = f0 - kk * t0, f1 - kk * t1, f2 - kk * t2
                    sFx, sFy, sFz = sFx + f0, sFy + f1, sFz + f2
                    sTx = sTx + (e1 * f2 - e2 * f1)
                    sTy = sTy + (e2 * f0 - e0 * f2)
                    sTz = sTz + (e0 * f1 - e1 * f0)
            Fx, Fy, Fz = Fx + sFx, Fy + sFy, Fz + sFz
            Tx, Ty, Tz = Tx + sTx, Ty + sTy, Tz + sTz
        # Euler's equations in the body frame, where the inertia is constant.
        for j in range(n_tors):
            n0, n1, n2, cap = scratch[j, 9], scratch[j, 10], scratch[j, 11], scratch[j, 12]
            spin = w0 * n0 + w1 * n1 + w2 * n2
            if spin != 0.0:
                nb0 = r00 * n0 + r10 * n1 + r20 * n2
                nb1 = r01 * n0 + r11 * n1 + r21 * n2
                nb2 = r02 * n0 + r12 * n1 + r22 * n2
                a0 = body[0, 0] * nb0 + body[0, 1] * nb1 + body[0, 2] * nb2
                a1 = body[1, 0] * nb0 + body[1, 1] * nb1 + body[1, 2] * nb2
                a2 = body[2, 0] * nb0 + body[2, 1] * nb1 + body[2, 2] * nb2
                In = 0.0 + nb0 * a0 + nb1 * a1 + nb2 * a2
                stop = In * abs(spin) / h
                t = math.copysign(stop if stop < cap else cap, spin)
                Tx, Ty, Tz = Tx - t * n0, Ty - t * n1, Tz - t * n2
        wb0 = r00 * w0 + r10 * w1 + r20 * w2
        wb1 = r01 * w0 + r11 * w1 + r21 * w2
        wb2 = r02 * w0 + r12 * w1 + r22 * w2
        a0 = body[0, 0] * wb0 + body[0, 1] * wb1 + body[0, 2] * wb2
        a1 = body[1, 0] * wb0 + body[1, 1] * wb1 + body[1, 2] * wb2
        a2 = body[2, 0] * wb0 + body[2, 1] * wb1 + body[2, 2] * wb2
        g0, g1, g2 = wb1 * a2 - wb2 * a1, wb2 * a0 - wb0 * a2, wb0 * a1 - wb1 * a0
        Tb0 = r00 * Tx + r10 * Ty + r20 * Tz
        Tb1 = r01 * Tx + r11 * Ty + r21 * Tz
        Tb2 = r02 * Tx + r12 * Ty + r22 * Tz
        c0, c1, c2 = Tb0 - g0, Tb1 - g1, Tb2 - g2
        dwb0 = body[3, 0] * c0 + body[3, 1] * c1 + body[3, 2] * c2
        dwb1 = body[4, 0] * c0 + body[4, 1] * c1 + body[4, 2] * c2
        dwb2 = body[5, 0] * c0 + body[5, 1] * c1 + body[5, 2] * c2
        dw0 = r00 * dwb0 + r01 * dwb1 + r02 * dwb2
        dw1 = r10 * dwb0 + r11 * dwb1 + r12 * dwb2
        dw2 = r20 * dwb0 + r21 * dwb1 + r22 * dwb2
        v0, v1, v2 = v0 + h * Fx / m, v1 + h * Fy / m, v2 + h * Fz / m
        w0, w1, w2 = w0 + h * dw0, w1 + h * dw1, w2 + h * dw2
        x0, x1, x2 = x0 + h * v0, x1 + h * v1, x2 + h * v2
        # q advanced by w over h: exp(w h / 2) * q, normalised.
        speed = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        half = 0.5 * speed * h
        if half == math.inf:
            # A spin whose square overflowed: NaN (compiled, cos gives it; uncompiled,
            # math.cos would raise); the loop's object check then ends the run.
            qw = qx = qy = qz = math.nan
        elif not half < 1e-15:
            c, s = math.cos(half), math.sin(half) / speed
            a0, a1, a2, a3 = c, s * w0, s * w1, s * w2
            p0 = a0 * qw - a1 * qx - a2 * qy - a3 * qz
            p1 = a0 * qx + a1 * qw + a2 * qz - a3 * qy
            p2 = a0 * qy - a1 * qz + a2 * qw + a3 * qx
            p3 = a0 * qz + a1 * qy - a2 * qx + a3 * qw
            nq = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2 + p3 * p3)
            qw, qx, qy, qz = p0 / nq, p1 / nq, p2 / nq, p3 / nq
        r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
        r01 = 2.0 * (qx * qy - qw * qz)
        r02 = 2.0 * (qx * qz + qw * qy)
        r10 = 2.0 * (qx * qy + qw * qz)
        r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
        r12 = 2.0 * (qy * qz - qw * qx)
        r20 = 2.0 * (qx * qz - qw * qy)
        r21 = 2.0 * (qy * qz + qw * qx)
        r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
    state[0], state[1], state[2] = x0, x1, x2
    state[3], state[4], state[5] = v0, v1, v2
    state[6], state[7], state[8] = w0, w1, w2
    state[9], state[10], state[11] = r00, r01, r02
    state[12], state[13], state[14] = r10, r11, r12
    state[15], state[16], state[17] = r20, r21, r22


# Functions the kernels call (everything else a kernel does is inline): this module's and
# the allocation's (hapticd.allocation.kernels', written once for the loop, allocate() and
# allocate_many). hapticd.physics.jit compiles them into the kernels that call them.
KERNEL_HELPERS = (
    *allocation.KERNEL_HELPERS,
    "_gram_mu",
    "_norm3",
    "ramp_down_factor",
    "plausible",
    # tick_step's stages: compiled into it, one call per tick
    "world_planes",
    "contact_step",
    "friction_step",
    "forces_step",
    "free_body_step",
    "_passivity",
    "_span_project",
    observe,
    control,
    authority,
    "_rows",
    "_block",
    "_bytes",
    "safety_step",
    "_along",
    "_gap",
    "_project",
    "_solve2",
)
# The sources whose code or constants the kernels compile in: numba's cache knows only
# this file's, so hapticd.physics.jit keys its record of compiled kernels on all of them.
SOURCES = (__file__, *allocation.SOURCES, observe.__code__.co_filename)


# The Friction stage's per-finger array (F, FRICTION_COLUMNS), its carried state that
# friction_step reads and writes: the anchor in the object's body frame (3, m), whether it
# is set (1.0) or not (0.0), the fingertip's radius (m).
FRICTION_COLUMNS = 5
ANCHOR_SET = 3
FINGER_RADIUS = 4


# friction_step's params: static and dynamic friction coefficients
FRICTION_PARAMS = 2


def friction_step(
    in_contact: np.ndarray,
    device_pos: np.ndarray,
    plain_surface: np.ndarray,
    plain_proxy: np.ndarray,
    plain_point: np.ndarray,
    surface_point: np.ndarray,
    normals: np.ndarray,
    proxy_pos: np.ndarray,
    contact_point: np.ndarray,
    fingers: np.ndarray,
    state: np.ndarray,
    params: np.ndarray,
) -> None:
    """Coulomb stick/slip at each fingertip in contact (after CHAI3D's finger proxy; the
    Friction stage's physics): from contact's frictionless surface point, proxy
    and contact point (``plain_surface``, ``plain_proxy``, ``plain_point``, (F, 3) m),
    writes the friction proxy to ``surface_point`` (F, 3) m, ``proxy_pos`` (F, 3) m moved
    with it, and ``contact_point`` (F, 3) m to match; rows of fingers out of contact are
    contact's, copied. Each input may be its output (moved in place).

    ``in_contact`` (F,) u1, ``device_pos`` (F, 3) m and ``normals`` (F, 3) (unit) are the
    frame's. ``fingers`` (F, FRICTION_COLUMNS): the stage's anchors (body frame, m), read
    and written, their set flags (1.0 or 0.0; cleared out of contact) and the radii (m).
    ``state`` (STATE,): the object's pose, x (m) and R (row by row) as free_body_step has
    them (velocities unread). ``params`` (FRICTION_PARAMS,): mu_static, mu_dynamic.

    The frictionless point p lies on a face with unit normal n, at depth
    d = n . (p - device) >= 0. A sticking contact keeps an anchor on the face (projected
    onto the plane through p); the friction proxy stays at the anchor while it lies within
    mu_s d of p (the static cone), else slips to the dynamic cone's edge, mu_d d from p
    toward the anchor; a new contact, or one at depth <= 0, sticks at p. The force
    k (proxy - device) then has normal part k d and tangential part at most mu k d.
    """
    mu_s, mu_d = params[0], params[1]
    x0, x1, x2 = state[0], state[1], state[2]
    r00, r01, r02 = state[9], state[10], state[11]
    r10, r11, r12 = state[12], state[13], state[14]
    r20, r21, r22 = state[15], state[16], state[17]
    for i in range(in_contact.shape[0]):
        if in_contact[i] == 0:
            fingers[i, ANCHOR_SET] = 0.0
            for j in range(3):
                surface_point[i, j] = plain_surface[i, j]
                proxy_pos[i, j] = plain_proxy[i, j]
                contact_point[i, j] = plain_point[i, j]
            continue
        p0, p1, p2 = plain_surface[i, 0], plain_surface[i, 1], plain_surface[i, 2]
        n0, n1, n2 = normals[i, 0], normals[i, 1], normals[i, 2]
        # The friction proxy: p stays where contact put it (a new contact sticks there)
        # unless an anchor held from the last tick moves it.
        q0, q1, q2 = p0, p1, p2
        if fingers[i, ANCHOR_SET] != 0.0:
            depth = (
                (p0 - device_pos[i, 0]) * n0
                + (p1 - device_pos[i, 1]) * n1
                + (p2 - device_pos[i, 2]) * n2
            )
            if not depth <= 0.0:
                # The anchor in the world, less p, less its normal part: t, along the face.
                a0, a1, a2 = fingers[i, 0], fingers[i, 1], fingers[i, 2]
                o0 = r00 * a0 + r01 * a1 + r02 * a2 + x0 - p0
                o1 = r10 * a0 + r11 * a1 + r12 * a2 + x1 - p1
                o2 = r20 * a0 + r21 * a1 + r22 * a2 + x2 - p2
                s = o0 * n0 + o1 * n1 + o2 * n2
                t0, t1, t2 = o0 - s * n0, o1 - s * n1, o2 - s * n2
                tn = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
                # Within the static cone: stick at the anchor; else slip to the dynamic
                # cone's edge, toward the anchor.
                k = 1.0 if tn <= mu_s * depth else mu_d * depth / tn
                q0, q1, q2 = p0 + k * t0, p1 + k * t1, p2 + k * t2
        d0, d1, d2 = q0 - x0, q1 - x1, q2 - x2
        fingers[i, 0] = r00 * d0 + r10 * d1 + r20 * d2
        fingers[i, 1] = r01 * d0 + r11 * d1 + r21 * d2
        fingers[i, 2] = r02 * d0 + r12 * d1 + r22 * d2
        fingers[i, ANCHOR_SET] = 1.0
        surface_point[i, 0], surface_point[i, 1], surface_point[i, 2] = q0, q1, q2
        proxy_pos[i, 0] = plain_proxy[i, 0] + q0 - p0
        proxy_pos[i, 1] = plain_proxy[i, 1] + q1 - p1
        proxy_pos[i, 2] = plain_proxy[i, 2] + q2 - p2
        r = fingers[i, FINGER_RADIUS]
        contact_point[i, 0] = q0 - r * n0
        contact_point[i, 1] = q1 - r * n1
        contact_point[i, 2] = q2 - r * n2


# forces_step's params: stiffness k (N/m), damping b (N s/m), 1.0 if the object moves
# (free: the relative velocity takes its motion from ``state``) else 0.0
FORCES_PARAMS = 3


def forces_step(
    in_contact: np.ndarray,
    device_pos: np.ndarray,
    device_vel: np.ndarray,
    surface_point: np.ndarray,
    normals: np.ndarray,
    contact_force: np.ndarray,
    state: np.ndarray,
    params: np.ndarray,
) -> None:
    """The full contact force on each finger (the Forces stage's physics): k (surface point
    - device) - b v_rel, less any normal part that would pull the finger in; writes
    ``contact_force`` (F, 3) N, zero out of contact.

    ``in_contact`` (F,) u1, ``device_pos`` (F, 3) m, ``device_vel`` (F, 3) m/s,
    ``surface_point`` (F, 3) m and ``normals`` (F, 3) are the frame's. ``state``
    (STATE,): the object's x (m), v (m/s) and w (rad/s), read when it moves and b != 0.
    ``params`` (FORCES_PARAMS,) as declared above.
    """
    k, b = params[0], params[1]
    moving = params[2] != 0.0
    x0, x1, x2 = state[0], state[1], state[2]
    u0, u1, u2 = state[3], state[4], state[5]
    w0, w1, w2 = state[6], state[7], state[8]
    for i in range(in_contact.shape[0]):
        if in_contact[i] == 0:
            contact_force[i, 0], contact_force[i, 1], contact_force[i, 2] = 0.0, 0.0, 0.0
            continue
        p0, p1, p2 = surface_point[i, 0], surface_point[i, 1], surface_point[i, 2]
        f0 = k * (p0 - device_pos[i, 0])
        f1 = k * (p1 - device_pos[i, 1])
        f2 = k * (p2 - device_pos[i, 2])
        if b != 0.0:  # NaN damps too
            v0, v1, v2 = device_vel[i, 0], device_vel[i, 1], device_vel[i, 2]
            if moving:  # relative to the object's material at the surface point: u + w x e
                e0, e1, e2 = p0 - x0, p1 - x1, p2 - x2
                v0 = v0 - u0 - (w1 * e2 - w2 * e1)
                v1 = v1 - u1 - (w2 * e0 - w0 * e2)
                v2 = v2 - u2 - (w0 * e1 - w1 * e0)
            f0, f1, f2 = f0 - b * v0, f1 - b * v1, f2 - b * v2
            n0, n1, n2 = normals[i, 0], normals[i, 1], normals[i, 2]
            fn = f0 * n0 + f1 * n1 + f2 * n2
            if fn < 0.0:  # damping may slow the finger, never pull it in
                f0, f1, f2 = f0 - fn * n0, f1 - fn * n1, f2 - fn * n2
        contact_force[i, 0], contact_force[i, 1], contact_force[i, 2] = f0, f1, f2


# contact_step's plane columns: unit normal (3), offset (m, not inflated), obstacle (0: the
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
    n_fingers = device_pos.shape[0]
    n_planes = planes.shape[0]
    for kk in range(n_planes):
        for col in range(4):
            if not math.isfinite(planes[kk, col]):
                return CONTACT_NOT_TAKEN
    for i in range(n_fingers):
        for col in range(3):
            if not (math.isfinite(device_pos[i, col]) and math.isfinite(device_vel[i, col])):
                return CONTACT_NOT_TAKEN
        for col in range(_C_RADIUS + 1):  # the proxy and the radius
            if not math.isfinite(state[i, col]):
                return CONTACT_NOT_TAKEN
    n_obst = int(planes[n_planes - 1, 4]) + 1
    for i in range(n_fingers):
        r = state[i, _C_RADIUS]
        d0, d1, d2 = device_pos[i, 0], device_pos[i, 1], device_pos[i, 2]
        p0, p1, p2 = state[i, 0], state[i, 1], state[i, 2]
        # -- out of every obstacle the proxy is inside: through the nearest plane, or onto
        # the projection on the planes pushed through where they all push (a crease)
        s = (p0, p1, p2)
        npushed = 0
        for _ in range(n_obst + 1):
            moved = False
            lo = 0
            while lo < n_planes:
                hi = int(planes[lo, 6])
                best = -math.inf
                arg = lo
                for kk in range(lo, hi):
                    v = (planes[kk, 0] * p0 + planes[kk, 1] * p1 + planes[kk, 2] * p2) - (
                        planes[kk, 3] + r
                    )
                    if v >= 0.0:  # outside (or on) this plane: not inside the obstacle
                        best = v
                        break
                    if v > best:
                        best = v
                        arg = kk
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
        # -- toward the device, sliding on up to three planes
        nact = 0
        held = False
        for _ in range(_MAX_ITER):
            t0, t1, t2 = d0, d1, d2
            if nact == 1:  # _project's point, without its calls (quicker uncompiled)
                qq = int(state[i, _C_ACTIVE])
                state[i, _C_MU] = m = -_gap(planes, qq, r, d0, d1, d2)
                t0, t1, t2 = _along(planes, qq, m, d0, d1, d2)
            elif nact > 1:
                t0, t1, t2 = _project(planes, state, i, _C_ACTIVE, nact, r, (d0, d1, d2))
            e0, e1, e2 = t0 - p0, t1 - p1, t2 - p2
            # The first obstacle the path p + t e (t in [0, 1)) enters, and the plane: a
            # path whose two ends are outside or on one plane of an obstacle never enters
            # it; a crossing time is computed only on the segment (no ratio of two
            # rounding errors); inside every plane (a push-out could not clear another
            # obstacle): in at once, through the nearest.
            bt = 0.0
            bk = -1
            lo = 0
            while lo < n_planes:
                hi = int(planes[lo, 6])
                t_enter = 0.0
                t_exit = math.inf
                plane = -1
                never = False
                for kk in range(lo, hi):
                    nx, ny, nz = planes[kk, 0], planes[kk, 1], planes[kk, 2]
                    num = (planes[kk, 3] + r) - (nx * p0 + ny * p1 + nz * p2)
                    denom = nx * e0 + ny * e1 + nz * e2
                    if num <= _ON_PLANE:
                        if num - denom <= _ON_PLANE:
                            never = True
                            break
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
                if not (never or grazes) and (bk < 0 or t_enter < bt):
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
            w = 0
            for q in range(nact):
                qq = int(state[i, _C_ACTIVE + q])
                dist = -math.inf
                for kk in range(int(planes[qq, 5]), int(planes[qq, 6])):
                    v = (planes[kk, 0] * p0 + planes[kk, 1] * p1 + planes[kk, 2] * p2) - (
                        planes[kk, 3] + r
                    )
                    if v > dist:
                        dist = v
                        if v > _FREE_TOL:  # off this obstacle: the rest cannot change that
                            break
                m = state[i, _C_MU + q]
                if dist <= _FREE_TOL and m >= 0.0:
                    state[i, _C_ACTIVE + w] = qq
                    state[i, _C_MU + w] = m
                    w += 1
            if w == nact:
                held = True
                break
            nact = w
        # Held: the planes that push (mu > 0). Stopped short of a projection: those the
        # device is inside of (the others do not push), their multipliers from p - device.
        w = 0
        for q in range(nact):
            qq = int(state[i, _C_ACTIVE + q])
            if (state[i, _C_MU + q] > 0.0) if held else (_gap(planes, qq, r, d0, d1, d2) < 0.0):
                state[i, _C_ACTIVE + w] = qq
                state[i, _C_MU + w] = state[i, _C_MU + q]
                w += 1
        nact = w
        if not held and nact > 0:
            f0, f1, f2 = p0 - d0, p1 - d1, p2 - d2
            for q in range(nact):
                qq = int(state[i, _C_ACTIVE + q])
                state[i, _C_RHS + q] = f0 * planes[qq, 0] + f1 * planes[qq, 1] + f2 * planes[qq, 2]
            _gram_mu(planes, state, i, nact, _C_ACTIVE)
        # -- this finger's outputs: the proxy, its active planes (-1 past the last), the
        # surfaces' forces
        state[i, 0], state[i, 1], state[i, 2] = p0, p1, p2
        for q in range(nact, _MAX_CONSTRAINTS):
            state[i, _C_ACTIVE + q] = -1.0
        proxy_pos[i, 0], proxy_pos[i, 1], proxy_pos[i, 2] = p0, p1, p2
        v0, v1, v2 = device_vel[i, 0], device_vel[i, 1], device_vel[i, 2]
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
        if n_obst > 1:
            env_force[i, 0], env_force[i, 1], env_force[i, 2] = g0, g1, g2
        # In contact: the device moved out by the object's planes alone; else the proxy.
        x0, x1, x2 = p0, p1, p2
        n0, n1, n2 = 0.0, 0.0, 0.0
        if n_obj > 0:
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
        in_contact[i] = 1 if n_obj > 0 else 0
        surface_point[i, 0], surface_point[i, 1], surface_point[i, 2] = x0, x1, x2
        contact_normal[i, 0], contact_normal[i, 1], contact_normal[i, 2] = n0, n1, n2
        contact_point[i, 0] = x0 - r * n0
        contact_point[i, 1] = x1 - r * n1
        contact_point[i, 2] = x2 - r * n2
    return CONTACT_DONE


# -- the safety chain ---------------------------------------------------------------------

# The safety chain's array (hapticd.physics.safety.SafetyChain's, safety_step's ``params``):
# its parameters and the state it carries from tick to tick. The rate limit's largest
# change a tick (N; inf: off), the workspace's radius (m; inf: off) and centre (3, m), the
# enable ramp's length (s), when forces were enabled (s, nominal), when the ramp-down
# begins (s; inf: none) and its length (s), 1.0 while a fault is latched (forces zero, the
# deadman gates still follow their buttons), the ticks on which a force was clamped and on
# which one was rate limited, and the distance from the centre of the finger that left the
# workspace (m, written when one does); then SAFETY_COLUMNS blocks of F items, one item a
# finger: its force limit (N), its deadman button (-1: none), that deadman's ramp (s), when
# the button went down (s, nominal; inf: up) and the deadman's gate on the last tick (0 to
# 1; 1 without a deadman).
SAFETY_RATE, SAFETY_RADIUS, SAFETY_CENTRE = 0, 1, 2
SAFETY_RAMP_S, SAFETY_T_ENABLED, SAFETY_T_DOWN, SAFETY_DOWN_S = 5, 6, 7, 8
SAFETY_LATCHED, SAFETY_CLAMPED_TICKS, SAFETY_LIMITED_TICKS, SAFETY_DISTANCE = 9, 10, 11, 12
SAFETY_PARAMS = 13
SAFETY_LIMIT, SAFETY_BUTTON, SAFETY_BUTTON_RAMP, SAFETY_PRESSED, SAFETY_GATE = range(5)
SAFETY_COLUMNS = 5
# safety_step's outcome: bit flags of a tick made safe (a force clamped, a force rate
# limited), or of a trip, with the output zeroed (the chain latches the fault, with its
# message): a non-finite force, the bits from SAFETY_FINGERS on naming its fingers (bit
# SAFETY_FINGERS + i: finger i), or a finger beyond the workspace's radius, the bits from
# SAFETY_FINGERS on its index.
SAFETY_CLAMPED, SAFETY_LIMITED, SAFETY_NON_FINITE, SAFETY_WORKSPACE = 1, 2, 4, 8
SAFETY_FINGERS = 4


def _norm3(x0: float, x1: float, x2: float) -> float:
    """The length of (x0, x1, x2), scaled by its largest magnitude so that no square
    overflows or underflows (a force of 1e200 N keeps its direction when clamped); inf
    for an infinite argument, NaN for a NaN one (every comparison then fails)."""
    a0, a1, a2 = abs(x0), abs(x1), abs(x2)
    top = a1 if a1 > a0 else a0
    top = a2 if a2 > top else top
    if top == 0.0 or math.isinf(top):
        # A NaN beside zeros or an infinity: the comparisons above skipped it.
        return top if a0 == a0 and a1 == a1 and a2 == a2 else math.nan
    a0, a1, a2 = a0 / top, a1 / top, a2 / top
    return top * math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)


def ramp_down_factor(t: float, t_down: float, down_s: float) -> float:
    """The ramp-down's factor at nominal time ``t`` (s): 1 before ``t_down`` (s), then
    falling to exactly 0 after ``down_s`` (s): tick times carry rounding, and a remainder
    of 1e-15 must not leave a force of 1e-15 N. safety_step's, and the chain's
    ``ramped_down``."""
    if t < t_down:
        return 1.0
    left = 1.0 - (t - t_down) / down_s if down_s > 0.0 else 0.0
    return left if left > 1e-9 else 0.0


def safety_step(
    forces: np.ndarray,
    positions: np.ndarray,
    buttons: np.ndarray,
    params: np.ndarray,
    out_prev: np.ndarray,
    t: float,
) -> int:
    """The safety chain's tick for F fingers at nominal time ``t`` (s): the deadman gates;
    then, with no fault latched, the finite and workspace checks (a trip zeroes the
    output), the clamp (direction kept), the smallest of the ramps and the gate, the rate
    limit, the counters. Returns the SAFETY_ outcome.

    ``forces`` (F, 3) N, ``positions`` (F, 3) m, ``buttons`` the frame's button bytes
    (4 F: each finger's little-endian uint32), ``params`` the chain's array (SAFETY_*),
    ``out_prev`` (2, F, 3) N: this tick's output, then last tick's.
    """
    n = forces.shape[0]
    limits = SAFETY_PARAMS + SAFETY_LIMIT * n
    gates = SAFETY_PARAMS + SAFETY_GATE * n
    for i in range(n):
        button = params[SAFETY_PARAMS + SAFETY_BUTTON * n + i]
        if button < 0.0:
            continue
        # The gate follows its button also while a fault holds the forces at zero.
        bit = int(button)
        pressed = SAFETY_PARAMS + SAFETY_PRESSED * n + i
        if (int(buttons[4 * i + bit // 8]) >> (bit % 8)) & 1 == 0:
            params[pressed] = math.inf
            params[gates + i] = 0.0
            continue
        if params[pressed] == math.inf:
            params[pressed] = t
        held = t - params[pressed]
        ramp_s = params[SAFETY_PARAMS + SAFETY_BUTTON_RAMP * n + i]
        params[gates + i] = 1.0 if ramp_s <= 0.0 or held >= ramp_s else held / ramp_s
    outcome = 0
    if params[SAFETY_LATCHED] != 0.0:
        outcome = -1
    else:
        for i in range(n):
            f0, f1, f2 = forces[i, 0], forces[i, 1], forces[i, 2]
            if not (math.isfinite(f0) and math.isfinite(f1) and math.isfinite(f2)):
                outcome |= 1 << (SAFETY_FINGERS + i)
        if outcome != 0:
            outcome |= SAFETY_NON_FINITE
        elif math.isfinite(params[SAFETY_RADIUS]):
            c0, c1, c2 = params[SAFETY_CENTRE], params[SAFETY_CENTRE + 1], params[SAFETY_CENTRE + 2]
            for i in range(n):
                r = _norm3(positions[i, 0] - c0, positions[i, 1] - c1, positions[i, 2] - c2)
                if not r <= params[SAFETY_RADIUS]:
                    params[SAFETY_DISTANCE] = r
                    outcome = SAFETY_WORKSPACE | (i << SAFETY_FINGERS)
                    break
    if outcome != 0:  # a latched fault or a trip: zero force, and nothing to limit from
        for i in range(n):
            for j in range(3):
                out_prev[0, i, j] = 0.0
                out_prev[1, i, j] = 0.0
        return 0 if outcome < 0 else outcome
    ramp = 1.0
    ramp_s = params[SAFETY_RAMP_S]
    if ramp_s > 0.0:
        ramp = (t - params[SAFETY_T_ENABLED]) / ramp_s
        if not ramp > 0.0:
            ramp = 0.0
        elif not ramp < 1.0:
            ramp = 1.0
    down = ramp_down_factor(t, params[SAFETY_T_DOWN], params[SAFETY_DOWN_S])
    ramp = down if down < ramp else ramp
    step = params[SAFETY_RATE]
    rate_limited = step < math.inf
    flags = 0
    for i in range(n):
        f0, f1, f2 = forces[i, 0], forces[i, 1], forces[i, 2]
        mag = _norm3(f0, f1, f2)
        limit = params[limits + i]
        if mag > limit:
            s = limit / mag
            f0, f1, f2 = f0 * s, f1 * s, f2 * s
            flags |= SAFETY_CLAMPED
        g = params[gates + i]
        scale_i = ramp if ramp <= g else g
        if scale_i <= 0.0:
            # Exactly zero, never -0.0; the rate limit never delays a drop to zero.
            f0, f1, f2 = 0.0, 0.0, 0.0
        elif scale_i < 1.0:
            f0, f1, f2 = f0 * scale_i, f1 * scale_i, f2 * scale_i
        if rate_limited and (f0 != 0.0 or f1 != 0.0 or f2 != 0.0):
            p0, p1, p2 = out_prev[1, i, 0], out_prev[1, i, 1], out_prev[1, i, 2]
            d0, d1, d2 = f0 - p0, f1 - p1, f2 - p2
            change = _norm3(d0, d1, d2)
            if change > step:
                k = step / change
                f0, f1, f2 = p0 + k * d0, p1 + k * d1, p2 + k * d2
                flags |= SAFETY_LIMITED
        out_prev[0, i, 0], out_prev[0, i, 1], out_prev[0, i, 2] = f0, f1, f2
        out_prev[1, i, 0], out_prev[1, i, 1], out_prev[1, i, 2] = f0, f1, f2
    if flags & SAFETY_CLAMPED:
        params[SAFETY_CLAMPED_TICKS] += 1.0
    if flags & SAFETY_LIMITED:
        params[SAFETY_LIMITED_TICKS] += 1.0
    return flags


# -- the object's planes in the world ------------------------------------------------------


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


# tick_step's params: what the plan has (1.0 or 0.0: friction, a free object, surfaces, a
# sum of contributions into rendered_force, passivity), whether the safety chain's
# tick runs in the call (set per tick), the stages this call runs (STAGE_ indices, from
# first to before last), then the passivity, friction, forces, allocation and free-body
# params at their offsets (each one's layout above; passivity's: velocity threshold m/s,
# most damping N s/m, the tick's period s)
TICK_FRICTION, TICK_FREE, TICK_SURFACES, TICK_SUM, TICK_SAFETY = range(5)
TICK_FIRST, TICK_LAST, TICK_PASSIVITY = 5, 6, 7
TICK_PASSIVITY_AT = 8
PASSIVITY_PARAMS = 3
TICK_FRICTION_AT = TICK_PASSIVITY_AT + PASSIVITY_PARAMS
TICK_FORCES_AT = TICK_FRICTION_AT + FRICTION_PARAMS
TICK_ALLOCATION_AT = TICK_FORCES_AT + FORCES_PARAMS
TICK_BODY_AT = TICK_ALLOCATION_AT + ALLOCATION_PARAMS
TICK_PARAMS = TICK_BODY_AT + PARAMS
# The stages of a tick, in order, as tick_step runs them (hapticd.physics.stages names each
# stage's), then the safety chain's tick (when the call makes it).
STAGE_CONTACT, STAGE_FRICTION, STAGE_FORCES, STAGE_ALLOCATION, STAGE_ENVIRONMENT = range(5)
STAGE_PASSIVITY, STAGE_SUM, STAGE_DYNAMICS, STAGE_SCENE, STAGE_SAFETY, STAGE_END = range(5, 11)
# The passivity stage's carried state per finger: its observed energy (J), its position on
# the last tick (3, m) and 1.0 once it has one (the first tick sees no motion).
PASSIVITY_STATE = 5
# tick_step's outcomes: done; stopped at contact, a non-finite input (nothing of it
# written: the contact stage names it); allocation refused a non-finite input or produced
# a non-finite output (nothing after it written); with the safety chain's tick: a free
# object's state beyond MAX_OBJECT_* (the chain not run: the loop latches the fault);
# TICK_SAFE + safety_step's outcome: done, the safety chain's tick too (a trip zeroed
# device_force; the chain latches it). From TICK_FINISHED on, every stage of the plan
# has run.
TICK_FROM_CONTACT, TICK_NON_FINITE_INPUT, TICK_NON_FINITE_OUTPUT = 1, 3, 4
# The devices' samples the call was to check (the loop's block says they wait) hold one no
# hand makes (non-finite, too fast or too far): nothing written, the device bank checks
# them itself, with its messages.
TICK_SAMPLES = 2
TICK_FINISHED = TICK_DONE = 5
TICK_OBJECT = 6
TICK_SAFE = 16
# A free object beyond these has left any scene a hand can reach (a free fall of a day
# stays below them), and well before float overflow breaks its dynamics: the loop's
# backstop (hapticd.loop.servo) latches a fault.
MAX_OBJECT_DISTANCE_M = 1e12
MAX_OBJECT_SPEED_M_PER_S = 1e7
MAX_OBJECT_SPIN_RAD_PER_S = 1e7


# tick_step's frame fields: each one's offset in the frame's record, in float64 items
# (``at``), in this order (under each line of names, their indices in it). With friction
# contact writes the frictionless ones and friction the final three; without, the
# frictionless ones are the final ones (the same offsets). residual_internal is followed by
# residual_external, residual_total, amplification and alpha; object_pos by object_vel,
# object_omega and object_rot (STATE floats).
TICK_FIELDS = ("device_pos", "device_vel", "frictionless_proxy", "frictionless_point")
_AT_POS, _AT_VEL, _AT_PLAIN_PROXY, _AT_PLAIN_SURFACE = range(4)
TICK_FIELDS += ("frictionless_contact_point", "contact_normal", "env_force", "proxy_pos")
_AT_PLAIN_POINT, _AT_NORMAL, _AT_ENV, _AT_PROXY = range(4, 8)
TICK_FIELDS += ("surface_point", "contact_point", "contact_force", "lam_a", "allocated_force")
_AT_SURFACE, _AT_POINT, _AT_FORCE, _AT_LAM, _AT_ALLOCATED = range(8, 13)
TICK_FIELDS += ("residual_internal", "env_rendered", "passivity_force", "passivity_energy")
_AT_SCALARS, _AT_ENV_RENDERED, _AT_DAMPING_FORCE, _AT_ENERGY = range(13, 17)
TICK_FIELDS += ("passivity_damping", "rendered_force", "object_pos")
_AT_DAMPING, _AT_RENDERED, _AT_OBJECT = range(17, 20)
TICK_FIELDS += ("device_force", "device_sample", "t")
_AT_DEVICE_FORCE, _AT_SAMPLE, _AT_T = range(20, len(TICK_FIELDS))


def _rows(a: np.ndarray, start: int, n: int) -> np.ndarray:
    """Items ``start`` to ``start + 3 n`` of the flat ``a`` as an (n, 3) view (``_block``)."""
    return _block(a, start, n, 3)


def _block(a: np.ndarray, start: int, n: int, cols: int) -> np.ndarray:
    """Items ``start`` to ``start + n cols`` of the flat ``a`` as an (n, cols) view (a
    memoryview's, uncompiled; ``_block_compiled`` in compiled code)."""
    if n == 0:
        return np.zeros((0, cols))  # a memoryview has no empty shape
    return a[start : start + n * cols].cast("B").cast("d", (n, cols))  # type: ignore[attr-defined]


def _block_compiled(a: np.ndarray, start: int, n: int, cols: int) -> np.ndarray:
    # as_strided, not reshape: numba's reshape searches for strides at run time (about 40
    # ns a view, a third of a tick's unpacking); the range is checked here instead.
    if start < 0 or n < 0 or start + n * cols > a.shape[0]:
        raise IndexError("a block beyond its array")
    return as_strided(a[start:], shape=(n, cols), strides=(8 * cols, 8))


def _bytes(a: np.ndarray) -> np.ndarray:
    """The flat float64 ``a``'s memory as bytes (a memoryview's, uncompiled;
    ``_bytes_compiled`` in compiled code): the frame's one-byte fields."""
    return a.cast("B")  # type: ignore[attr-defined]


def _bytes_compiled(a: np.ndarray) -> np.ndarray:
    return a.view(np.uint8)


# Helpers whose compiled form is another function (hapticd.physics.jit compiles that one in).
COMPILED_FORMS = {_block: _block_compiled, _bytes: _bytes_compiled}


# tick_step's state: everything a tick carries to the next (hapticd.physics.frame.STATE) in one
# float64 array, the renderer's; each stage holds views of its block: contact's (F,
# CONTACT_STATE), friction's anchors (F, FRICTION_COLUMNS), passivity's (F,
# PASSIVITY_STATE), the allocator's alpha (ALLOCATION_STATE,) and workspace
# (allocation_work_shape(F)), and the loop's (LOOP_HEAD + 8 F,; below). The object's own
# state is the scene's (SceneObject.state), and the safety chain's its own.
TICK_STATE = ("contact", "anchors", "passive", "alloc", "work", "loop")
# The loop's block: 1.0 while the devices' samples wait in the frame's device_sample for
# the call's check (the device bank's deferred read; the call clears it), the fastest
# plausible device speed (m/s) and farthest position (m), 1.0 while the loop watches the
# ticks, then (written by the call when it does) 1.0 when in_contact or buttons differ
# from the last tick's; then each finger's largest device force (F, N), its value before
# this tick (F, N), and the last tick's in_contact (F) and buttons (4 F, their bytes).
LOOP_SAMPLES, LOOP_MAX_SPEED, LOOP_MAX_DISTANCE, LOOP_WATCH, LOOP_CHANGED = range(5)
LOOP_HEAD = 5


def state_layout(n_fingers: int, n_directions: int) -> dict[str, tuple[int, tuple[int, ...]]]:
    """Each TICK_STATE block's (offset in float64 items, shape) for F fingers with D actuated
    directions in all."""
    shapes = {
        "contact": (n_fingers, CONTACT_STATE),
        "anchors": (n_fingers, FRICTION_COLUMNS),
        "passive": (n_fingers, PASSIVITY_STATE),
        "alloc": (ALLOCATION_STATE,),
        "work": allocation_work_shape(n_fingers, n_directions),
        "loop": (LOOP_HEAD + 8 * n_fingers,),
    }
    out, at = {}, 0
    for name in TICK_STATE:
        out[name] = (at, shapes[name])
        at += math.prod(shapes[name])
    return out


def plausible(
    p0: float, p1: float, p2: float, v0: float, v1: float, v2: float, speed: float, far: float
) -> bool:
    """Whether a device's sample, position (p0, p1, p2) m and velocity (v0, v1, v2) m/s, is
    one a hand makes: no faster than ``speed`` m/s, no farther than ``far`` m from the
    device's origin, finite (NaN fails every comparison). The one check of a sample: the
    tick's one call runs it compiled, the device bank (hapticd.loop.device_bank) on floats."""
    return _norm3(v0, v1, v2) <= speed and _norm3(p0, p1, p2) <= far


# tick_step's plan: one float64 array: where things are (TICK_AT items: each TICK_FIELDS
# field's offset in the frame's record, then each TICK_PLAN block's below, then each
# TICK_STATE block's in the state and the workspace's rows and columns, then in_contact's
# and buttons' offsets in the record's bytes, and the number of fingers), the params
# (TICK_PARAMS), then these blocks (with their rows where they vary): contact's planes (P,
# PLANE_COLUMNS), the free body's body (K, 3) and surfaces
# (S, SURFACE_COLUMNS), the shape's normals (M, 3) and offsets (M,), the free body's
# scratch (F, SCRATCH_COLUMNS), every finger's actuated directions in the actuation's frame
# (D, 3), finger by finger, and how many each finger has (F,)
TICK_PLAN = ("planes", "rows", "body", "rows", "surf", "rows", "normals", "rows")
TICK_PLAN += ("offsets", "scratch", "directions", "rows", "counts")
_AT_PLAN = len(TICK_FIELDS)
_AT_STATE = _AT_PLAN + len(TICK_PLAN)
_AT_IN_CONTACT = _AT_STATE + len(TICK_STATE) + 2
_AT_BUTTONS = _AT_IN_CONTACT + 1
_AT_FINGERS = _AT_BUTTONS + 1
TICK_AT = _AT_FINGERS + 1


def tick_step(
    record: np.ndarray,
    state: np.ndarray,
    plan: np.ndarray,
    obj_state: np.ndarray,
    safety_params: np.ndarray,
    out_prev: np.ndarray,
) -> int:
    """The renderer's plan as one call, stage by stage (STAGE_ indices params[TICK_FIRST]
    to before params[TICK_LAST]): the waiting device samples checked, the object's planes,
    contact, friction, forces, allocation, environment, passivity, their sum, the free
    object's step, the scene's state; with params[TICK_SAFETY], the object checked and the
    safety chain's tick into ``device_force``. Returns a TICK_ outcome.

    ``record``: the frame's record as float64 items (``plan`` says where each field is);
    ``state``: the carried state (TICK_STATE); ``plan``: offsets, params and the
    ``TICK_PLAN`` blocks; ``obj_state`` (STATE,); ``safety_params`` and ``out_prev``: the
    chain's arrays (safety_step).
    """
    n = int(plan[_AT_FINGERS])
    s = _AT_STATE
    contact_state = _block(state, int(plan[s]), n, CONTACT_STATE)
    anchors = _block(state, int(plan[s + 1]), n, FRICTION_COLUMNS)
    passive = _block(state, int(plan[s + 2]), n, PASSIVITY_STATE)
    alloc_state = state[int(plan[s + 3]) : int(plan[s + 3]) + ALLOCATION_STATE]
    alloc_work = _block(state, int(plan[s + 4]), int(plan[s + 6]), int(plan[s + 7]))
    lp = int(plan[s + 5])
    at_pos, at_vel = int(plan[_AT_POS]), int(plan[_AT_VEL])
    if state[lp + LOOP_SAMPLES] != 0.0:
        # The device bank's check of the samples it read (hapticd.loop.device_bank), compiled:
        # a sample no hand makes refuses the tick before anything is written.
        state[lp + LOOP_SAMPLES] = 0.0
        sp = int(plan[_AT_SAMPLE])
        sv = sp + 3 * n
        speed, far = state[lp + LOOP_MAX_SPEED], state[lp + LOOP_MAX_DISTANCE]
        for i in range(n):
            p, v = sp + 3 * i, sv + 3 * i
            if not plausible(
                record[p], record[p + 1], record[p + 2], record[v], record[v + 1], record[v + 2],
                speed, far,
            ):  # fmt: skip
                return TICK_SAMPLES
        for j in range(3 * n):
            record[at_pos + j] = record[sp + j]
            record[at_vel + j] = record[sv + j]
    ic, bt = int(plan[_AT_IN_CONTACT]), int(plan[_AT_BUTTONS])
    in_contact = _bytes(record)[ic : ic + n]
    k = _AT_PLAN
    params = plan[TICK_AT : TICK_AT + TICK_PARAMS]
    first, last = params[TICK_FIRST], params[TICK_LAST]
    planes = _block(plan, int(plan[k]), int(plan[k + 1]), PLANE_COLUMNS)
    body = _rows(plan, int(plan[k + 2]), int(plan[k + 3]))
    surf = _block(plan, int(plan[k + 4]), int(plan[k + 5]), SURFACE_COLUMNS)
    body_normals = _rows(plan, int(plan[k + 6]), int(plan[k + 7]))
    body_offsets = plan[int(plan[k + 8]) : int(plan[k + 8]) + int(plan[k + 7])]
    scratch = _block(plan, int(plan[k + 9]), n, SCRATCH_COLUMNS)
    n_dirs = int(plan[k + 11])
    directions = _rows(plan, int(plan[k + 10]), n_dirs)
    counts = plan[int(plan[k + 12]) : int(plan[k + 12]) + n]
    device_pos = _rows(record, int(plan[_AT_POS]), n)
    device_vel = _rows(record, int(plan[_AT_VEL]), n)
    plain_proxy = _rows(record, int(plan[_AT_PLAIN_PROXY]), n)
    plain_surface = _rows(record, int(plan[_AT_PLAIN_SURFACE]), n)
    plain_point = _rows(record, int(plan[_AT_PLAIN_POINT]), n)
    normal = _rows(record, int(plan[_AT_NORMAL]), n)
    env_force = _rows(record, int(plan[_AT_ENV]), n)
    surface_point = _rows(record, int(plan[_AT_SURFACE]), n)
    contact_point = _rows(record, int(plan[_AT_POINT]), n)
    contact_force = _rows(record, int(plan[_AT_FORCE]), n)
    allocated = _rows(record, int(plan[_AT_ALLOCATED]), n)
    env_rendered = _rows(record, int(plan[_AT_ENV_RENDERED]), n)
    damping_force = _rows(record, int(plan[_AT_DAMPING_FORCE]), n)
    rendered = _rows(record, int(plan[_AT_RENDERED]), n)
    if first <= STAGE_CONTACT < last:
        world_planes(_rows(obj_state, 9, 3), obj_state[0:3], body_normals, body_offsets, planes)
        found = contact_step(
            device_pos,
            device_vel,
            planes,
            contact_state,
            plain_proxy,
            in_contact,
            plain_surface,
            plain_point,
            normal,
            env_force,
        )
        if found != CONTACT_DONE:
            return TICK_FROM_CONTACT
    if params[TICK_FRICTION] != 0.0 and first <= STAGE_FRICTION < last:
        friction_step(
            in_contact,
            device_pos,
            plain_surface,
            plain_proxy,
            plain_point,
            surface_point,
            normal,
            _rows(record, int(plan[_AT_PROXY]), n),
            contact_point,
            anchors,
            obj_state,
            params[TICK_FRICTION_AT:TICK_FORCES_AT],
        )
    if first <= STAGE_FORCES < last:
        forces_step(
            in_contact,
            device_pos,
            device_vel,
            surface_point,
            normal,
            contact_force,
            obj_state,
            params[TICK_FORCES_AT:TICK_ALLOCATION_AT],
        )
    a = TICK_ALLOCATION_AT
    if first <= STAGE_ALLOCATION < last:
        params[a + 5], params[a + 6], params[a + 7] = obj_state[0], obj_state[1], obj_state[2]
        scalars = record[int(plan[_AT_SCALARS]) : int(plan[_AT_SCALARS]) + ACCURACY + 1]
        outcome = allocation_step(
            in_contact,
            device_pos,
            contact_point,
            contact_force,
            directions,
            counts,
            params[a:TICK_BODY_AT],
            alloc_state,
            record[int(plan[_AT_LAM]) : int(plan[_AT_LAM]) + n_dirs],
            allocated,
            scalars,
            alloc_work,
        )
        if outcome == NON_FINITE_INPUT:
            return TICK_NON_FINITE_INPUT
        if outcome == NON_FINITE_OUTPUT:
            return TICK_NON_FINITE_OUTPUT
        scalars[ACCURACY] = alloc_state[0]
    surfaces, passivity = params[TICK_SURFACES] != 0.0, params[TICK_PASSIVITY] != 0.0
    # The actuation frame's axes in the world (the grasp's moves with the fingers).
    ax = _axes(device_pos, params[a + 4] != 0.0 and (surfaces or passivity))
    if surfaces and first <= STAGE_ENVIRONMENT < last:
        # The environment's force projected onto the span of each finger's own directions.
        start = 0
        for i in range(n):
            c = int(counts[i])
            e0, e1, e2 = env_force[i, 0], env_force[i, 1], env_force[i, 2]
            p0 = p1 = p2 = 0.0
            if e0 != 0.0 or e1 != 0.0 or e2 != 0.0:
                p0, p1, p2 = _span_project(directions, start, c, ax, e0, e1, e2)
            env_rendered[i, 0], env_rendered[i, 1], env_rendered[i, 2] = p0, p1, p2
            start += c
    if passivity and first <= STAGE_PASSIVITY < last:
        _passivity(
            device_pos,
            allocated,
            env_rendered,
            surfaces,
            directions,
            counts,
            ax,
            params[TICK_PASSIVITY_AT:TICK_FRICTION_AT],
            passive,
            damping_force,
            record[int(plan[_AT_ENERGY]) : int(plan[_AT_ENERGY]) + n],
            record[int(plan[_AT_DAMPING]) : int(plan[_AT_DAMPING]) + n],
        )
    if params[TICK_SUM] != 0.0 and first <= STAGE_SUM < last:
        # The contributions in the plan's order: allocated, environment's, passivity's.
        for i in range(n):
            for j in range(3):
                f = allocated[i, j]
                if surfaces:
                    f = f + env_rendered[i, j]
                if passivity:
                    f = f + damping_force[i, j]
                rendered[i, j] = f
    if params[TICK_FREE] != 0.0 and first <= STAGE_DYNAMICS < last:
        free_body_step(
            in_contact,
            contact_point,
            contact_force,
            normal,
            params[TICK_BODY_AT:TICK_PARAMS],
            obj_state,
            body,
            surf,
            scratch,
        )
    if first <= STAGE_SCENE < last:
        o = int(plan[_AT_OBJECT])
        for k in range(STATE):
            record[o + k] = obj_state[k]
    watch = state[lp + LOOP_WATCH] != 0.0
    if watch and first <= STAGE_SAFETY < last:
        # The loop's events watcher (hapticd.loop.event_ring.FrameEvents) runs when in_contact
        # or buttons changed since the last tick: whether they did, kept for the next.
        raw = _bytes(record)
        was = lp + LOOP_HEAD + 2 * n
        changed = 0.0
        for j in range(5 * n):  # in_contact's n bytes, then the buttons' 4 n
            b = raw[ic + j] if j < n else raw[bt + j - n]
            if state[was + j] != b:
                state[was + j] = b
                changed = 1.0
        state[lp + LOOP_CHANGED] = changed
    if params[TICK_SAFETY] == 0.0 or not first <= STAGE_SAFETY < last:
        return TICK_DONE
    # NaN fails every comparison (the loop's backstop, math.hypot, agrees to rounding).
    if params[TICK_FREE] != 0.0 and not (
        _norm3(obj_state[0], obj_state[1], obj_state[2]) <= MAX_OBJECT_DISTANCE_M
        and _norm3(obj_state[3], obj_state[4], obj_state[5]) <= MAX_OBJECT_SPEED_M_PER_S
        and _norm3(obj_state[6], obj_state[7], obj_state[8]) <= MAX_OBJECT_SPIN_RAD_PER_S
    ):
        return TICK_OBJECT
    t = record[int(plan[_AT_T])]
    outcome = safety_step(
        rendered, device_pos, _bytes(record)[bt : bt + 4 * n], safety_params, out_prev, t
    )
    out = _rows(record, int(plan[_AT_DEVICE_FORCE]), n)
    for i in range(n):
        f0, f1, f2 = out_prev[0, i, 0], out_prev[0, i, 1], out_prev[0, i, 2]
        out[i, 0], out[i, 1], out[i, 2] = f0, f1, f2
        if watch:  # the loop's statistics: each finger's largest force, and the last one
            top = lp + LOOP_HEAD + i
            was = state[top]
            state[top + n] = was
            mag = _norm3(f0, f1, f2)
            if mag > was:
                state[top] = mag
    return TICK_SAFE + outcome


def _passivity(
    device_pos: np.ndarray,
    allocated: np.ndarray,
    env_rendered: np.ndarray,
    surfaces: bool,
    directions: np.ndarray,
    counts: np.ndarray,
    ax: tuple[float, ...],
    params: np.ndarray,
    passive: np.ndarray,
    damping_force: np.ndarray,
    energy: np.ndarray,
    damping: np.ndarray,
) -> None:
    """The passivity stage (hapticd.physics.passivity's observer and controller) on every finger:
    observes the energy of the force before it (the allocated force, plus the environment's
    with ``surfaces``) over the finger's motion since the last tick, and writes the damping
    force along the finger's actuated directions, the energy and the damping (N s/m).
    ``passive`` (F, PASSIVITY_STATE) is its carried state; ``params`` PASSIVITY_PARAMS."""
    threshold, most, dt = params[0], params[1], params[2]
    start = 0
    for i in range(damping_force.shape[0]):
        c = int(counts[i])
        x0, x1, x2 = device_pos[i, 0], device_pos[i, 1], device_pos[i, 2]
        d0 = d1 = d2 = 0.0
        if passive[i, 4] != 0.0:  # the first tick sees no motion
            d0, d1, d2 = x0 - passive[i, 1], x1 - passive[i, 2], x2 - passive[i, 3]
        passive[i, 1], passive[i, 2], passive[i, 3], passive[i, 4] = x0, x1, x2, 1.0
        f0, f1, f2 = allocated[i, 0], allocated[i, 1], allocated[i, 2]
        if surfaces:
            f0, f1, f2 = f0 + env_rendered[i, 0], f1 + env_rendered[i, 1], f2 + env_rendered[i, 2]
        e = observe(passive[i, 0], (f0, f1, f2), (d0, d1, d2))
        alpha = 0.0
        damping_force[i, 0], damping_force[i, 1], damping_force[i, 2] = 0.0, 0.0, 0.0
        if e < 0.0:  # only then the controller needs the actuated motion
            u = _span_project(directions, start, c, ax, d0, d1, d2)
            e, alpha = control(e, u, dt, threshold, most)
            if alpha > 0.0:
                g = alpha / dt  # the damping force is -alpha P_a v, v = dx / T
                damping_force[i, 0], damping_force[i, 1] = -(g * u[0]), -(g * u[1])
                damping_force[i, 2] = -(g * u[2])
        elif not e >= 0.0:  # NaN: a non-finite position or force; keep the last energy
            e = passive[i, 0]
        passive[i, 0] = energy[i] = e
        damping[i] = alpha
        start += c


def _span_project(
    directions: np.ndarray,
    start: int,
    count: int,
    ax: tuple[float, ...],
    v0: float,
    v1: float,
    v2: float,
) -> tuple[float, float, float]:
    """(v0, v1, v2) projected onto the span of a finger's ``count`` actuated directions
    (rows ``start`` on of ``directions``, in the actuation's frame, whose axes in the world
    are ``ax``: _axes'), by Gram-Schmidt in order: a direction whose part orthogonal to the
    ones before is shorter than DEPENDENT of it adds nothing; three independent ones span
    everything (v itself)."""
    k = 0
    b0 = b1 = b2 = c0 = c1 = c2 = 0.0  # the first two unit vectors of the basis
    p0 = p1 = p2 = 0.0
    for j in range(start, start + count):
        l0, l1, l2 = directions[j, 0], directions[j, 1], directions[j, 2]
        x = ax[0] * l0 + ax[3] * l1 + ax[6] * l2
        y = ax[1] * l0 + ax[4] * l1 + ax[7] * l2
        z = ax[2] * l0 + ax[5] * l1 + ax[8] * l2
        n0 = math.sqrt(x * x + y * y + z * z)
        if not n0 > 0.0:  # also false for NaN
            continue
        if k > 0:
            d = x * b0 + y * b1 + z * b2
            x, y, z = x - d * b0, y - d * b1, z - d * b2
        if k > 1:
            d = x * c0 + y * c1 + z * c2
            x, y, z = x - d * c0, y - d * c1, z - d * c2
        m = math.sqrt(x * x + y * y + z * z)
        if not m > DEPENDENT * n0:
            continue
        if k == 2:
            return v0, v1, v2
        x, y, z = x / m, y / m, z / m
        d = v0 * x + v1 * y + v2 * z
        p0, p1, p2 = p0 + d * x, p1 + d * y, p2 + d * z
        if k == 0:
            b0, b1, b2 = x, y, z
        else:
            c0, c1, c2 = x, y, z
        k += 1
    return p0, p1, p2
