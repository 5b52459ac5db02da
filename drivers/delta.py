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
    """Forward and inverse kinematics, Jacobian and force mapping of one delta device.

    Scalar arithmetic on 3-vectors (the math module), not numpy: a device's read and
    write run these every tick, and numpy's per-call overhead on (3,) arrays made them
    four to eight times slower (forward kinematics 71 us against 9, torques 124 against 20)."""

    def __init__(self, desc: DeltaDescription) -> None:
        self.desc = desc
        self._u = [(math.cos(a), math.sin(a)) for a in desc.azimuth]
        self._v = [(-math.sin(a), math.cos(a)) for a in desc.azimuth]
        self._origin = (0.0, 0.0, 0.0)
        self._origin = self._point(self._centres([desc.home_angle] * 3), [desc.home_angle] * 3)
        self.origin = np.array(self._origin)

    def _centres(self, theta: Any) -> list[tuple[float, float, float]]:
        """Sphere centres C_i = E_i - r u_i (base frame, m) for arm angles (3,) rad."""
        d = self.desc
        out = []
        for (ux, uy), t in zip(self._u, (float(t) for t in theta), strict=True):
            reach = d.base_radius - d.effector_radius + d.upper_arm * math.cos(t)
            out.append((ux * reach, uy * reach, -d.upper_arm * math.sin(t)))
        return out

    def _point(self, C: list[tuple[float, float, float]], theta: Any) -> tuple[float, float, float]:
        """The end-effector (base frame, m) for the sphere centres ``C`` of arm angles
        ``theta`` (rad): the lower of the three spheres' two common points."""
        (x0, y0, z0), (x1, y1, z1), (x2, y2, z2) = C
        # The two radical planes 2 d_k . p = |C_k|^2 - |C_0|^2 meet in a line; p0 is its
        # point nearest the origin (the planes' Gram system), n its direction.
        d1 = (x1 - x0, y1 - y0, z1 - z0)
        d2 = (x2 - x0, y2 - y0, z2 - z0)
        s0 = x0 * x0 + y0 * y0 + z0 * z0
        r1 = x1 * x1 + y1 * y1 + z1 * z1 - s0
        r2 = x2 * x2 + y2 * y2 + z2 * z2 - s0
        g11, g12, g22 = _dot(d1, d1), _dot(d1, d2), _dot(d2, d2)
        det = g11 * g22 - g12 * g12
        n = _cross(d1, d2)
        aa = _dot(n, n)
        if not (det > 0.0 and aa > 0.0):
            raise KinematicsError(f"arm angles {list(map(float, theta))} are degenerate")
        w1, w2 = (g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det
        p0 = tuple(0.5 * (w1 * a + w2 * b) for a, b in zip(d1, d2, strict=True))
        q = (p0[0] - x0, p0[1] - y0, p0[2] - z0)
        bb, cc = 2.0 * _dot(n, q), _dot(q, q) - self.desc.lower_arm**2
        disc = bb * bb - 4.0 * aa * cc
        if disc < 0.0:
            raise KinematicsError(
                f"arm angles {list(map(float, theta))} do not close the mechanism"
            )
        lo, hi = (-bb - math.sqrt(disc)) / (2 * aa), (-bb + math.sqrt(disc)) / (2 * aa)
        # The end-effector hangs below the base: the root with the lower z.
        s = lo if p0[2] + lo * n[2] <= p0[2] + hi * n[2] else hi
        return (p0[0] + s * n[0], p0[1] + s * n[1], p0[2] + s * n[2])

    def forward(self, theta: np.ndarray) -> np.ndarray:
        """End-effector position (3,) m in the device frame for arm angles (3,) rad."""
        x, y, z = self._point(self._centres(theta), theta)
        ox, oy, oz = self._origin
        return np.array((x - ox, y - oy, z - oz))

    def inverse(self, p: np.ndarray) -> np.ndarray:
        """Arm angles (3,) rad for an end-effector position (3,) m (elbows out)."""
        d = self.desc
        ox, oy, oz = self._origin
        px, py, pz = (float(v) for v in p)
        x, y, Z = px + ox, py + oy, pz + oz
        theta = np.empty(3)
        for i in range(3):
            (ux, uy), (vx, vy) = self._u[i], self._v[i]
            X = x * ux + y * uy + d.effector_radius - d.base_radius
            Y = x * vx + y * vy
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

    def _columns(self, theta: Any) -> tuple[list[tuple[float, float, float]], list[float]]:
        """J = dp/dtheta as columns (3 of 3) m per rad, from the constraints
        (p - C_i) . dp = (p - C_i) . dC_i dtheta_i: J = M^-1 diag(B) with M's rows p - C_i,
        B_i = (p - C_i) . dC_i; M^-1's columns are the rows' cross products over det M.
        Returns M^-1's columns times det M and B_i / det M."""
        d = self.desc
        C = self._centres(theta)
        px, py, pz = self._point(C, theta)
        rows = [(px - cx, py - cy, pz - cz) for cx, cy, cz in C]
        # dC_i = -a (sin theta_i u_i + cos theta_i z)
        scale = [
            -d.upper_arm * (math.sin(t) * (r[0] * ux + r[1] * uy) + math.cos(t) * r[2])
            for (ux, uy), t, r in zip(self._u, (float(t) for t in theta), rows, strict=True)
        ]
        cols = [_cross(rows[1], rows[2]), _cross(rows[2], rows[0]), _cross(rows[0], rows[1])]
        det = _dot(rows[0], cols[0])
        if det == 0.0:
            raise KinematicsError(f"arm angles {list(map(float, theta))} are singular")
        return cols, [b / det for b in scale]

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        """J = dp/dtheta (3, 3), m per rad."""
        cols, scale = self._columns(theta)
        return np.array([[cols[i][k] * scale[i] for i in range(3)] for k in range(3)])

    def torques(self, theta: np.ndarray, force: np.ndarray) -> np.ndarray:
        """Arm torques (3,) N m that render ``force`` (3,) N at the end-effector: J^T f."""
        cols, scale = self._columns(theta)
        f = tuple(float(v) for v in force)
        return np.array([_dot(cols[i], f) * scale[i] for i in range(3)])

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


def _dot(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float]:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
