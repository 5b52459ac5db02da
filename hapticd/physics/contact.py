"""The convex polytope contact renders against (the contact itself is
``kernels.contact_step``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Polytope:
    """Convex polytope as half-spaces n . x <= d: unit outward normals (m, 3), offsets (m,)
    in m, and a centre (3,) m."""

    normals: np.ndarray
    offsets: np.ndarray
    center: np.ndarray

    def signed_distance(self, x: np.ndarray) -> float:
        """max_i (n_i . x - d_i): > 0 outside, < 0 inside (exact inside, a lower bound outside)."""
        return float(np.max(self.normals @ np.asarray(x, dtype=float) - self.offsets))
