"""Tikhonov-regularised least squares as a hapticd allocator (a lab's own, by entry point).

lam_a = argmin |M_a lam_a - lam|^2 + mu^2 |lam_a|^2 = (M_a^T M_a + mu^2 I)^-1 M_a^T lam:
the contact forces rendered as closely as the actuated directions allow, the actuator
forces kept small where two directions nearly coincide (the damping mu bounds the gain by
1 / (2 mu)). Unlike the seed's allocators it ignores the grasp matrix G: it matches each
contact force, not the object's wrench.

Written in the Python numba compiles (numpy arrays and loops, np.linalg.solve): hapticd
compiles it into the tick.
"""

from __future__ import annotations

import numpy as np

# The damping (dimensionless: M_a's columns are unit directions); the gain stays below
# 1 / (2 MU) = 50.
MU = 0.01


def tikhonov(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Least squares on each contact's force, damped by MU: G (6, 3p), M_a (3p, r), lam
    (3p,) N -> lam_a (r,) N."""
    if not (np.all(np.isfinite(lam)) and np.all(np.isfinite(M_a))):
        # The tick never passes one (it refuses a non-finite contact first), but an
        # allocator called on its own refuses it too: a force from NaN is no force.
        raise ValueError("non-finite lam or M_a")
    r = M_a.shape[1]
    A = M_a.T @ M_a
    for i in range(r):
        A[i, i] += MU * MU
    return np.linalg.solve(A, M_a.T @ lam)


# It is linear in lam: ``hapticd allocators check tikhonov`` tests that too.
tikhonov.linear = True  # type: ignore[attr-defined]
