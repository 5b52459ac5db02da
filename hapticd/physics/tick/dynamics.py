"""The Dynamics stage: a free object's motion over a tick under the fingers' reactions,
gravity and surfaces. Its declaration, its arrays' layout (PARAMS, STATE, BODY_HEAD,
SURFACE_COLUMNS, SCRATCH_COLUMNS), its kernel (``free_body_step``) and the loop's backstop
on a diverged object (``object_bounded``).

Units: positions m, velocities m/s, angular velocities rad/s, forces N, torques N m,
stiffness N/m, damping N s/m, mass kg, inertia kg m^2, times s.
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.physics.tick.layout import Declaration
from hapticd.physics.tick.safety import _norm3

SCRATCH_COLUMNS = 13  # per finger: c0 (3), body (3), f0 (3), torsion normal (3), cap (1)
# free_body_step's params: k (N/m), mu_t (m), m (kg), dt (s), substeps, reach (m), gravity
# (3, m/s^2)
PARAM_NAMES = ("stiffness", "torsion", "mass", "dt", "substeps", "reach", "gx", "gy", "gz")
PARAMS = len(PARAM_NAMES)
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


# A free object beyond these has left any scene a hand can reach (a free fall of a day
# stays below them), and well before float overflow breaks its dynamics: the loop's
# backstop (hapticd.loop.servo) latches a fault.
MAX_OBJECT_DISTANCE_M = 1e12
MAX_OBJECT_SPEED_M_PER_S = 1e7
MAX_OBJECT_SPIN_RAD_PER_S = 1e7


def object_bounded(obj_state: np.ndarray) -> bool:
    """Whether the object's state (STATE,) is within MAX_OBJECT_*; NaN fails every
    comparison (the loop's backstop, math.hypot, agrees to rounding)."""
    return (
        _norm3(obj_state[0], obj_state[1], obj_state[2]) <= MAX_OBJECT_DISTANCE_M
        and _norm3(obj_state[3], obj_state[4], obj_state[5]) <= MAX_OBJECT_SPEED_M_PER_S
        and _norm3(obj_state[6], obj_state[7], obj_state[8]) <= MAX_OBJECT_SPIN_RAD_PER_S
    )


DECLARATION = Declaration(
    "dynamics",
    reads=("in_contact", "contact_point", "contact_force", "contact_normal"),
    blocks=(("body", True), ("surf", True), ("scratch", False)),
    params=PARAM_NAMES,
    flag="free",
    helpers=("free_body_step", "object_bounded"),
)
