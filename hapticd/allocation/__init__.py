"""Force allocation: contact forces ``lam`` onto the actuated directions ``M_a``.

Solves lam ~= M_a @ lam_a for the actuator forces lam_a. Shapes: G (6, 3p),
M_a (3p, r), lam (3p,), lam_a (r,); forces in N. ``allocate_many`` does the
same for a batch of N grasps (G (N, 6, 3p), lam (N, 3p), M_a per grasp or
shared), and ``allocate`` is it with N = 1 (``hapticd.allocation.batch``): the
closed forms of ``closed`` and the general path of ``general``, the functions the
servo loop's kernel compiles, or the seed's formulas of ``exact``. Every
allocator is linear, so ``lam`` may be the force on the object (the seed's
convention) or on the finger (hapticd's): flipping its sign flips lam_a.

Methods (docs/allocation.md): ``pinv``, ``if``, ``ef``, singularity-robust
versions of the seed's allocators (Meli & Prattichizzo): equal to the seed's
formulas where the problem is well-conditioned, finite, bounded and continuous
near and at singularities (every pseudoinverse filtered: a singular value s gets
the gain 1/s when s >= eps and s/eps^2 below); ``pinv_exact``, ``if_exact``,
``ef_exact``, the seed's formulas with numpy's pseudoinverse, for comparison;
``adaptive``: (1 - alpha) * if + alpha * ef, alpha in [0, 1] from the task
(``AdaptiveState``).
"""

from __future__ import annotations

import numpy as np

from hapticd.allocation.accuracy import Accuracy, accuracy
from hapticd.allocation.adaptive import AdaptiveState, smoothstep
from hapticd.allocation.batch import (
    EXACT_METHODS,
    METHODS,
    ROBUST_METHODS,
    allocate_many,
    check,
    solve,
)
from hapticd.allocation.closed import (
    adaptive_mix,
    one_contact,
    two_contact,
    two_contact_ef,
    two_contact_if,
    two_contact_pinv,
    two_contact_structure,
)
from hapticd.allocation.exact import ef_exact, if_exact, pinv_exact
from hapticd.allocation.robust import (
    DEFAULT_CONTACT_ONSET_N,
    DEFAULT_EPS,
    DEFAULT_MIN_SEPARATION_M,
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
    """Actuator forces lam_a (r,) N for contact forces ``lam`` (3p,) N with ``method``:
    ``allocate_many`` with a batch of one.

    ``alpha`` (0..1) is the external-force weight of ``adaptive``. ``fast``
    allows the closed form for two contacts with one direction each (equal to
    the general path to rounding). Raises AllocationError on an unknown method,
    mismatched shapes or NaN/inf input.
    """
    G = np.asarray(G, dtype=float)
    if G.ndim != 2:
        raise AllocationError(f"G must have shape (6, 3p), got {G.shape}")
    lam = np.asarray(lam, dtype=float).reshape(1, -1)
    G, M, lam, a = check(method, G[None], M_a, lam, alpha, one=True)
    if M.shape[-1] == 0 or G.shape[2] == 0:
        return np.zeros(M.shape[-1])
    return solve(method, G, M, lam, a, robust, fast)[0]


__all__ = [
    "DEFAULT_CONTACT_ONSET_N",
    "DEFAULT_EPS",
    "DEFAULT_MIN_SEPARATION_M",
    "DEFAULT_ROBUSTNESS",
    "EXACT_METHODS",
    "METHODS",
    "ROBUST_METHODS",
    "Accuracy",
    "AdaptiveState",
    "AllocationError",
    "Robustness",
    "accuracy",
    "adaptive_mix",
    "allocate",
    "allocate_many",
    "contact_offsets",
    "ef_exact",
    "if_exact",
    "one_contact",
    "pinv_exact",
    "smoothstep",
    "two_contact",
    "two_contact_ef",
    "two_contact_if",
    "two_contact_pinv",
    "two_contact_structure",
]
