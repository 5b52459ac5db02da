"""Force allocation: contact forces ``lam`` onto the actuated directions ``M_a``.

Solves lam ~= M_a @ lam_a for the actuator forces lam_a with one of the seed's
(Meli & Prattichizzo) allocators:

- ``pinv``: lam_a = M_a^# lam, least squares over all of lam;
- ``if``  : internal forces first (two-level task priority on N(G), then the rest);
- ``ef``  : external forces, lam_a = (G M_a)^# G lam.

Shapes: G (6, 3p), M_a (3p, r), lam (3p,), lam_a (r,). Forces in N.
``lam`` may be either the force on the object or on the finger: every allocator
is linear, so flipping its sign flips lam_a.

These are the seed's exact formulas with numpy's default pseudoinverse; see
docs/math.md for their singularities.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hapticd.grasp import null_space_basis

METHODS: tuple[str, ...] = ("pinv", "if", "ef")


class AllocationError(ValueError):
    """Raised for malformed or non-finite allocation inputs."""


def _check(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> None:
    if G.ndim != 2 or G.shape[0] != 6:
        raise AllocationError(f"G must have shape (6, 3p), got {G.shape}")
    n = G.shape[1]
    if M_a.ndim != 2 or M_a.shape[0] != n:
        raise AllocationError(f"M_a must have shape ({n}, r) to match G {G.shape}, got {M_a.shape}")
    if lam.shape != (n,):
        raise AllocationError(f"lam must have shape ({n},) to match G {G.shape}, got {lam.shape}")
    for name, arr in (("G", G), ("M_a", M_a), ("lam", lam)):
        if not np.all(np.isfinite(arr)):
            raise AllocationError(f"{name} contains NaN or inf; refusing to compute a force")


def alloc_pinv(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Seed eq. (2): lam_a = M_a^# lam (G unused)."""
    return np.linalg.pinv(M_a) @ lam


def alloc_if(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Seed's IF algorithm: internal forces exactly where possible, then least squares.

    lam_a = B^# N_G^T lam + N_B (M_a N_B)^# (I - M_a B^# N_G^T) lam, B = N_G^T M_a.
    """
    N_G = null_space_basis(G)
    B = N_G.T @ M_a
    B_pinv = np.linalg.pinv(B) if B.size else np.zeros((M_a.shape[1], 0))
    first = B_pinv @ (N_G.T @ lam)
    N_B = null_space_basis(B) if B.size else np.eye(M_a.shape[1])
    if N_B.shape[1] == 0:
        return first
    rest = lam - M_a @ first
    return first + N_B @ (np.linalg.pinv(M_a @ N_B) @ rest)


def alloc_ef(G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Seed's EF algorithm: lam_a = (G M_a)^# G lam."""
    return np.linalg.pinv(G @ M_a) @ (G @ lam)


_DISPATCH: dict[str, Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]] = {
    "pinv": alloc_pinv,
    "if": alloc_if,
    "ef": alloc_ef,
}


def allocate(method: str, G: np.ndarray, M_a: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Actuator forces lam_a (r,) for contact forces ``lam`` (3p,) with ``method``.

    Raises AllocationError on an unknown method, mismatched shapes or NaN/inf input.
    """
    fn = _DISPATCH.get(method)
    if fn is None:
        raise AllocationError(f"unknown allocator {method!r}; expected one of {list(METHODS)}")
    G = np.asarray(G, dtype=float)
    M_a = np.asarray(M_a, dtype=float)
    lam = np.asarray(lam, dtype=float).reshape(-1)
    _check(G, M_a, lam)
    if M_a.shape[1] == 0:
        return np.zeros(0)
    return fn(G, M_a, lam)
