"""The convex polytope god-object contact renders against: half-spaces n . x <= d.

The contact itself (proxy, first entry, sliding on up to three planes, the Gram systems)
is one function, hapticd.physics.kernels.contact_step: the Contact stage's part of the tick's one
call (hapticd.physics.kernels.tick_step).

Units: m. Unit outward normals n.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Polytope:
    """Convex polytope as half-spaces: normals (m, 3) unit, offsets (m,) in m, and a centre
    (3,) m."""

    normals: np.ndarray
    offsets: np.ndarray
    center: np.ndarray

    def signed_distance(self, x: np.ndarray) -> float:
        """max_i (n_i . x - d_i): > 0 outside, < 0 inside (exact inside, a lower bound outside)."""
        return float(np.max(self.normals @ np.asarray(x, dtype=float) - self.offsets))
