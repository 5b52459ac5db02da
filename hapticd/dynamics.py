"""Rigid-body dynamics of a free object: contact reactions, gravity, ground and walls.

``step_body`` advances a SceneObject by dt (s) in ``substeps`` semi-implicit
Euler steps. The fingers' contact forces are held over the tick (they are
computed once per servo tick); gravity (m/s^2) and surface contact act only
when given, so a scene without them never computes them. Surface contact is a
penalty spring-damper at the object's vertices with Coulomb friction whose
tangential impulse never exceeds what stops the sliding vertex in one step.
"""

from __future__ import annotations

import numpy as np

from hapticd.scene import SceneObject, Surface


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotate(R: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """R advanced by the world-frame angular velocity ``omega`` (rad/s) over dt (Rodrigues)."""
    angle = float(np.linalg.norm(omega)) * dt
    if angle < 1e-12:
        return R
    K = skew(omega / np.linalg.norm(omega))
    Rn = (np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)) @ R
    # One Bjorck step keeps R orthonormal against rounding drift.
    return 1.5 * Rn - 0.5 * Rn @ Rn.T @ Rn


def surface_wrench(
    obj: SceneObject, surfaces: list[Surface], dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Force (3,) N and torque about the centre of mass (3,) N m from surface contact."""
    verts = obj.vertices_world()
    rel = verts - obj.position
    vel = obj.velocity + np.cross(obj.omega, rel)
    force = np.zeros(3)
    torque = np.zeros(3)
    for s in surfaces:
        n = np.array(s.normal)
        pen = s.offset - verts @ n + 0.0  # > 0: the vertex is inside the solid
        hit = pen > 0.0
        if not np.any(hit):
            continue
        m = s.material
        vn = vel[hit] @ n
        fn = np.maximum(m.stiffness * pen[hit] - m.damping * vn, 0.0)
        f = np.outer(fn, n)
        if m.mu_dynamic > 0.0:
            vt = vel[hit] - np.outer(vn, n)
            speed = np.linalg.norm(vt, axis=1)
            moving = speed > 1e-12
            share = obj.mass / max(int(np.count_nonzero(hit)), 1)
            cap = np.minimum(m.mu_dynamic * fn, share * speed / dt)
            ft = np.zeros_like(vt)
            ft[moving] = -vt[moving] * (cap[moving] / speed[moving])[:, None]
            f = f + ft
        force += f.sum(axis=0)
        torque += np.cross(rel[hit], f).sum(axis=0)
    return force, torque


def step_body(
    obj: SceneObject,
    force: np.ndarray,
    torque: np.ndarray,
    dt: float,
    *,
    gravity: np.ndarray | None = None,
    surfaces: list[Surface] | None = None,
    substeps: int = 1,
) -> None:
    """Advance a free object by dt under ``force`` (N) and ``torque`` (N m, about the COM)."""
    h = dt / substeps
    inv_mass = 1.0 / obj.mass
    I_body = obj.inertia_body
    for _ in range(substeps):
        F = force.copy()
        T = torque.copy()
        if gravity is not None:
            F += obj.mass * gravity
        if surfaces:
            fs, ts = surface_wrench(obj, surfaces, h)
            F += fs
            T += ts
        R = obj.rotation
        I_world = R @ I_body @ R.T
        w = obj.omega
        obj.velocity = obj.velocity + h * inv_mass * F
        obj.omega = w + h * np.linalg.solve(I_world, T - np.cross(w, I_world @ w))
        obj.position = obj.position + h * obj.velocity
        obj.rotation = rotate(R, obj.omega, h)
    obj.update_world()


def kinetic_energy(obj: SceneObject) -> float:
    """Translational plus rotational kinetic energy, J."""
    I_world = obj.rotation @ obj.inertia_body @ obj.rotation.T
    return 0.5 * obj.mass * float(obj.velocity @ obj.velocity) + 0.5 * float(
        obj.omega @ I_world @ obj.omega
    )
