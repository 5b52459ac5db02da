"""The Forces stage: the full contact force on each finger in contact, a spring to the
surface point with damping that never pulls the finger in. Its declaration, its
parameters' packing (``pack``) and its kernel (``forces_step``).

Units: positions m, velocities m/s, stiffness N/m, damping N s/m, forces N.
"""

from __future__ import annotations

import numpy as np

from hapticd.physics.tick.layout import Declaration

# forces_step's params: stiffness k (N/m), damping b (N s/m), 1.0 if the object moves
# (free: the relative velocity takes its motion from ``state``) else 0.0
PARAMS = ("stiffness", "damping", "moving")
FORCES_PARAMS = len(PARAMS)


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


def pack(stiffness: float, damping: float, moving: bool) -> tuple[float, ...]:
    """forces_step's params (FORCES_PARAMS,): the material's stiffness (N/m) and damping
    (N s/m), and whether the object moves."""
    return (stiffness, damping, float(moving))


DECLARATION = Declaration(
    "forces",
    reads=("in_contact", "device_pos", "device_vel", "surface_point", "contact_normal"),
    writes=("contact_force",),
    fields=("surface_point", "contact_force"),
    params=PARAMS,
    helpers=("forces_step",),
)
