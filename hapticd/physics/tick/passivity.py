"""The Passivity stage: a time-domain passivity observer and controller on each finger
(hapticd.physics.passivity's, after Hannaford & Ryu), whose damping acts along the
finger's actuated directions. Its declaration, its parameters' packing (``pack``) and its
kernel (``passivity_step``).

Units: positions m, forces N, energy J, damping N s/m, times s.
"""

from __future__ import annotations

import numpy as np

from hapticd.physics.passivity import authority, control, observe
from hapticd.physics.tick.environment import _span_project
from hapticd.physics.tick.layout import Declaration

# The stage's params: velocity threshold (m/s), most damping (N s/m), the tick's period (s)
PARAMS = ("threshold", "most", "dt")
PASSIVITY_PARAMS = len(PARAMS)
# The stage's carried state per finger: its observed energy (J), its position on the last
# tick (3, m) and 1.0 once it has one (the first tick sees no motion).
PASSIVITY_STATE = 5


def passivity_step(
    device_pos: np.ndarray,
    allocated: np.ndarray,
    env_rendered: np.ndarray,
    surfaces: bool,
    directions: np.ndarray,
    counts: np.ndarray,
    ax: tuple[float, ...],
    params: np.ndarray,
    passive: np.ndarray,
    damping_force: np.ndarray,
    energy: np.ndarray,
    damping: np.ndarray,
) -> None:
    """The passivity stage (hapticd.physics.passivity's observer and controller) on every finger:
    observes the energy of the force before it (the allocated force, plus the environment's
    with ``surfaces``) over the finger's motion since the last tick, and writes the damping
    force along the finger's actuated directions, the energy and the damping (N s/m).
    ``passive`` (F, PASSIVITY_STATE) is its carried state; ``params`` PASSIVITY_PARAMS."""
    threshold, most, dt = params[0], params[1], params[2]
    start = 0
    for i in range(damping_force.shape[0]):
        c = int(counts[i])
        x0, x1, x2 = device_pos[i, 0], device_pos[i, 1], device_pos[i, 2]
        d0 = d1 = d2 = 0.0
        if passive[i, 4] != 0.0:  # the first tick sees no motion
            d0, d1, d2 = x0 - passive[i, 1], x1 - passive[i, 2], x2 - passive[i, 3]
        passive[i, 1], passive[i, 2], passive[i, 3], passive[i, 4] = x0, x1, x2, 1.0
        f0, f1, f2 = allocated[i, 0], allocated[i, 1], allocated[i, 2]
        if surfaces:
            f0, f1, f2 = f0 + env_rendered[i, 0], f1 + env_rendered[i, 1], f2 + env_rendered[i, 2]
        e = observe(passive[i, 0], (f0, f1, f2), (d0, d1, d2))
        alpha = 0.0
        damping_force[i, 0], damping_force[i, 1], damping_force[i, 2] = 0.0, 0.0, 0.0
        if e < 0.0:  # only then the controller needs the actuated motion
            u = _span_project(directions, start, c, ax, d0, d1, d2)
            e, alpha = control(e, u, dt, threshold, most)
            if alpha > 0.0:
                g = alpha / dt  # the damping force is -alpha P_a v, v = dx / T
                damping_force[i, 0], damping_force[i, 1] = -(g * u[0]), -(g * u[1])
                damping_force[i, 2] = -(g * u[2])
        elif not e >= 0.0:  # NaN: a non-finite position or force; keep the last energy
            e = passive[i, 0]
        passive[i, 0] = energy[i] = e
        damping[i] = alpha
        start += c


DECLARATION = Declaration(
    "passivity",
    writes=("passivity_force", "passivity_energy", "passivity_damping"),
    fields=("passivity_force", "passivity_energy", "passivity_damping"),
    state=(("passive", lambda n, d: (n, PASSIVITY_STATE)),),
    params=PARAMS,
    flag="passivity",
    helpers=("passivity_step", observe, control, authority),
)
