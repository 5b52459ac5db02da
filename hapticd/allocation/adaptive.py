"""The task-adaptive allocator's state: alpha, the weight of external forces, from the task."""

from __future__ import annotations

from dataclasses import dataclass

# -- the task-adaptive allocator's state ----------------------------------------------------


def smoothstep(x: float) -> float:
    """3x^2 - 2x^3 on [0, 1], clamped: a switch with zero slope at both ends."""
    x = 0.0 if x < 0.0 else (1.0 if x > 1.0 else x)
    return x * x * (3.0 - 2.0 * x)


@dataclass
class AdaptiveState:
    """External-force weight alpha of the ``adaptive`` allocator, following the task.

    The target is smoothstep((rho - ratio_low) / (ratio_high - ratio_low)) of the
    external ratio rho (0 while the object is supported); alpha follows it with
    a first-order lag of ``time_constant_s`` so that no switch is a jolt.
    """

    ratio_low: float = 0.2
    ratio_high: float = 0.6
    time_constant_s: float = 0.1
    alpha: float = 0.0

    def target(self, rho: float, supported: bool = False) -> float:
        if supported:
            return 0.0
        return smoothstep((rho - self.ratio_low) / (self.ratio_high - self.ratio_low))

    def update(self, rho: float, dt: float, supported: bool = False) -> float:
        """Advance alpha by ``dt`` (s) toward the target for ``rho``; returns alpha."""
        gain = 1.0 if self.time_constant_s <= 0 else min(1.0, dt / self.time_constant_s)
        self.alpha += gain * (self.target(rho, supported) - self.alpha)
        return self.alpha
