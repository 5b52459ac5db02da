"""How many substeps a free object's step (``kernels.free_body_step``) needs, and the
lightest mass a number of them integrates."""

from __future__ import annotations

import math

from hapticd.physics.scene import SceneObject, Surface

# The most substeps a tick's free-body step takes (each costs the whole object's step).
MAX_SUBSTEPS = 64
# The stability bound each substep of h s keeps: omega h and (damping / mass) h below it.
STEP_BOUND = 0.5


def _springs(
    obj: SceneObject, surfaces: list[Surface], finger_stiffness: float, n_fingers: int
) -> tuple[float, float]:
    """The stiffness (N/m) and damping (N s/m) acting on the object, a conservative bound:
    every finger, and up to four of the object's vertices on the first surface (a box's
    face), as springs and dampers in parallel."""
    touching = min(4, len(obj.shape.vertices))
    k = n_fingers * finger_stiffness + sum(touching * s.material.stiffness for s in surfaces[:1])
    b = n_fingers * obj.material.damping + sum(touching * s.material.damping for s in surfaces[:1])
    return k, b


def needed_substeps(
    obj: SceneObject, surfaces: list[Surface], finger_stiffness: float, n_fingers: int, dt: float
) -> float:
    """Substeps (unrounded; may exceed MAX_SUBSTEPS; inf for no mass) that keep omega h and
    (damping / mass) h below STEP_BOUND for a free object in a tick of ``dt`` s;
    ``finger_stiffness`` N/m."""
    if not obj.mass > 0.0:
        return math.inf
    k, b = _springs(obj, surfaces, finger_stiffness, n_fingers)
    rate = max(math.sqrt(k / obj.mass), b / obj.mass)  # a tiny mass: inf, never an error
    return rate * dt / STEP_BOUND


def lightest_mass(
    obj: SceneObject,
    surfaces: list[Surface],
    finger_stiffness: float,
    n_fingers: int,
    dt: float,
    substeps: int,
) -> float:
    """The smallest mass (kg) ``substeps`` substeps of a ``dt`` s tick integrate for the
    object's material and surfaces (``needed_substeps`` inverted)."""
    k, b = _springs(obj, surfaces, finger_stiffness, n_fingers)
    h = dt / (substeps * STEP_BOUND)
    return max(k * h * h, b * h)


def auto_substeps(
    obj: SceneObject, surfaces: list[Surface], finger_stiffness: float, n_fingers: int, dt: float
) -> int:
    """Substeps (1 to MAX_SUBSTEPS) for a free object in a tick of ``dt`` s: ``needed_substeps``
    rounded up, within those bounds."""
    n = needed_substeps(obj, surfaces, finger_stiffness, n_fingers, dt)
    return MAX_SUBSTEPS if not n <= MAX_SUBSTEPS else max(1, math.ceil(n))
