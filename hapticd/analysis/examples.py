"""The seed's two examples (Barbagli & Salisbury, section 4) as scenes for the pipeline.

- ``tilted_wall``: one point against a frictionless wall tilted by alpha, one
  actuator along the seed's y axis, two sensors (eqs. 10-13). The profile format
  has no tilted wall, so the scene is built here: an axis-aligned box whose top
  face is the wall (normal world +y) and the actuated direction tilted by alpha
  from that normal. That is the seed's geometry turned by -alpha about z: the
  seed's axes are ``ex``, ``ey`` in the world, the seed's coordinates
  (x, y) are generalized coordinates of the finger, x = origin + x ex + y ey,
  and matrices in them are the seed's (a rotation changes no symmetry, rank or
  work).
- ``rod``: two points pinching a static wall of half-thickness x_R, centre of
  the line between them fixed at the origin, generalized coordinates L (their
  distance, m) and alpha (the line's angle to x, rad); one actuator along the
  line (eqs. 14-18). The wall is the 50 mm cube of configs/grasp-stiffness.yaml
  with 8 mm fingertips (x_R = 25 + 8 mm for the fingertip centres), and each
  finger's actuated direction is the grasp line (the grasp frame's x axis).

Each example has the seed's closed forms beside it. The seed's lower-right entry
of eq. (16), k (L sin(2 alpha) / 2 - x_R cos(alpha)), is in N where a torque
derivative needs N m / rad; differentiating eq. (14) gives
k L (L cos(2 alpha) / 2 - x_R cos(alpha)), which ``rod_f_l`` returns and the
pipeline reproduces. Units: m, rad, N, N/m. Pure.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hapticd.allocation.actuation import Actuation
from hapticd.analysis.pipeline import Pipeline
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject

# -- single point on a tilted wall (seed section 4.1) -----------------------------------------


def wall_f_l(alpha: float, k: float) -> np.ndarray:
    """Seed eq. (11): the linearization F_L (2, 2) N/m of the wall's force in (x, y)."""
    s, c = math.sin(alpha), math.cos(alpha)
    return np.array([[-k * s * s, k * s * c], [k * s * c, -k * c * c]])


def wall_rendered(alpha: float, k: float) -> np.ndarray:
    """Seed eq. (12): M_A F_L M_S (2, 2) N/m with the actuator along y, two sensors."""
    s, c = math.sin(alpha), math.cos(alpha)
    return np.array([[0.0, 0.0], [k * s * c, -k * c * c]])


def wall_work(alpha: float, k: float, delta: float) -> float:
    """Seed eq. (13) with its stiffness: k delta^2 sin^2(alpha) / 2 (J), the rendered
    force's work around ``triangle``."""
    return k * delta * delta * math.sin(alpha) ** 2 / 2.0


@dataclass(frozen=True)
class TiltedWall:
    """The tilted-wall scene: ``pipeline`` (one finger, radius 0: a point), the wall's
    tilt ``alpha`` (rad) and stiffness ``k`` (N/m), the seed's axes ``ex``, ``ey`` (3,)
    and ``origin`` (3,) m (a point of the wall) in the world."""

    pipeline: Pipeline
    alpha: float
    k: float
    ex: np.ndarray
    ey: np.ndarray
    origin: np.ndarray

    def coords(self, q: np.ndarray) -> np.ndarray:
        """Finger position (1, 3) m for the seed's coordinates q = (x, y) m."""
        return (self.origin + q[0] * self.ex + q[1] * self.ey).reshape(1, 3)

    def inside(self, depth: float) -> np.ndarray:
        """Seed coordinates (2,) of the point ``depth`` m inside the wall below the origin."""
        s, c = math.sin(self.alpha), math.cos(self.alpha)
        return depth * np.array([s, -c])

    def triangle_q(self, delta: float, n: int = 40) -> np.ndarray:
        """The closed path (3 n + 1, 2) of the seed's Fig. 3 in the seed's coordinates (m):
        from the wall's origin ``delta`` along x (into the wall), along y back to the wall
        (delta tan(alpha)), and along the wall to the start; ``n`` steps per leg."""
        t = math.tan(self.alpha)
        corners = [np.array(c) for c in ((0.0, 0.0), (delta, 0.0), (delta, delta * t), (0.0, 0.0))]
        qs = [corners[0]]
        for a, b in itertools.pairwise(corners):
            qs += [a + (b - a) * (i / n) for i in range(1, n + 1)]
        return np.array(qs)

    def triangle(self, delta: float, n: int = 40) -> np.ndarray:
        """``triangle_q`` as finger positions (3 n + 1, 1, 3) m in the world."""
        return np.array([self.coords(q) for q in self.triangle_q(delta, n)])


