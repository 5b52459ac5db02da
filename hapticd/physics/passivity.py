"""Time-domain passivity (Hannaford & Ryu 2002), per finger, along its actuated directions:
the observer and controller the tick's one call compiles in. Plain floats, no I/O.

The sign of the energy, the equations, the authority ramp and why the velocity is the
backward difference of the position: docs/analysis.md, "Passivity controller".
Units: m, m/s, N, N s/m, J, s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

DEPENDENT = 1e-9
"""A direction whose part orthogonal to the previous ones is shorter than this (of a unit
vector) adds nothing to the span of the actuated directions."""


@dataclass(frozen=True)
class PassivityParams:
    """The controller's limits: ``velocity_threshold`` (m/s), the actuated speed below which
    it does not act (full authority at twice it), and ``max_damping`` (N s/m); ValueError
    unless both are positive and finite."""

    velocity_threshold: float
    max_damping: float

    def __post_init__(self) -> None:
        for name, what in (
            ("velocity_threshold", "speed in m/s"),
            ("max_damping", "damping in N s/m"),
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a positive {what}, got {value!r}")


def authority(speed: float, threshold: float) -> float:
    """The controller's authority in [0, 1] at actuated speed ``speed`` (m/s): 0 up to
    ``threshold``, rising linearly to 1 at twice it."""
    return min(max(speed / threshold - 1.0, 0.0), 1.0)


def observe(energy: float, force: Sequence[float], dx: Sequence[float]) -> float:
    """The observer: E_pre(n) = E(n-1) - f(n) . dx (J), for ``energy`` E(n-1) (J), the
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
    finger's motion along its actuated directions ``dx_actuated`` = P_a dx (3,) m over a tick
    of ``dt`` s. The force to display is f(n) - alpha(n) P_a dx / dt."""
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
