"""The task-adaptive allocator's parameters (docs/allocation.md, "The task-adaptive allocator")."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class AdaptiveState:
    """``adaptive``'s external-force weight alpha (its start, 0..1) and how it follows the
    task: toward smoothstep((rho - ratio_low) / (ratio_high - ratio_low)) of the external
    ratio rho with a first-order lag of ``time_constant_s`` (s), so no switch is a jolt."""

    ratio_low: float = 0.2
    ratio_high: float = 0.6
    time_constant_s: float = 0.1
    alpha: float = 0.0
