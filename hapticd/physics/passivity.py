"""Time-domain passivity (Hannaford & Ryu 2002), per finger, along its actuated directions.

With full sensing and partial actuation the displayed stiffness M_A F_L M_S is
not symmetric, so a finger moving around a closed loop can gain energy from
the display (Barbagli & Salisbury). A passivity observer counts the energy
that went through each finger's port; a passivity controller adds the least
damping along that finger's actuated directions that keeps it from going
negative.

Sign: the observed energy E (J) is the energy the display has **absorbed**
from the finger since the stage started: positive, the display has taken in
(stored or dissipated) energy; negative, it has generated energy (it felt
active). With f (3,) N the force the display applies to the finger and
dx = x(n) - x(n-1) (3,) m the finger's motion into tick n (v(n) = dx / T the
backward-difference velocity, T s the tick period):

    E_pre(n) = E(n-1) - f(n) . v(n) T                   (Hannaford & Ryu's observer)
    alpha(n) = -E_pre(n) / (T |P_a v(n)|^2)  if E_pre(n) < 0, else 0,
               clamped to [0, w alpha_max]              (the controller, N s/m)
    f_out(n) = f(n) - alpha(n) P_a v(n)                 (damping along the actuated directions)
    E(n)     = E_pre(n) + T alpha(n) |P_a v(n)|^2 = E(n-1) - f_out(n) . v(n) T

P_a is the orthogonal projector onto the finger's actuated directions, so the
device can render the damping force. Hannaford & Ryu book the controller's
dissipation one tick later (their T alpha(n-1) v(n-1)^2); here the controller's
output is known before it is sent, so E(n) already holds it: the same sum.

The authority w ramps from 0 at ``velocity_threshold`` to 1 at twice it, in
|P_a v|: below the threshold the controller does not act (alpha would grow as
1 / |v|), and the damping force alpha |P_a v| <= w alpha_max |P_a v| is a
continuous function of the velocity, so crossing the threshold makes no jump
(no chatter). Energy that passes while the controller may not act (below the
threshold, or beyond ``max_damping``) stays in E as a deficit, which the
controller pays back from later motion.

v is the backward difference of the finger's position, not the device's own
velocity estimate: paired with f(n), it makes the observed energy of a
conservative rendering with a convex potential U (a spring on a face, any
fully actuated frictionless contact on one face) at least U(x(n)) - U(x(0))
(the gradient inequality of a convex function: grad U(x_n) . (x_n - x_(n-1)) >=
U(x_n) - U(x_(n-1))), never negative from outside contact, so the controller
provably leaves such a rendering alone. An instantaneous velocity would pair
with f(n) with an error of order T^2 k |v|^2 of either sign.

Units: m, m/s, N, N s/m, J, s. Pure: plain floats, no I/O. ``observe``, ``control`` and
``authority`` are compiled into the tick's one call (hapticd.physics.kernels.tick_step).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

DEPENDENT = 1e-9
"""A direction whose part orthogonal to the previous ones is shorter than this (of a unit
vector) adds nothing to the span."""


@dataclass(frozen=True)
class PassivityParams:
    """The controller's limits: ``velocity_threshold`` (m/s), the speed along the actuated
    directions below which it does not act (full authority at twice it), and
    ``max_damping`` (N s/m), the most damping it adds."""

    velocity_threshold: float
    max_damping: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.velocity_threshold) and self.velocity_threshold > 0.0):
            raise ValueError(
                "velocity_threshold must be a positive speed in m/s, "
                f"got {self.velocity_threshold!r}"
            )
        if not (math.isfinite(self.max_damping) and self.max_damping > 0.0):
            raise ValueError(
                f"max_damping must be a positive damping in N s/m, got {self.max_damping!r}"
            )


def authority(speed: float, threshold: float) -> float:
    """The controller's authority in [0, 1] at actuated speed ``speed`` (m/s): 0 up to
    ``threshold``, rising linearly to 1 at twice it."""
    return min(max(speed / threshold - 1.0, 0.0), 1.0)


def observe(energy: float, force: Sequence[float], dx: Sequence[float]) -> float:
    """The observer: E_pre(n) = E(n-1) - f(n) . v(n) T (J), for ``energy`` E(n-1) (J), the
    rendered force ``force`` f(n) (3,) N on the finger and its motion ``dx`` = x(n) - x(n-1)
    (3,) m. Non-finite input gives a non-finite result (``control`` then adds nothing)."""
    return energy - (force[0] * dx[0] + force[1] * dx[1] + force[2] * dx[2])


def control(
    observed: float,
    dx_actuated: Sequence[float],
    dt: float,
    velocity_threshold: float,
    max_damping: float,
) -> tuple[float, float]:
    """The controller: (E(n) J, alpha(n) N s/m) for the observed energy E_pre(n) (J) and the
    finger's motion projected onto its actuated directions, ``dx_actuated`` = P_a dx (3,) m,
    over a tick of ``dt`` s, with PassivityParams' limits. The force to display is
    f(n) - alpha(n) P_a dx / T."""
    if not observed < 0.0:  # also for NaN: nothing to pay back, or nothing sound to pay
        return observed, 0.0
    ua2 = dx_actuated[0] ** 2 + dx_actuated[1] ** 2 + dx_actuated[2] ** 2  # |P_a v|^2 T^2
    w = authority(math.sqrt(ua2) / dt, velocity_threshold)  # 0 for NaN too
    if not w > 0.0:
        return observed, 0.0
    # T alpha |P_a v|^2 = alpha ua2 / T: the damping's dissipation over the tick.
    need = -observed * dt / ua2
    cap = w * max_damping
    if need <= cap:
        return 0.0, need  # exactly what brings E back to zero
    return observed + cap * ua2 / dt, cap
