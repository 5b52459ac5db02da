"""The virtual scene: the grasped object, the ground and walls, gravity.

The object is a convex polytope in its body frame (origin at its centre of
mass), placed by a pose; a free object also has mass (kg), inertia (kg m^2,
body frame) and velocities. Ground and walls are half-spaces. Each has a
material: stiffness (N/m), damping (N s/m), static and dynamic friction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hapticd.physics.kernels import world_planes


def rpy_matrix(rpy: tuple[float, float, float]) -> np.ndarray:
    """Rotation (3, 3) for roll, pitch, yaw (rad) about fixed x, y, z: Rz Ry Rx."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


@dataclass(frozen=True)
class Material:
    """Contact material: stiffness k (N/m), damping b (N s/m), friction mu_s >= mu_d."""

    stiffness: float
    damping: float = 0.0
    mu_static: float = 0.0
    mu_dynamic: float = 0.0
    torsion: float = 0.0  # m: torsional friction moment per newton of normal force

    @property
    def has_friction(self) -> bool:
        return self.mu_static > 0.0


@dataclass(frozen=True)
class Polytope:
    """Convex polytope as half-spaces n . x <= d: unit outward normals (m, 3), offsets (m,)
    in m, and a centre (3,) m; contact renders against it (``kernels.contact_step``)."""

    normals: np.ndarray
    offsets: np.ndarray
    center: np.ndarray

    def signed_distance(self, x: np.ndarray) -> float:
        """max_i (n_i . x - d_i): > 0 outside, < 0 inside (exact inside, a lower bound outside)."""
        return float(np.max(self.normals @ np.asarray(x, dtype=float) - self.offsets))


@dataclass(frozen=True)
class ConvexShape:
    """Convex polytope in its body frame: unit normals (m, 3), offsets (m,) m, vertices (v, 3)
    m, volume m^3. A mesh's hull is made by ``hapticd.daemon.build.mesh_shape``."""

    normals: np.ndarray
    offsets: np.ndarray
    vertices: np.ndarray
    volume: float
    inertia_unit_mass: np.ndarray  # (3, 3) kg m^2 per kg, about the centre of mass

    @classmethod
    def box(cls, size: np.ndarray) -> ConvexShape:
        a, b, c = (float(s) for s in size)
        h = 0.5 * np.array([a, b, c])
        normals = np.vstack([np.eye(3), -np.eye(3)])
        offsets = np.concatenate([h, h])
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        inertia = np.diag([b * b + c * c, a * a + c * c, a * a + b * b]) / 12.0
        return cls(normals, offsets, signs * h, a * b * c, inertia)


OBJECT_STATE = 18
"""Length of a SceneObject's ``state``: x (3, m), v (3, m/s), w (3, rad/s), R (9, row by
row)."""

_MOTION: dict[str, tuple[slice, tuple[int, ...]]] = {
    "position": (slice(0, 3), (3,)),
    "velocity": (slice(3, 6), (3,)),
    "omega": (slice(6, 9), (3,)),
    "rotation": (slice(9, 18), (3, 3)),
}


@dataclass
class SceneObject:
    """The grasped object: shape, material and pose; velocities and mass (kg) when free.

    ``position`` (3,) m, ``velocity`` (3,) m/s, ``omega`` (3,) rad/s and ``rotation`` (3, 3)
    are always views of one array, ``state`` (OBJECT_STATE,), which the kernels update in
    place; assigning one of them copies into it.
    """

    shape: ConvexShape
    material: Material
    position: np.ndarray
    rotation: np.ndarray
    fixed: bool = True
    mass: float = 0.0
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        given = {name: self.__dict__[name] for name in _MOTION}
        self.__dict__["state"] = np.zeros(OBJECT_STATE)
        self._bind()
        for name, value in given.items():
            setattr(self, name, value)

    def _bind(self) -> None:
        state = self.__dict__["state"]
        for name, (part, shape) in _MOTION.items():
            self.__dict__[name] = state[part].reshape(shape)

    def __setattr__(self, name: str, value: object) -> None:
        if name in _MOTION and "state" in self.__dict__:
            shape = _MOTION[name][1]
            self.__dict__[name][...] = np.asarray(value, dtype=float).reshape(shape)
            return
        object.__setattr__(self, name, value)

    def __getstate__(self) -> dict[str, object]:
        # The views are made again from the state on the other side (a deep copy or a
        # pickle would otherwise detach them from it).
        return {k: v for k, v in self.__dict__.items() if k not in _MOTION}

    def __setstate__(self, d: dict[str, object]) -> None:
        self.__dict__.update(d)
        self._bind()

    @property
    def polytope(self) -> Polytope:
        """The world-frame polytope at the object's pose now (by the tick's own
        ``world_planes``, so it matches the contact kernel's planes bit for bit)."""
        shape = self.shape
        planes = np.zeros((len(shape.offsets), 4))
        world_planes(self.rotation, self.position, shape.normals, shape.offsets, planes)
        return Polytope(planes[:, :3], planes[:, 3], self.position.copy())

    @property
    def center(self) -> np.ndarray:
        """Centre of mass, the grasp reference point (m)."""
        return self.position

    @property
    def inertia_body(self) -> np.ndarray:
        return self.mass * self.shape.inertia_unit_mass

    def vertices_world(self) -> np.ndarray:
        return self.shape.vertices @ self.rotation.T + self.position


@dataclass(frozen=True)
class Surface:
    """A half-space obstacle (ground or wall): solid where normal . x <= offset."""

    name: str
    normal: tuple[float, float, float]
    offset: float
    material: Material

    @property
    def polytope(self) -> Polytope:
        return Polytope(np.array([self.normal]), np.array([self.offset]), np.zeros(3))


@dataclass
class Scene:
    """Everything the fingers and the object can touch, and gravity (m/s^2) if enabled."""

    object: SceneObject
    surfaces: list[Surface]
    gravity: np.ndarray | None
    substeps: int = 1  # 0: chosen by the renderer's plan (auto)
