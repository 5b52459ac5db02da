"""Kinematics of a 3-DOF delta (Clavel) haptic device, such as an Omega-class device.

Three motors on a base triangle turn upper arms; parallelogram lower arms keep
the end-effector parallel to the base. With motor azimuths phi_i, base radius
R, effector radius r, upper arm a and lower arm b, the elbow of arm i at arm
angle theta_i (below the base plane) is

    E_i = (R + a cos theta_i) u_i - a sin theta_i z,  u_i = (cos phi_i, sin phi_i, 0)

and the end-effector p satisfies |p + r u_i - E_i| = b for i = 1, 2, 3.
Forward kinematics intersects three spheres; inverse kinematics solves each
arm in closed form; the Jacobian J = dp/dtheta follows from differentiating the
constraints, and motor torques are J^T f (virtual work f . dp = tau . dtheta).
Positions are in the device frame, origin at the home pose, metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from hapticd_drivers.base import DeviceError


class KinematicsError(DeviceError):
    """A pose the mechanism cannot reach, or a description that does not describe one."""


@dataclass(frozen=True)
class DeltaDescription:
    """Geometry (m, rad), encoders, motors and limits of one delta device model."""

    model: str
    base_radius: float
    effector_radius: float
    upper_arm: float
    lower_arm: float
    azimuth: tuple[float, float, float]
    home_angle: float
    counts_per_rev: int
    gear_ratio: float
    torque_constant: float
    max_current: float
    max_force: float
    workspace_radius: float
    reports: dict[str, Any] | None = None
    usb: dict[str, Any] | None = None

    @property
    def counts_per_radian(self) -> float:
        """Encoder counts per radian of arm rotation."""
        return self.counts_per_rev * self.gear_ratio / (2.0 * math.pi)

    @property
    def max_arm_torque(self) -> float:
        """Largest torque a motor puts on its arm, N m."""
        return self.torque_constant * self.max_current * self.gear_ratio


def _get(data: dict[str, Any], path: str, where: str) -> Any:
    node: Any = data
    for key in path.split("."):
        if not isinstance(node, dict) or key not in node:
            raise KinematicsError(f"{where}: missing key {path!r}")
        node = node[key]
    return node


def load_description(name_or_path: str | Path) -> DeltaDescription:
    """A device description by bundled name (e.g. 'delta-omega-class') or YAML path."""
    p = Path(name_or_path)
    if not p.suffix:
        p = Path(str(resources.files("hapticd_drivers") / "devices" / f"{name_or_path}.yaml"))
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise KinematicsError(f"{p}: cannot read device description: {exc}") from None
    if not isinstance(data, dict):
        raise KinematicsError(f"{p}: expected a mapping")
    w = str(p)
    try:
        az = tuple(float(v) for v in _get(data, "geometry.motor_azimuth_rad", w))
        desc = DeltaDescription(
            model=str(_get(data, "model", w)),
            base_radius=float(_get(data, "geometry.base_radius_m", w)),
            effector_radius=float(_get(data, "geometry.effector_radius_m", w)),
            upper_arm=float(_get(data, "geometry.upper_arm_m", w)),
            lower_arm=float(_get(data, "geometry.lower_arm_m", w)),
            azimuth=(az[0], az[1], az[2]),
            home_angle=float(_get(data, "geometry.home_angle_rad", w)),
            counts_per_rev=int(_get(data, "encoders.counts_per_rev", w)),
            gear_ratio=float(_get(data, "encoders.gear_ratio", w)),
            torque_constant=float(_get(data, "motors.torque_constant_n_m_per_a", w)),
            max_current=float(_get(data, "motors.max_current_a", w)),
            max_force=float(_get(data, "limits.max_force_n", w)),
            workspace_radius=float(_get(data, "limits.workspace_radius_m", w)),
            reports=data.get("reports"),
            usb=data.get("usb"),
        )
    except (TypeError, ValueError, IndexError) as exc:
        raise KinematicsError(f"{w}: malformed value: {exc}") from None
    if min(desc.base_radius, desc.upper_arm, desc.lower_arm, desc.counts_per_rev) <= 0:
        raise KinematicsError(f"{w}: lengths and counts must be positive")
    return desc


class Delta:
    """Forward and inverse kinematics, Jacobian and force mapping of one delta device."""

    def __init__(self, desc: DeltaDescription) -> None:
        self.desc = desc
        self._u = np.array([[math.cos(a), math.sin(a), 0.0] for a in desc.azimuth])
        self._v = np.array([[-math.sin(a), math.cos(a), 0.0] for a in desc.azimuth])
        home = np.full(3, desc.home_angle)
        self.origin = np.zeros(3)
        self.origin = self.forward(home)

    def _centres(self, theta: np.ndarray) -> np.ndarray:
        """Sphere centres C_i = E_i - r u_i (base frame), shape (3, 3)."""
        d = self.desc
        reach = d.base_radius - d.effector_radius + d.upper_arm * np.cos(theta)
        c = self._u * reach[:, None]
        c[:, 2] = -d.upper_arm * np.sin(theta)
        return c

    def forward(self, theta: np.ndarray) -> np.ndarray:
        """End-effector position (3,) m in the device frame for arm angles (3,) rad."""
        C = self._centres(np.asarray(theta, dtype=float))
        b = self.desc.lower_arm
        A = 2.0 * np.array([C[1] - C[0], C[2] - C[0]])
        rhs = np.array([C[1] @ C[1] - C[0] @ C[0], C[2] @ C[2] - C[0] @ C[0]])
        p0 = A.T @ np.linalg.solve(A @ A.T, rhs)
        n = np.cross(C[1] - C[0], C[2] - C[0])
        q = p0 - C[0]
        aa, bb, cc = n @ n, 2.0 * (n @ q), q @ q - b * b
        disc = bb * bb - 4.0 * aa * cc
        if disc < 0.0:
            raise KinematicsError(
                f"arm angles {np.asarray(theta).tolist()} do not close the mechanism"
            )
        roots = ((-bb - math.sqrt(disc)) / (2 * aa), (-bb + math.sqrt(disc)) / (2 * aa))
        pts = [p0 + s * n for s in roots]
        p = min(pts, key=lambda x: x[2])  # the end-effector hangs below the base
        return p - self.origin

    def inverse(self, p: np.ndarray) -> np.ndarray:
        """Arm angles (3,) rad for an end-effector position (3,) m (elbows out)."""
        d = self.desc
        x = np.asarray(p, dtype=float) + self.origin
        theta = np.empty(3)
        for i in range(3):
            X = x @ self._u[i] + d.effector_radius - d.base_radius
            Y = x @ self._v[i]
            Z = x[2]
            # -2 a X cos(t) + 2 a Z sin(t) = b^2 - X^2 - Y^2 - Z^2 - a^2
            A, B = -2.0 * d.upper_arm * X, 2.0 * d.upper_arm * Z
            K = d.lower_arm**2 - X * X - Y * Y - Z * Z - d.upper_arm**2
            rho = math.hypot(A, B)
            if rho == 0.0 or abs(K) > rho:
                raise KinematicsError(
                    f"position {np.asarray(p).tolist()} m is out of reach of arm {i}"
                )
            theta[i] = math.atan2(B, A) + math.acos(K / rho)
        return (theta + math.pi) % (2.0 * math.pi) - math.pi

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        """J = dp/dtheta (3, 3), m per rad."""
        d = self.desc
        theta = np.asarray(theta, dtype=float)
        C = self._centres(theta)
        p = self.forward(theta) + self.origin
        dC = self._u * (-d.upper_arm * np.sin(theta))[:, None]
        dC[:, 2] = -d.upper_arm * np.cos(theta)
        rows = p - C  # constraint gradients: (p - C_i) . dp = (p - C_i) . dC_i dtheta_i
        Bdiag = np.einsum("ij,ij->i", rows, dC)
        return np.linalg.solve(rows, np.diag(Bdiag))

    def torques(self, theta: np.ndarray, force: np.ndarray) -> np.ndarray:
        """Arm torques (3,) N m that render ``force`` (3,) N at the end-effector: J^T f."""
        return self.jacobian(theta).T @ np.asarray(force, dtype=float)

    def angles_from_counts(self, counts: np.ndarray) -> np.ndarray:
        """Arm angles (3,) rad from encoder counts relative to the home pose."""
        return self.desc.home_angle + np.asarray(counts, dtype=float) / self.desc.counts_per_radian

    def counts_from_angles(self, theta: np.ndarray) -> np.ndarray:
        """Encoder counts (3,) int relative to the home pose (quantised as an encoder would)."""
        return np.round(
            (np.asarray(theta) - self.desc.home_angle) * self.desc.counts_per_radian
        ).astype(np.int64)

    def currents(self, tau: np.ndarray) -> np.ndarray:
        """Motor currents (3,) A for arm torques (3,) N m, before saturation."""
        d = self.desc
        return np.asarray(tau, dtype=float) / (d.torque_constant * d.gear_ratio)
