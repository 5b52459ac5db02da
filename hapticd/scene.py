"""The virtual scene: the grasped object's geometry, pose and contact parameters."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hapticd.contact import Polytope, box_polytope
from hapticd.profile import BoxConfig


def rpy_matrix(rpy: tuple[float, float, float]) -> np.ndarray:
    """Rotation (3, 3) for roll, pitch, yaw (rad) about fixed x, y, z: Rz Ry Rx."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


@dataclass(frozen=True)
class SceneObject:
    """A fixed object: convex geometry (m), stiffness (N/m), damping (N s/m)."""

    polytope: Polytope
    stiffness: float
    damping: float

    @property
    def center(self) -> np.ndarray:
        return self.polytope.center

    @classmethod
    def from_config(cls, cfg: BoxConfig) -> SceneObject:
        poly = box_polytope(
            np.array(cfg.position_m), rpy_matrix(cfg.orientation_rpy_rad), np.array(cfg.size_m)
        )
        return cls(poly, cfg.stiffness_n_per_m, cfg.damping_n_s_per_m)
