"""The robust allocators' parameters and their error.

The general path itself (filtered pseudoinverses, the soft internal projector) is
``hapticd.allocation.general``; the closed forms are ``hapticd.allocation.closed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEFAULT_EPS = 0.2
DEFAULT_MIN_SEPARATION_M = 0.005
DEFAULT_CONTACT_ONSET_N = 0.05
_TINY = 1e-300


class AllocationError(ValueError):
    """Raised for malformed or non-finite allocation inputs."""


@dataclass(frozen=True)
class Robustness:
    """Parameters of the robust allocators.

    eps: singular-value threshold (dimensionless: directions are unit vectors,
    moments are in N m per N); below it pseudoinverse gains are damped.
    min_separation_m: contacts closer than this (m) blend the internal subspace
    toward every opposing pair of forces.
    contact_onset_n: a contact whose force is below this (N) joins the grasp
    gradually (the renderer blends the allocations with and without it).
    """

    eps: float = DEFAULT_EPS
    min_separation_m: float = DEFAULT_MIN_SEPARATION_M
    contact_onset_n: float = DEFAULT_CONTACT_ONSET_N

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
    p = G.shape[1] // 3
    out = np.empty((p, 3))
    for i in range(p):
        S = G[3:6, 3 * i : 3 * i + 3]
        out[i] = (S[2, 1], S[0, 2], S[1, 0])
    return out
