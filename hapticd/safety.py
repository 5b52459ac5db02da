"""Safety between allocation and the devices: the last stage before a force leaves.

Every force passes ``SafetyChain.apply``: a non-finite value latches a fault and
zeroes every finger; a magnitude above the finger's limit (the smaller of the
device's and the profile's) is scaled down with its direction kept. A latched
fault keeps all forces at zero until ``reset``. Forces in N, shape (F, 3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Fault:
    """A latched fault: tick, time (s) and a human-readable cause."""

    tick: int
    t: float
    cause: str


class SafetyChain:
    """NaN/inf guard, magnitude clamp and fault latch for F fingers."""

    def __init__(self, limits_n: list[float]) -> None:
        if not limits_n or any(not (math.isfinite(v) and v > 0) for v in limits_n):
            raise ValueError(f"force limits must be positive and finite, got {limits_n}")
        self.limits = [float(v) for v in limits_n]
        self.fault: Fault | None = None
        self.clamped_ticks = 0
        self.output = np.zeros((len(limits_n), 3))

    @property
    def latched(self) -> bool:
        return self.fault is not None

    def trip(self, tick: int, t: float, cause: str) -> None:
        """Latch a fault (the first cause is kept) and zero the output."""
        if self.fault is None:
            self.fault = Fault(tick, t, cause)
        self.output[:] = 0.0

    def reset(self) -> None:
        self.fault = None
        self.output[:] = 0.0

    def apply(self, forces: np.ndarray, tick: int, t: float) -> np.ndarray:
        """Safe forces (F, 3) N for ``forces`` (F, 3) N; returns an internal buffer."""
        out = self.output
        if self.fault is not None:
            out[:] = 0.0
            return out
        if not np.all(np.isfinite(forces)):
            bad = [i for i in range(len(self.limits)) if not np.all(np.isfinite(forces[i]))]
            self.trip(tick, t, f"non-finite force for finger(s) {bad}")
            return out
        out[:] = forces
        clamped = False
        for i, limit in enumerate(self.limits):
            f = out[i]
            mag = math.hypot(f[0], f[1], f[2])
            if mag > limit:
                f *= limit / mag
                clamped = True
        if clamped:
            self.clamped_ticks += 1
        return out