def tilted_wall(
    alpha: float, k: float = 60.0, allocators: Sequence[str] | None = None
) -> TiltedWall:
    """The seed's single point on a wall tilted by ``alpha`` (rad), stiffness ``k`` N/m."""
    s, c = math.sin(alpha), math.cos(alpha)
    # The wall: the top face (y = 0) of a box much larger than any motion analysed.
    size = np.array([0.4, 0.2, 0.4])
    wall = SceneObject(
        ConvexShape.box(size), Material(k), np.array([0.0, -0.1, 0.0]), np.eye(3), fixed=True
    )
    ex = np.array([c, -s, 0.0])  # the seed's x axis: the wall's normal is -s ex + c ey = +y
    ey = np.array([s, c, 0.0])  # the seed's y axis: the one actuated direction
    pipe = Pipeline(
        Scene(wall, [], None),
        [0.0],
        Actuation([[tuple(ey)]], "world"),
        allocators=allocators,
        finger_names=["point"],
    )
    return TiltedWall(pipe, alpha, k, ex, ey, np.zeros(3))


# -- two points on a static rod (seed section 4.2) --------------------------------------------


def rod_forces(L: float, alpha: float, k: float, x_r: float) -> np.ndarray:
    """Seed eq. (14): (F_g N, tau N m) for distance L (m) and angle alpha (rad); zero
    outside contact (eq. 15)."""
    c, s = math.cos(alpha), math.sin(alpha)
    depth = x_r - L / 2.0 * c
    if depth <= 0.0:
        return np.zeros(2)
    return np.array([k * depth * c, -L * k * depth * s])


def rod_f_l(L: float, alpha: float, k: float, x_r: float) -> np.ndarray:
    """The derivative (2, 2) of eq. (14) in (L, alpha): eq. (16), with its lower-right
    entry derived again, k L (L cos(2 alpha) / 2 - x_R cos(alpha)) N m/rad (the seed
    prints k (L sin(2 alpha) / 2 - x_R cos(alpha)))."""
    c, s = math.cos(alpha), math.sin(alpha)
    off = k * (L * math.sin(2 * alpha) / 2.0 - x_r * s)
    return np.array(
        [[-k / 2.0 * c * c, off], [off, k * L * (L * math.cos(2 * alpha) / 2.0 - x_r * c)]]
    )


def rod_f_l_printed(L: float, alpha: float, k: float, x_r: float) -> np.ndarray:
    """Eq. (16) exactly as the seed prints it (lower-right entry in N, see the module)."""
    out = rod_f_l(L, alpha, k, x_r)
    out[1, 1] = k * (L * math.sin(2 * alpha) / 2.0 - x_r * math.cos(alpha))
    return out


def rod_rendered(L: float, alpha: float, k: float, x_r: float) -> np.ndarray:
    """Seed eq. (18): M_A F_L M_S (2, 2) with M_A = diag(1, 0) (only F_g rendered)."""
    out = rod_f_l(L, alpha, k, x_r)
    out[1] = 0.0
    return out


@dataclass(frozen=True)
class Rod:
    """The rod scene: ``pipeline`` (thumb and index), stiffness ``k`` (N/m) and the wall's
    face ``x_r`` (m) for the fingertip centres."""

    pipeline: Pipeline
    k: float
    x_r: float

    @staticmethod
    def coords(q: np.ndarray) -> np.ndarray:
        """Finger positions (2, 3) m for q = (L m, alpha rad): thumb at -L/2 (cos, sin, 0),
        index at +L/2 (cos, sin, 0)."""
        L, a = float(q[0]), float(q[1])
        u = np.array([math.cos(a), math.sin(a), 0.0])
        return np.array([-L / 2.0 * u, L / 2.0 * u])


def rod(
    k: float = 60.0,
    half_width: float = 0.025,
    radius: float = 0.008,
    allocators: Sequence[str] | None = None,
) -> Rod:
    """The seed's two points on a static wall: a fixed cube of half-width ``half_width``
    (m) and stiffness ``k`` (N/m), fingertips of ``radius`` (m), each actuated along the
    grasp line only."""
    cube = SceneObject(
        ConvexShape.box(np.full(3, 2.0 * half_width)),
        Material(k),
        np.zeros(3),
        np.eye(3),
        fixed=True,
    )
    pipe = Pipeline(
        Scene(cube, [], None),
        [radius, radius],
        Actuation([[(1.0, 0.0, 0.0)], [(-1.0, 0.0, 0.0)]], "grasp"),
        allocators=allocators,
        finger_names=["thumb", "index"],
    )
    return Rod(pipe, k, half_width + radius)
