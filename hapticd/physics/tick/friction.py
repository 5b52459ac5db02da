"""The Friction stage: Coulomb stick/slip at each fingertip in contact (after CHAI3D's
finger proxy). Its declaration, its parameters' packing (``pack``) and its kernel
(``friction_step``).

Units: positions m; the coefficients are dimensionless.
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.physics.tick.layout import Declaration

# The Friction stage's per-finger array (F, FRICTION_COLUMNS), its carried state that
# friction_step reads and writes: the anchor in the object's body frame (3, m), whether it
# is set (1.0) or not (0.0), the fingertip's radius (m).
FRICTION_COLUMNS = 5
ANCHOR_SET = 3
FINGER_RADIUS = 4


# friction_step's params: static and dynamic friction coefficients
PARAMS = ("mu_static", "mu_dynamic")
FRICTION_PARAMS = len(PARAMS)


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


def pack(mu_static: float, mu_dynamic: float) -> tuple[float, ...]:
    """friction_step's params (FRICTION_PARAMS,) from the material's coefficients."""
    return (mu_static, mu_dynamic)


# What contact writes when friction then moves it (hapticd.physics.stages.FRICTIONLESS), and
# the final fields friction writes (HELD).
FRICTIONLESS = ("frictionless_proxy", "frictionless_point", "frictionless_contact_point")
HELD = ("proxy_pos", "surface_point", "contact_point")

DECLARATION = Declaration(
    "friction",
    reads=("in_contact", "device_pos", "contact_normal", *FRICTIONLESS),
    writes=HELD,
    fields=HELD,
    state=(("anchors", lambda n, d: (n, FRICTION_COLUMNS)),),
    params=PARAMS,
    flag="friction",
    helpers=("friction_step",),
)
