"""The Output stage (the contributions' sum into ``rendered_force``) and the Scene stage (the
object's state into the frame): their declarations and kernels.

Units: forces N; the object's state as free_body_step's (m, m/s, rad/s).
"""

from __future__ import annotations

import numpy as np

from hapticd.physics.tick.dynamics import STATE
from hapticd.physics.tick.layout import Declaration


def sum_step(
    allocated: np.ndarray,
    env_rendered: np.ndarray,
    damping_force: np.ndarray,
    surfaces: bool,
    passivity: bool,
    rendered: np.ndarray,
) -> None:
    """``rendered`` (F, 3) N: the contributions in the plan's order, the allocated force,
    the environment's (with ``surfaces``), passivity's (with ``passivity``)."""
    for i in range(rendered.shape[0]):
        for j in range(3):
            f = allocated[i, j]
            if surfaces:
                f = f + env_rendered[i, j]
            if passivity:
                f = f + damping_force[i, j]
            rendered[i, j] = f


def scene_step(obj_state: np.ndarray, record: np.ndarray, at: int) -> None:
    """The object's state (STATE,) into the frame's record from float ``at`` on (object_pos,
    object_vel, object_omega, object_rot)."""
    for k in range(STATE):
        record[at + k] = obj_state[k]


OUTPUT = Declaration(
    "output",
    writes=("rendered_force",),
    fields=("rendered_force",),
    flag="sum",
    helpers=("sum_step",),
)
SCENE = Declaration("scene", fields=("object_pos",), helpers=("scene_step",))
