"""How many substeps a free object's step (``kernels.free_body_step``) needs."""

from __future__ import annotations

import math

from hapticd.physics.scene import SceneObject, Surface


def auto_substeps(
    obj: SceneObject, surfaces: list[Surface], finger_stiffness: float, n_fingers: int, dt: float
) -> int:
    """Substeps (1-64) that keep omega h and (damping / mass) h below 0.5 for a free object
    in a tick of ``dt`` s; ``finger_stiffness`` N/m.

    Every finger, and up to four of the object's vertices on the first surface (a box's
    face), count as springs and dampers in parallel: a conservative bound.
    """
    touching = min(4, len(obj.shape.vertices))
    k = n_fingers * finger_stiffness + sum(touching * s.material.stiffness for s in surfaces[:1])
    b = n_fingers * obj.material.damping + sum(touching * s.material.damping for s in surfaces[:1])
    rate = max(math.sqrt(k / obj.mass), b / obj.mass)
    return max(1, min(64, math.ceil(rate * dt / 0.5)))
