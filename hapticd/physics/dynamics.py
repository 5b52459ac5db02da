"""Rigid-body dynamics of a free object: how many substeps its step needs.

The step itself is hapticd.physics.kernels.free_body_step, in the tick's one call (the Dynamics
stage's physics: the fingers as springs moving with the object, gravity, the ground's
and walls' penalty spring-damper with Coulomb friction at the object's vertices, in
``substeps`` semi-implicit Euler steps). tests/dynamics_oracle.py is the same model in
numpy, written independently: the tests' cross-check.
"""

from __future__ import annotations

import math

from hapticd.physics.scene import SceneObject, Surface


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
