"""An independent oracle for the free object's step: hapticd.physics.kernels.free_body_step's
model (the Dynamics stage's physics, in the tick's one call) written again in numpy,
independently: forces summed in another order, Euler's equations in the world frame,
Rodrigues with a Bjorck step instead of a quaternion exponential. Tests only
(tests/test_dynamics.py checks the one call against it).

``step_body`` advances a SceneObject by dt (s) in ``substeps`` semi-implicit Euler steps.
The fingers' contact forces are held over the tick (they are computed once per servo
tick); gravity (m/s^2) and surface contact act only when given. Surface contact is a
penalty spring-damper at the object's vertices with Coulomb friction whose tangential
impulse never exceeds what stops the sliding vertex in one step.
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.physics.scene import SceneObject, Surface


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


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (..., 3) arrays (np.cross is slow for small inputs)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


class SurfaceSet:
    """Surfaces stacked for one matrix product per step: normals (s, 3), offsets (s,)."""

    def __init__(self, surfaces: list[Surface]) -> None:
        self.surfaces = surfaces
        self.normals = np.array([s.normal for s in surfaces], dtype=float).reshape(-1, 3)
        self.offsets = np.array([s.offset for s in surfaces], dtype=float)


def surface_wrench(
    obj: SceneObject, surfaces: SurfaceSet, dt: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """Force (3,) N and torque about the COM (3,) N m from surface contact; None if none."""
    verts = obj.vertices_world()
    pen_all = surfaces.offsets - verts @ surfaces.normals.T  # (v, s); > 0: inside the solid
    if not (pen_all > 0.0).any():
        return None
    rel = verts - obj.position
    vel = obj.velocity + cross(obj.omega, rel)
    force = np.zeros(3)
    torque = np.zeros(3)
    for k, s in enumerate(surfaces.surfaces):
        pen = pen_all[:, k]
        hit = pen > 0.0
        if not hit.any():
            continue
        n = surfaces.normals[k]
        m = s.material
        vn = vel[hit] @ n
        fn = np.maximum(m.stiffness * pen[hit] - m.damping * vn, 0.0)
        f = fn[:, None] * n
        if m.mu_dynamic > 0.0:
            vt = vel[hit] - vn[:, None] * n
            speed = np.sqrt((vt * vt).sum(axis=1))
            share = obj.mass / max(int(np.count_nonzero(hit)), 1)
            cap = np.minimum(m.mu_dynamic * fn, share * speed / dt)
            scale = np.divide(cap, speed, out=np.zeros_like(cap), where=speed > 1e-12)
            f = f - vt * scale[:, None]
        force += f.sum(axis=0)
        torque += cross(rel[hit], f).sum(axis=0)
    return force, torque


def step_body(
    obj: SceneObject,
    force: np.ndarray,
    torque: np.ndarray,
    dt: float,
    *,
    gravity: np.ndarray | None = None,
    surfaces: SurfaceSet | None = None,
    substeps: int = 1,
    torsion: list[tuple[np.ndarray, float]] | None = None,
    springs: list[tuple[np.ndarray, np.ndarray, float]] | None = None,
) -> None:
    """Advance a free object by dt under ``force`` (N) and ``torque`` (N m, about the COM).

    ``torsion``: soft-finger contacts as (unit normal, largest moment N m); each
    resists the object's spin about its normal up to that moment.
    ``springs``: finger contacts as (contact point m, force on the object N,
    stiffness N/m) at the tick's start. Within the tick each acts as a spring
    fixed to the object: its force changes by -k times the point's motion, so
    substeps see the fingers as the stiff springs they are, not as held forces.
    """
    h = dt / substeps
    inv_mass = 1.0 / obj.mass
    I_body = obj.inertia_body
    R0, x0 = obj.rotation.copy(), obj.position.copy()
    anchored = [(c, R0.T @ (c - x0), f, k) for c, f, k in springs] if springs else []
    for _ in range(substeps):
        F = force.copy()
        T = torque.copy()
        for c0, body, f0, k in anchored:
            rel = obj.rotation @ body
            f = f0 - k * (obj.position + rel - c0)
            F += f
            T += cross(rel, f)
        if gravity is not None:
            F += obj.mass * gravity
        if surfaces is not None:
            wrench = surface_wrench(obj, surfaces, h)
            if wrench is not None:
                F += wrench[0]
                T += wrench[1]
        R = obj.rotation
        I_world = R @ I_body @ R.T
        w = obj.omega
        if torsion:
            for n_, cap in torsion:
                n = np.asarray(n_, dtype=float)
                spin = float(w @ n)
                if spin != 0.0:
                    stop = float(n @ I_world @ n) * abs(spin) / h
                    T = T - math.copysign(min(cap, stop), spin) * n
        obj.velocity = obj.velocity + h * inv_mass * F
        obj.omega = w + h * np.linalg.solve(I_world, T - cross(w, I_world @ w))
        obj.position = obj.position + h * obj.velocity
        obj.rotation = rotate(R, obj.omega, h)
