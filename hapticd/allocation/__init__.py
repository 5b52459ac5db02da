"""Force allocation: contact forces lam (3p,) N onto the actuated directions M_a (3p, r).

``allocate`` and ``allocate_many`` (a batch) give the actuator forces lam_a (r,) N with
lam ~= M_a lam_a. Methods, robustness and speed: docs/allocation.md; conventions
(the sign of lam, G, M_a) and the seed's formulas: docs/math.md.
"""

from __future__ import annotations

import numpy as np

from hapticd.allocation.accuracy import accuracy
from hapticd.allocation.adaptive import AdaptiveState
from hapticd.allocation.batch import METHODS, ROBUST_METHODS, allocate_many, check, solve
from hapticd.allocation.closed import (
    one_contact,
    smoothstep,
    two_contact_ef,
    two_contact_if,
    two_contact_pinv,
    two_contact_structure,
)
from hapticd.allocation.exact import ef_exact, if_exact, pinv_exact
from hapticd.allocation.robust import (
    DEFAULT_ROBUSTNESS,
    AllocationError,
    Robustness,
    contact_offsets,
)


def allocate(
    method: str,
    G: np.ndarray,
    M_a: np.ndarray,
    lam: np.ndarray,
    *,
    robust: Robustness = DEFAULT_ROBUSTNESS,
    alpha: float = 0.0,
    fast: bool = True,
) -> np.ndarray:
    """Actuator forces lam_a (r,) N for contact forces ``lam`` (3p,) N: ``allocate_many``
    on one grasp, G (6, 3p), M_a (3p, r).

    ``alpha`` in [0, 1]: ``adaptive``'s external-force weight. ``fast`` False: the general
    path even where a closed form applies (they agree to rounding). Raises AllocationError
    on an unknown method, mismatched shapes or NaN/inf input.
    """
    G = np.asarray(G, dtype=float)
    if G.ndim != 2:
        raise AllocationError(f"G must have shape (6, 3p), got {G.shape}")
    lam = np.asarray(lam, dtype=float).reshape(1, -1)
    return solve(method, *check(method, G[None], M_a, lam, alpha, one=True), robust, fast)[0]


__all__ = [
    "DEFAULT_ROBUSTNESS",
    "METHODS",
    "ROBUST_METHODS",
    "AdaptiveState",
    "AllocationError",
    "Robustness",
    "accuracy",
    "allocate",
    "allocate_many",
    "contact_offsets",
    "ef_exact",
    "if_exact",
    "one_contact",
    "pinv_exact",
    "smoothstep",
    "two_contact_ef",
    "two_contact_if",
    "two_contact_pinv",
    "two_contact_structure",
]
