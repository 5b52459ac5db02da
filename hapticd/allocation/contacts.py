"""One tick's allocation for F fingertips: which contacts, which definition, contact onset.

``ContactAllocator.allocate`` takes the frame's arrays (which fingers touch, where
the devices are, the contact points in m and full contact forces in N, on the
finger) and writes lam_a (r,) N and M_a lam_a per finger, returning the accuracy of
the result. With one actuated direction per finger and a robust method, the kernel
``hapticd.kernels.allocation_step`` (compiled, or the same function uncompiled)
takes one or two contacts: the closed forms of ``hapticd.allocation.closed``.
Everything else (three or more contacts, several directions on a finger, the
seed's exact formulas) runs ``hapticd.allocation.allocate``, the batch definition
with N = 1. Both blend a contact being made or broken into the grasp gradually.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from hapticd import kernels
from hapticd.actuation import Actuation
from hapticd.allocation import allocate
from hapticd.allocation.accuracy import accuracy
from hapticd.allocation.adaptive import AdaptiveState, external_ratio, smoothstep
from hapticd.allocation.batch import soft_internal_projector
from hapticd.allocation.robust import AllocationError, Robustness
from hapticd.grasp import grasp_matrix

V3 = tuple[float, float, float]


def _norm(v: V3) -> float:
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


class ContactAllocator:
    """Allocates contact forces onto ``actuation``'s directions with ``method``.

    Holds the adaptive allocator's state (alpha follows the task over ticks of
    ``dt`` s) and the allocation kernel: ``kernel`` is the compiled
    ``allocation_step`` (hapticd.jit) or, set to None, the same function uncompiled.
    """

    def __init__(
        self,
        actuation: Actuation,
        method: str,
        robust: Robustness,
        adaptive: AdaptiveState,
        dt: float,
        kernel: Callable[..., int] | None = None,
    ) -> None:
        self.actuation = actuation
        self.method = method
        self.robust = robust
        self.adaptive = adaptive
        self.dt = dt
        self.alpha = 0.0
        self.kernel = kernel
        self.accuracy = np.zeros(kernels.ACCURACY)  # the last tick's (N, N, N, 1)
        self._params = np.zeros(kernels.ALLOCATION_PARAMS)
        self._local = np.zeros((actuation.n_fingers, 3))  # the kernel's directions
        self._local_for: tuple[Actuation, Robustness] | None = None

    @property
    def kernel(self) -> Callable[..., int]:
        """hapticd.kernels.allocation_step, compiled or not."""
        return self._kernel

    @kernel.setter
    def kernel(self, fn: Callable[..., int] | None) -> None:
        self._kernel = kernels.uncompiled("allocation_step") if fn is None else fn

    def allocate(
        self,
        in_contact: np.ndarray,
        device_pos: np.ndarray,
        points: np.ndarray,
        forces: np.ndarray,
        center: np.ndarray,
        lam_a: np.ndarray,
        rendered: np.ndarray,
    ) -> np.ndarray:
        """Write lam_a (r,) N and ``rendered`` (F, 3) N, M_a lam_a per finger (zero out of
        contact), and return the accuracy (internal, external, total, amplification).

        ``in_contact`` (F,) u1, ``device_pos`` (F, 3) m (the grasp frame follows fingers 0
        and 1), ``points`` (F, 3) m and ``forces`` (F, 3) N per finger, ``center`` (3,) m
        the grasp's reference point; C-contiguous float64 (the kernel's types). Updates
        ``alpha`` of the adaptive allocator. Raises AllocationError on non-finite contact
        geometry or forces, or a non-finite result.
        """
        tick = (in_contact, device_pos, points, forces, center, lam_a, rendered)
        if self.method != "adaptive":
            return self._allocate(*tick)
        # A refused tick, or forces whose task ratio overflows (inf / inf), leaves alpha as
        # it was: the allocator's state stays that of the last good tick.
        before = self.alpha, self.adaptive.alpha
        rho = self._external_ratio(in_contact, points, forces, center)
        if math.isfinite(rho):
            self.alpha = self.adaptive.update(rho, self.dt)
        try:
            return self._allocate(*tick)
        except AllocationError:
            self.alpha, self.adaptive.alpha = before
            raise

    def _allocate(self, *tick: np.ndarray) -> np.ndarray:
        """``allocate`` (its arguments: ``tick``) with alpha as it is now."""
        in_contact, device_pos, points, forces, center, lam_a, rendered = tick
        method = self.method
        if self._kernel_takes():
            params = self._params
            params[0] = kernels.ALLOCATION_METHODS.index(method)
            params[5:8] = center
            params[8] = self.alpha
            outcome = self._kernel(
                in_contact, device_pos, points, forces, self._local, params, lam_a, rendered,
                self.accuracy,
            )  # fmt: skip
            if outcome == kernels.ALLOCATED:
                return self.accuracy
            if outcome == kernels.NON_FINITE_INPUT:
                raise AllocationError("non-finite contact geometry or force; refusing to allocate")
            if outcome == kernels.NON_FINITE_OUTPUT:
                raise AllocationError(f"allocator {method!r} produced a non-finite force")
        with np.errstate(over="ignore"):  # finite forces whose residuals overflow: inf
            self._general(*tick)
        return self.accuracy

    def replay(
        self,
        in_contact: np.ndarray,
        device_pos: np.ndarray,
        points: np.ndarray,
        forces: np.ndarray,
        centers: np.ndarray,
    ) -> np.ndarray:
        """lam_a (N, r) N over N recorded ticks, tick by tick as the loop's Allocation stage
        allocates them: the same per-tick code (contact onset, the adaptive allocator's
        alpha following the task from its value now), so a recording's allocation is the
        loop's. ``in_contact`` (N, F), ``device_pos``, ``points`` (m) and ``forces`` (N)
        (N, F, 3) are the frame's fields per tick; ``centers`` (N, 3) m the grasp's
        reference point the tick allocated about (the object's position before the tick's
        dynamics moved it)."""
        touching = np.ascontiguousarray(in_contact, dtype=np.uint8)
        pos, pts, lam, ctr = (
            np.ascontiguousarray(a, dtype=float) for a in (device_pos, points, forces, centers)
        )
        out = np.zeros((len(touching), self.actuation.n_actuators))
        rendered = np.zeros((self.actuation.n_fingers, 3))
        for k in range(len(touching)):
            self.allocate(touching[k], pos[k], pts[k], lam[k], ctr[k], out[k], rendered)
        return out

    def kernel_inputs(self) -> tuple[np.ndarray, np.ndarray] | None:
        """allocation_step's ``local`` directions (F, 3) and ``params`` for the allocator as
        it is now (the object's position in params[5:8] is the caller's), or None when the
        kernel does not take it, or takes it only after ``allocate`` has moved adaptive's
        alpha (whose task ratio reads this tick's contact forces)."""
        if self.method == "adaptive" or not self._kernel_takes():
            return None
        self._params[0] = kernels.ALLOCATION_METHODS.index(self.method)
        self._params[8] = self.alpha
        return self._local, self._params

    def _kernel_takes(self) -> bool:
        """True if the kernel takes this method and actuation (one direction per finger);
        its directions and robustness parameters follow the actuation's and ours."""
        act, rb = self.actuation, self.robust
        if self.method not in kernels.ALLOCATION_METHODS:
            return False
        made_for = self._local_for
        if made_for is None or made_for[0] is not act or made_for[1] is not rb:
            if any(c != 1 for c in act.counts):
                return False
            self._local = np.array([ds[0] for ds in act.local], dtype=float).reshape(-1, 3)
            grasp = 1.0 if act.frame == "grasp" else 0.0
            self._params[1:5] = (rb.eps, rb.min_separation_m, rb.contact_onset_n, grasp)
            self._local_for = (act, rb)
        return True

    def _general(self, *tick: np.ndarray) -> None:
        """``allocate`` (its arguments: ``tick``) for what the kernel does not take:
        hapticd.allocation.allocate."""
        in_contact, device_pos, points, forces, center, lam_a, rendered = tick
        contacts = np.flatnonzero(in_contact).tolist()
        lam_a.fill(0.0)
        rendered.fill(0.0)
        self.accuracy.fill(0.0)
        if not contacts:
            return
        act = self.actuation
        world = act.world_directions(device_pos.tolist())
        M, cols = act.submatrix(world, contacts)
        geometry = (points[contacts], forces[contacts], center, M)
        if not all(np.all(np.isfinite(a)) for a in geometry):
            raise AllocationError("non-finite contact geometry or force; refusing to allocate")
        x, G, lam = self._solve(contacts, world, points, forces, center)
        onset = self.robust.contact_onset_n
        if len(contacts) >= 2 and onset > 0.0:
            # A contact that is just being made or broken joins the grasp gradually: without
            # this, the grasp matrix (and IF's squeeze) would jump when it appears or leaves.
            norms = np.linalg.norm(forces[contacts], axis=1)
            weakest = int(np.argmin(norms))
            beta = smoothstep(float(norms[weakest]) / onset)
            if beta < 1.0:
                rest = contacts[:weakest] + contacts[weakest + 1 :]
                x = beta * x + (1.0 - beta) * self._solve(rest, world, points, forces, center)[0]
        if not np.all(np.isfinite(x)):
            raise AllocationError(f"allocator {self.method!r} produced a non-finite force")
        lam_a[...] = x
        rendered[contacts] = (M @ x[cols]).reshape(-1, 3)
        a = accuracy(G, M, lam, x[cols])
        self.accuracy[:] = (a.internal, a.external, a.total, a.amplification)

    def _solve(
        self,
        contacts: list[int],
        world: list[list[V3]],
        points: np.ndarray,
        forces: np.ndarray,
        center: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """lam_a over all r actuators (zero for fingers not in ``contacts``), and the
        contacts' G (6, 3p) and lam (3p,) N."""
        act = self.actuation
        out = np.zeros(act.n_actuators)
        M, cols = act.submatrix(world, contacts)
        G = grasp_matrix(points[contacts], center)
        lam = forces[contacts].reshape(-1)
        if cols:
            out[cols] = allocate(self.method, G, M, lam, robust=self.robust, alpha=self.alpha)
        return out, G, lam

    def _external_ratio(
        self, in_contact: np.ndarray, points: np.ndarray, forces: np.ndarray, center: np.ndarray
    ) -> float:
        """The adaptive allocator's task state: |net force| / (|net force| + squeeze)."""
        contacts = [i for i, on in enumerate(in_contact.tolist()) if on]
        if not contacts:
            return 0.0
        pts, lam = points.tolist(), forces.tolist()
        net = [sum(lam[i][k] for i in contacts) for k in range(3)]
        if len(contacts) == 1:
            squeeze = 0.0
        elif len(contacts) == 2:
            c1, c2 = pts[contacts[0]], pts[contacts[1]]
            l1, l2 = lam[contacts[0]], lam[contacts[1]]
            e = (c2[0] - c1[0], c2[1] - c1[1], c2[2] - c1[2])
            ne = _norm(e)
            q = (l1[0] - l2[0], l1[1] - l2[1], l1[2] - l2[2])
            squeeze = abs(e[0] * q[0] + e[1] * q[1] + e[2] * q[2]) / (2.0 * ne) if ne > 0 else 0.0
        else:
            G = grasp_matrix(points[contacts], center)
            P = soft_internal_projector(G, self.robust)
            squeeze = float(np.linalg.norm(P @ forces[contacts].reshape(-1))) / math.sqrt(2.0)
        return external_ratio(_norm((net[0], net[1], net[2])), squeeze)
