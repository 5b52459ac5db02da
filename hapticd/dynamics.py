"""Rigid-body dynamics of a free object: contact reactions, gravity, ground and walls.

``step_body`` advances a SceneObject by dt (s) in ``substeps`` semi-implicit
Euler steps. The fingers' contact forces are held over the tick (they are
computed once per servo tick); gravity (m/s^2) and surface contact act only
when given, so a scene without them never computes them. Surface contact is a
penalty spring-damper at the object's vertices with Coulomb friction whose
tangential impulse never exceeds what stops the sliding vertex in one step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from hapticd.scene import Material, SceneObject, Surface


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
    obj.update_world()


def kinetic_energy(obj: SceneObject) -> float:
    """Translational plus rotational kinetic energy, J."""
    I_world = obj.rotation @ obj.inertia_body @ obj.rotation.T
    return 0.5 * obj.mass * float(obj.velocity @ obj.velocity) + 0.5 * float(
        obj.omega @ I_world @ obj.omega
    )


# -- the same step on plain floats: faster for small shapes (a box has 8 vertices) -------------

SMALL_SHAPE = 32  # vertices; above this the numpy path is faster


def _mat_vec(M: list[list[float]], v: tuple[float, float, float]) -> tuple[float, float, float]:
    return (
        M[0][0] * v[0] + M[0][1] * v[1] + M[0][2] * v[2],
        M[1][0] * v[0] + M[1][1] * v[1] + M[1][2] * v[2],
        M[2][0] * v[0] + M[2][1] * v[1] + M[2][2] * v[2],
    )


def _transpose(A: list[list[float]]) -> list[list[float]]:
    return [[A[0][i], A[1][i], A[2][i]] for i in range(3)]


def _cross3(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float]:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def quat_from_matrix(R: list[list[float]]) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    tr = R[0][0] + R[1][1] + R[2][2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        return (0.25 * s, (R[2][1] - R[1][2]) / s, (R[0][2] - R[2][0]) / s, (R[1][0] - R[0][1]) / s)
    if R[0][0] > R[1][1] and R[0][0] > R[2][2]:
        s = 2.0 * math.sqrt(1.0 + R[0][0] - R[1][1] - R[2][2])
        return ((R[2][1] - R[1][2]) / s, 0.25 * s, (R[0][1] + R[1][0]) / s, (R[0][2] + R[2][0]) / s)
    if R[1][1] > R[2][2]:
        s = 2.0 * math.sqrt(1.0 + R[1][1] - R[0][0] - R[2][2])
        return ((R[0][2] - R[2][0]) / s, (R[0][1] + R[1][0]) / s, 0.25 * s, (R[1][2] + R[2][1]) / s)
    s = 2.0 * math.sqrt(1.0 + R[2][2] - R[0][0] - R[1][1])
    return ((R[1][0] - R[0][1]) / s, (R[0][2] + R[2][0]) / s, (R[1][2] + R[2][1]) / s, 0.25 * s)


def matrix_from_quat(q: tuple[float, float, float, float]) -> list[list[float]]:
    w, x, y, z = q
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]


def _quat_step(
    q: tuple[float, float, float, float], w: tuple[float, float, float], h: float
) -> tuple[float, float, float, float]:
    """q advanced by the world-frame angular velocity w over h: exp(w h / 2) * q, normalised."""
    speed = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    half = 0.5 * speed * h
    if half < 1e-15:
        return q
    if half == math.inf:
        # A spin whose square overflowed: math.cos would raise. NaN, as the compiled step
        # gives; the loop's object check then ends the run (an object_state fault).
        return (math.nan, math.nan, math.nan, math.nan)
    c, s = math.cos(half), math.sin(half) / speed
    a = (c, s * w[0], s * w[1], s * w[2])
    r = (
        a[0] * q[0] - a[1] * q[1] - a[2] * q[2] - a[3] * q[3],
        a[0] * q[1] + a[1] * q[0] + a[2] * q[3] - a[3] * q[2],
        a[0] * q[2] - a[1] * q[3] + a[2] * q[0] + a[3] * q[1],
        a[0] * q[3] + a[1] * q[2] - a[2] * q[1] + a[3] * q[0],
    )
    n = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3])
    return (r[0] / n, r[1] / n, r[2] / n, r[3] / n)


class SmallBody:
    """What ``step_body_small`` derives from an object's shape and mass and the surfaces,
    on plain floats: body inertia and its inverse (kg m^2, rows), the vertices (m, body
    frame), the surfaces' (normal, offset m, material) and the reach (m: the farthest
    vertex from the centre of mass)."""

    def __init__(self, obj: SceneObject, surfaces: SurfaceSet | None) -> None:
        self.shape = obj.shape
        self.mass = obj.mass
        self.surfaces = surfaces
        self.Ib = obj.inertia_body.tolist()
        self.Ib_inv = np.linalg.inv(obj.inertia_body).tolist()
        self.local = [tuple(p) for p in obj.shape.vertices.tolist()]
        self.reach = max((math.sqrt(_dot3(p, p)) for p in self.local), default=0.0)
        self.surf = []
        if surfaces is not None:
            self.surf = [
                (tuple(map(float, n)), float(d), s.material)
                for n, d, s in zip(
                    surfaces.normals, surfaces.offsets, surfaces.surfaces, strict=True
                )
            ]

    def fits(self, obj: SceneObject, surfaces: SurfaceSet | None) -> bool:
        """True while it describes ``obj`` (same shape, same mass) and ``surfaces``."""
        return obj.shape is self.shape and obj.mass == self.mass and surfaces is self.surfaces


def _dot3(a: Sequence[float], b: Sequence[float]) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def step_body_small(
    obj: SceneObject,
    force: tuple[float, float, float],
    torque: tuple[float, float, float],
    dt: float,
    *,
    gravity: np.ndarray | None = None,
    surfaces: SurfaceSet | None = None,
    substeps: int = 1,
    torsion: list[tuple[np.ndarray, float]] | None = None,
    springs: list[tuple[np.ndarray, np.ndarray, float]] | None = None,
    prepared: SmallBody | None = None,
) -> None:
    """``step_body`` on plain floats, for shapes with few vertices. Same model, same results.

    ``prepared``: what the step derives from the object's shape and mass and the
    surfaces (made anew here when it does not fit them; the Dynamics stage keeps one).
    """
    if prepared is None or not prepared.fits(obj, surfaces):
        prepared = SmallBody(obj, surfaces)
    h = dt / substeps
    m = obj.mass
    x = tuple(map(float, obj.position))
    v = tuple(map(float, obj.velocity))
    w = tuple(map(float, obj.omega))
    R = obj.rotation.tolist()
    q = quat_from_matrix(R)
    Ib, Ib_inv, local, surf = prepared.Ib, prepared.Ib_inv, prepared.local, prepared.surf
    gx, gy, gz = (0.0, 0.0, 0.0) if gravity is None else tuple(map(float, gravity))
    tors = [(tuple(map(float, n)), float(c)) for n, c in torsion] if torsion else []
    Rt0 = _transpose(R)
    anchored = []
    for c, f, k in springs or []:
        c0 = (float(c[0]), float(c[1]), float(c[2]))
        body = _mat_vec(Rt0, (c0[0] - x[0], c0[1] - x[1], c0[2] - x[2]))
        anchored.append((c0, body, (float(f[0]), float(f[1]), float(f[2])), float(k)))
    for _ in range(substeps):
        Fx, Fy, Fz = force[0] + m * gx, force[1] + m * gy, force[2] + m * gz
        Tx, Ty, Tz = torque
        for c0, body, f0, k in anchored:
            rel = _mat_vec(R, body)
            f = (
                f0[0] - k * (x[0] + rel[0] - c0[0]),
                f0[1] - k * (x[1] + rel[1] - c0[1]),
                f0[2] - k * (x[2] + rel[2] - c0[2]),
            )
            t = _cross3(rel, f)
            Fx, Fy, Fz = Fx + f[0], Fy + f[1], Fz + f[2]
            Tx, Ty, Tz = Tx + t[0], Ty + t[1], Tz + t[2]
        if surf:
            fs, ts = surface_wrench_small(surf, local, R, x, v, w, m, h, prepared.reach)
            Fx, Fy, Fz = Fx + fs[0], Fy + fs[1], Fz + fs[2]
            Tx, Ty, Tz = Tx + ts[0], Ty + ts[1], Tz + ts[2]
        # Euler's equations in the body frame, where the inertia is constant.
        Rt = _transpose(R)
        for n, cap in tors:
            spin = w[0] * n[0] + w[1] * n[1] + w[2] * n[2]
            if spin != 0.0:
                nb = _mat_vec(Rt, n)
                # 0.0 + ...: the sum() this was, term by term (a generator costs more).
                In = (
                    0.0
                    + nb[0] * (Ib[0][0] * nb[0] + Ib[0][1] * nb[1] + Ib[0][2] * nb[2])
                    + nb[1] * (Ib[1][0] * nb[0] + Ib[1][1] * nb[1] + Ib[1][2] * nb[2])
                    + nb[2] * (Ib[2][0] * nb[0] + Ib[2][1] * nb[1] + Ib[2][2] * nb[2])
                )
                t = math.copysign(min(cap, In * abs(spin) / h), spin)
                Tx, Ty, Tz = Tx - t * n[0], Ty - t * n[1], Tz - t * n[2]
        wb = _mat_vec(Rt, w)
        gyro = _cross3(wb, _mat_vec(Ib, wb))
        Tb = _mat_vec(Rt, (Tx, Ty, Tz))
        dwb = _mat_vec(Ib_inv, (Tb[0] - gyro[0], Tb[1] - gyro[1], Tb[2] - gyro[2]))
        dw = _mat_vec(R, dwb)
        v = (v[0] + h * Fx / m, v[1] + h * Fy / m, v[2] + h * Fz / m)
        w = (w[0] + h * dw[0], w[1] + h * dw[1], w[2] + h * dw[2])
        x = (x[0] + h * v[0], x[1] + h * v[1], x[2] + h * v[2])
        q = _quat_step(q, w, h)
        R = matrix_from_quat(q)
    obj.position = np.array(x)
    obj.velocity = np.array(v)
    obj.omega = np.array(w)
    obj.rotation = np.array(R)
    obj.update_world()


def surface_wrench_small(
    surf: list[tuple[tuple[float, float, float], float, Material]],
    local: list[tuple[float, float, float]],
    R: list[list[float]],
    x: tuple[float, float, float],
    v: tuple[float, float, float],
    w: tuple[float, float, float],
    m: float,
    h: float,
    reach: float = math.inf,
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """``surface_wrench`` on plain floats: (force N, torque about the COM N m).

    ``reach`` (m): no vertex lies farther than this from the centre of mass; a surface
    the object is farther from than that (with room for rounding) is not looked at.
    """
    Fx = Fy = Fz = Tx = Ty = Tz = 0.0
    rels: list[tuple[float, float, float]] | None = None
    x0, x1, x2 = x
    ax = abs(x0) + abs(x1) + abs(x2)
    for n, d, mat in surf:
        n0, n1, n2 = n
        # Every vertex is at least n.x - |n| reach above the surface (|n| <= |n|_1); the
        # margin covers the rounding of the sums below many times over. NaN never skips.
        nn = abs(n0) + abs(n1) + abs(n2)
        clear = n0 * x0 + n1 * x1 + n2 * x2 - nn * reach - d
        if clear > 1e-9 * (nn * (ax + reach) + abs(d)):
            continue
        if rels is None:
            (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R
            # _mat_vec inline: the same sums.
            rels = [
                (
                    r00 * p0 + r01 * p1 + r02 * p2,
                    r10 * p0 + r11 * p1 + r12 * p2,
                    r20 * p0 + r21 * p1 + r22 * p2,
                )
                for p0, p1, p2 in local
            ]
        hits = []
        for r in rels:
            pen = d - (n0 * (r[0] + x0) + n1 * (r[1] + x1) + n2 * (r[2] + x2))
            if pen > 0.0:
                hits.append((r, pen))
        if not hits:
            continue
        share = m / len(hits)
        for r, pen in hits:
            s = _cross3(w, r)
            vel = (v[0] + s[0], v[1] + s[1], v[2] + s[2])
            vn = vel[0] * n[0] + vel[1] * n[1] + vel[2] * n[2]
            fn = mat.stiffness * pen - mat.damping * vn
            if fn <= 0.0:
                continue
            f = [fn * n[0], fn * n[1], fn * n[2]]
            if mat.mu_dynamic > 0.0:
                vt = (vel[0] - vn * n[0], vel[1] - vn * n[1], vel[2] - vn * n[2])
                speed = math.sqrt(vt[0] * vt[0] + vt[1] * vt[1] + vt[2] * vt[2])
                if speed > 1e-12:
                    k = min(mat.mu_dynamic * fn, share * speed / h) / speed
                    f[0] -= k * vt[0]
                    f[1] -= k * vt[1]
                    f[2] -= k * vt[2]
            Fx, Fy, Fz = Fx + f[0], Fy + f[1], Fz + f[2]
            t = _cross3(r, f)
            Tx, Ty, Tz = Tx + t[0], Ty + t[1], Tz + t[2]
    return (Fx, Fy, Fz), (Tx, Ty, Tz)


def auto_substeps(
    obj: SceneObject, surfaces: list[Surface], finger_stiffness: float, n_fingers: int, dt: float
) -> int:
    """Substeps that keep omega h and (damping / mass) h below 0.5 for a free object.

    Counts every finger and the surface vertices that can touch at once (a face:
    four for a box) as springs and dampers in parallel: a conservative bound.
    """
    touching = min(4, len(obj.shape.vertices))
    k = n_fingers * finger_stiffness + sum(touching * s.material.stiffness for s in surfaces[:1])
    b = n_fingers * obj.material.damping + sum(touching * s.material.damping for s in surfaces[:1])
    omega = math.sqrt(k / obj.mass)
    rate = max(omega, b / obj.mass)
    return max(1, min(64, math.ceil(rate * dt / 0.5)))
