"""The robust allocators' parameters (docs/allocation.md, "Parameters") and their error."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_TINY = 1e-300


class AllocationError(ValueError):
    """Malformed or non-finite allocation input."""


@dataclass(frozen=True)
class Robustness:
    """Parameters of the robust allocators; ValueError outside their ranges.

    eps: singular-value threshold (dimensionless) below which gains are damped;
    min_separation_m (m): closer contacts blend toward every opposing pair;
    contact_onset_n (N): a weaker contact joins the grasp gradually.
    """

    eps: float = 0.2
    min_separation_m: float = 0.005
    contact_onset_n: float = 0.05

    def __post_init__(self) -> None:
        ok = 0 < self.eps < 1 and 0 < self.min_separation_m < 1 and 0 <= self.contact_onset_n < 10
        if not ok:
            raise ValueError(f"invalid robustness parameters {self}")

    @property
    def length_scale_m(self) -> float:
        """Moment weighting length L: two contacts at min_separation_m give sigma = eps."""
        return self.min_separation_m / (math.sqrt(2.0) * self.eps)


DEFAULT_ROBUSTNESS = Robustness()


def contact_offsets(G: np.ndarray) -> np.ndarray:
    """Contact points relative to G's reference point, (p, 3) m, read off G's moment rows."""
    return np.stack((G[5, 1::3], G[3, 2::3], G[4, 0::3]), axis=1)  # [r]x = G's skew blocks
