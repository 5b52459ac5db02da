"""Force allocation: contact forces ``lam`` onto the actuated directions ``M_a``.

Solves lam ~= M_a @ lam_a for the actuator forces lam_a. Shapes: G (6, 3p),
M_a (3p, r), lam (3p,), lam_a (r,); forces in N. ``allocate_many`` does the
same for a batch of N grasps (G (N, 6, 3p), lam (N, 3p), M_a per grasp or
shared); both run the one definition of each method in ``hapticd.allocation.batch``
(``allocate`` with N = 1): the two-contact closed forms of ``closed`` and the general
path of ``general``, the same functions the servo loop's kernel compiles.
``lam`` may be the force on the object (the seed's convention) or on the
finger (hapticd's): every allocator is linear, so flipping its sign flips lam_a.

Methods (see docs/allocation.md):

- ``pinv``, ``if``, ``ef``: singularity-robust versions of the seed's
  allocators (Meli & Prattichizzo). Equal to the seed's formulas wherever the
  problem is well-conditioned (every singular value involved is 0 or >= eps,
  contacts are at least ``min_separation_m`` apart and, three or more, not
  nearly collinear); near and at
  singularities finite, bounded and continuous.
- ``pinv_exact``, ``if_exact``, ``ef_exact``: the seed's formulas with numpy's
  default pseudoinverse, for comparison. They blow up or jump at singularities.
- ``adaptive``: (1 - alpha) * if + alpha * ef, alpha in [0, 1] from the task
  (0 squeezing a supported object, 1 lifting it); see ``AdaptiveState``.

Robustness scheme: every pseudoinverse is a *filtered* one. A singular value
sigma gets the gain 1/sigma when sigma >= eps and sigma/eps^2 below (damped
least squares with the variable damping mu^2 = eps^2 - sigma^2, which vanishes
away from the singularity). The gain is continuous, zero at sigma = 0 and at
most 1/eps. Trade: below eps the allocation renders less than the exact
formula asks for (which there is unbounded), and two directions that are
nearly dependent share the force smoothly instead of opposing each other.

IF uses the projector form lam_a = x1 + P (M_a P)^+ (lam - M_a x1),
x1 = B^+ P_int lam, B = P_int M_a, P = I - B^+ B, which is continuous when
B changes rank; P_int, the projector onto the internal forces N(G), is also
softened as two contacts approach each other (N(G) grows from the grasp line
to all opposing pairs when they coincide).
"""

from __future__ import annotations

import numpy as np

from hapticd import params
from hapticd.allocation.accuracy import (
    Accuracy,
    accuracy,
    one_contact_accuracy,
    two_contact_accuracy,
)
from hapticd.allocation.adaptive import AdaptiveState, external_ratio, smoothstep
from hapticd.allocation.batch import (
    allocate_many,
    filtered_pinv,
    soft_internal_projector,
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
    filtered_gain,
)

# Declared with the other settable parameters (the control client reads them too).
METHODS: tuple[str, ...] = tuple(params.ALLOCATORS)
ROBUST_METHODS: tuple[str, ...] = ("pinv", "if", "ef", "adaptive")
EXACT_METHODS: tuple[str, ...] = ("pinv_exact", "if_exact", "ef_exact")

# -- public API ---------------------------------------------------------------------------


def _check(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> None:
    if G.ndim != 2 or G.shape[0] != 6 or G.shape[1] % 3:
        raise AllocationError(f"G must have shape (6, 3p), got {G.shape}")
    n = G.shape[1]
    if M_a.ndim != 2 or M_a.shape[0] != n:
        raise AllocationError(f"M_a must have shape ({n}, r) to match G {G.shape}, got {M_a.shape}")
    if lam.shape != (n,):
        raise AllocationError(f"lam must have shape ({n},) to match G {G.shape}, got {lam.shape}")
    for name, arr in (("G", G), ("M_a", M_a), ("lam", lam)):
        if not np.all(np.isfinite(arr)):
            raise AllocationError(f"{name} contains NaN or inf; refusing to compute a force")


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
    """Actuator forces lam_a (r,) N for contact forces ``lam`` (3p,) N with ``method``.

    ``alpha`` (0..1) is the external-force weight of ``adaptive``. ``fast``
    allows the closed form for two contacts with one direction each (equal to
    the general path to rounding). Raises AllocationError on an unknown method,
    mismatched shapes or NaN/inf input.
    """
    if method not in METHODS:
        raise AllocationError(f"unknown allocator {method!r}; expected one of {list(METHODS)}")
    G = np.asarray(G, dtype=float)
    M_a = np.asarray(M_a, dtype=float)
    lam = np.asarray(lam, dtype=float).reshape(-1)
    _check(G, M_a, lam)
    if M_a.shape[1] == 0 or G.shape[1] == 0:
        return np.zeros(M_a.shape[1])
    a = np.array([alpha], dtype=float)
    if method == "adaptive" and not (0.0 <= alpha <= 1.0):
        raise AllocationError(f"adaptive alpha must be in [0, 1], got {alpha}")
    return solve(method, G[None], M_a, lam[None], a, robust, fast)[0]


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
    "external_ratio",
    "filtered_gain",
    "filtered_pinv",
    "if_exact",
    "one_contact",
    "one_contact_accuracy",
    "pinv_exact",
    "smoothstep",
    "soft_internal_projector",
    "two_contact",
    "two_contact_accuracy",
    "two_contact_ef",
    "two_contact_if",
    "two_contact_pinv",
    "two_contact_structure",
]
