"""The task-adaptive allocator's state: alpha, the weight of external forces, from the task."""

from __future__ import annotations

from dataclasses import dataclass

# -- the task-adaptive allocator's state ----------------------------------------------------


def smoothstep(x: float) -> float:
    """3x^2 - 2x^3 on [0, 1], clamped: a switch with zero slope at both ends."""
    x = 0.0 if x < 0.0 else (1.0 if x > 1.0 else x)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True)
class AdaptiveState:
    """External-force weight alpha of the ``adaptive`` allocator, following the task.

    The target is smoothstep((rho - ratio_low) / (ratio_high - ratio_low)) of the
    external ratio rho; alpha (its start) follows it with a first-order lag of
    ``time_constant_s`` so that no switch is a jolt. The allocation kernel moves it
    each tick (``hapticd.physics.kernels._task_alpha``; ``ContactAllocator.alpha``).
    """

    ratio_low: float = 0.2
    ratio_high: float = 0.6
    time_constant_s: float = 0.1
    alpha: float = 0.0
