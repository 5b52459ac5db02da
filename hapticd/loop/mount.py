"""Device mounts: where each device's frame sits in the world, and the maps between them.

A mount is a rotation R (3, 3), a position t (3,) m and a workspace scale s (> 0,
dimensionless). A device reports positions and velocities in its own frame; the
tick frame holds world quantities; the device gets device-frame forces:

    x_world = s R x_dev + t,    v_world = s R v_dev,    f_dev = R^T f_world

so |f_dev| = |f_world| (force limits hold unchanged at the device) and a world
stiffness k is felt at the device as k s (docs/devices.md, "Mounting").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hapticd.physics.scene import rpy_matrix

# Angles beyond one turn are almost always degrees written where radians belong.
MAX_ANGLE_RAD = 2.0 * math.pi
_ORTHO_TOL = 1e-9


def mount_rotation(rpy: tuple[float, float, float]) -> np.ndarray:
    """The rotation (3, 3) for roll, pitch, yaw (rad, fixed x, y, z axes); ValueError for
    angles that are not finite, beyond one turn, or give no proper rotation."""
    vals = [float(a) for a in rpy]
    if len(vals) != 3 or not all(math.isfinite(a) for a in vals):
        raise ValueError(f"roll, pitch, yaw must be 3 finite angles in rad, got {list(rpy)}")
    if any(abs(a) > MAX_ANGLE_RAD for a in vals):
        raise ValueError(
            f"angles are in rad and within one turn (|angle| <= {MAX_ANGLE_RAD:.4f}); got "
            f"{vals} (degrees?)"
        )
    R = rpy_matrix((vals[0], vals[1], vals[2]))
    if not (
        np.all(np.isfinite(R))
        and np.abs(R.T @ R - np.eye(3)).max() <= _ORTHO_TOL
        and np.linalg.det(R) > 0
    ):
        raise ValueError(f"roll, pitch, yaw {vals} give no rotation")
    return R


@dataclass(frozen=True)
class Mount:
    """A device frame in the world: rotation (3, 3), position (3,) m, workspace scale s."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    def __post_init__(self) -> None:
        R = np.array(self.rotation, dtype=float).reshape(3, 3)
        t = np.array(self.position, dtype=float).reshape(3)
        if not (np.all(np.isfinite(R)) and np.abs(R.T @ R - np.eye(3)).max() <= _ORTHO_TOL):
            raise ValueError("a mount's rotation must be a finite orthonormal 3x3 matrix")
        if np.linalg.det(R) <= 0:
            raise ValueError("a mount's rotation must be proper (det +1), not a reflection")
        if not np.all(np.isfinite(t)):
            raise ValueError(f"a mount's position must be finite, got {t.tolist()}")
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"a mount's workspace scale must be positive, got {self.scale}")
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "position", t)
        object.__setattr__(self, "scale", float(self.scale))

    @classmethod
    def from_rpy(
        cls, position_m: tuple[float, ...], rpy_rad: tuple[float, ...], scale: float = 1.0
    ) -> Mount:
        return cls(mount_rotation(rpy_rad), np.array(position_m, dtype=float), scale)

    @property
    def is_identity(self) -> bool:
        """True when device and world frames coincide (the maps are exact copies)."""
        return bool(
            self.scale == 1.0
            and np.array_equal(self.rotation, np.eye(3))
            and not np.any(self.position)
        )

    def point_to_world(self, x_dev: np.ndarray) -> np.ndarray:
        """s R x + t for points (..., 3) m in the device frame."""
        return self.scale * (np.asarray(x_dev) @ self.rotation.T) + self.position

    def vector_to_world(self, v_dev: np.ndarray) -> np.ndarray:
        """s R v for velocities (..., 3) m/s in the device frame."""
        return self.scale * (np.asarray(v_dev) @ self.rotation.T)

    def point_to_device(self, x_world: np.ndarray) -> np.ndarray:
        """R^T (x - t) / s for points (..., 3) m in the world."""
        return ((np.asarray(x_world) - self.position) @ self.rotation) / self.scale

    def force_to_device(self, f_world: np.ndarray) -> np.ndarray:
        """R^T f for forces (..., 3) N in the world."""
        return np.asarray(f_world) @ self.rotation


def distance_to_polytope(normals: np.ndarray, offsets: np.ndarray, point: np.ndarray) -> float:
    """Euclidean distance (m) from ``point`` (3,) to the convex polytope normals . x <= offsets
    (0 inside); the polytope must be bounded and non-empty."""
    p = np.asarray(point, dtype=float)
    if np.max(normals @ p - offsets) <= 0.0:
        return 0.0
    from scipy.optimize import minimize  # here: the loop's modules never need it

    # A small quadratic programme: the nearest point of the polytope.
    start = np.linalg.lstsq(normals, offsets - 1e-9, rcond=None)[0]
    res = minimize(
        lambda x: float((x - p) @ (x - p)),
        start,
        jac=lambda x: 2.0 * (x - p),
        constraints=[
            {"type": "ineq", "fun": lambda x: offsets - normals @ x, "jac": lambda x: -normals}
        ],
        method="SLSQP",
        options={"ftol": 1e-14, "maxiter": 200},
    )
    return float(np.linalg.norm(res.x - p))


@dataclass(frozen=True)
class Reach:
    """How a device's workspace sphere (world frame) meets the object: the object's centre
    in device coordinates (m), its distance from the workspace centre, the nearest and
    farthest object points from it (m), and the verdicts."""

    center_device_m: np.ndarray
    center_distance_m: float
    nearest_m: float
    farthest_m: float
    workspace_radius_m: float
    reachable: bool  # a fingertip inside the workspace can touch the object
    contained: bool  # the whole object lies inside the workspace


def workspace_reach(
    mount: Mount,
    workspace_radius_m: float,
    normals: np.ndarray,
    offsets: np.ndarray,
    vertices: np.ndarray,
    center: np.ndarray,
    fingertip_radius_m: float,
) -> Reach:
    """Where a device's workspace (a sphere of ``workspace_radius_m`` in the device frame
    about its origin, so s r about t in the world) overlaps the object (world polytope
    ``normals``/``offsets``, its vertices (v, 3) and centre, m)."""
    c = mount.position
    r = mount.scale * workspace_radius_m
    nearest = distance_to_polytope(normals, offsets, c)
    farthest = float(np.max(np.linalg.norm(vertices - c, axis=1)))
    return Reach(
        mount.point_to_device(center),
        float(np.linalg.norm(np.asarray(center) - c)),
        nearest,
        farthest,
        r,
        nearest <= r + fingertip_radius_m,
        farthest <= r,
    )
