"""One tick's allocation for F fingertips: which contacts, which closed form, contact onset.

``ContactAllocator.allocate`` takes the fingers in contact, their contact
points (m), full contact forces (N, on the finger) and the world directions
each finger may render, and returns lam_a (r,) N with the accuracy of the
result. One contact with one direction, and two contacts with one direction
each, run the closed forms on plain floats; anything else takes the general
numpy path (``hapticd.allocation.allocate``). Both give the same numbers (a
test checks). A contact being made or broken joins the grasp gradually.
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.actuation import Actuation
from hapticd.allocation import EXACT_METHODS, allocate
from hapticd.allocation.accuracy import accuracy, one_contact_accuracy, two_contact_accuracy
from hapticd.allocation.adaptive import AdaptiveState, external_ratio, smoothstep
from hapticd.allocation.batch import soft_internal_projector
from hapticd.allocation.closed import one_contact, two_contact
from hapticd.allocation.robust import AllocationError, Robustness
from hapticd.grasp import grasp_matrix

V3 = tuple[float, float, float]
Accuracy4 = tuple[float, float, float, float]
NO_ACCURACY: Accuracy4 = (0.0, 0.0, 0.0, 0.0)


def _norm(v: V3) -> float:
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def _finite(*vecs: V3) -> bool:
    """True if every component of the 3-vectors is finite: 0 x c is 0 for a finite c and
    NaN for inf or NaN, so the sum of those products is finite exactly then (and cannot
    overflow); a third of a generator's cost here."""
    s = 0.0
    for v in vecs:
        s += 0.0 * v[0] + 0.0 * v[1] + 0.0 * v[2]
    return math.isfinite(s)


class ContactAllocator:
    """Allocates contact forces onto ``actuation``'s directions with ``method``.

    Holds the adaptive allocator's state (alpha follows the task over ticks of
    ``dt`` s); everything else is computed from the arguments.
    """

    def __init__(
        self,
        actuation: Actuation,
        method: str,
        robust: Robustness,
        adaptive: AdaptiveState,
        dt: float,
    ) -> None:
        self.actuation = actuation
        self.method = method
        self.robust = robust
        self.adaptive = adaptive
        self.dt = dt
        self.alpha = 0.0

    def allocate(
        self,
        contacts: list[int],
        world: list[list[V3]],
        points: list[V3],
        forces: list[V3],
        center: V3,
    ) -> tuple[np.ndarray | None, Accuracy4]:
        """(lam_a (r,) N, accuracy) for the fingers in ``contacts`` (lam_a None: no contact).

        ``world`` holds each finger's actuated directions in the world frame,
        ``points`` (m) and ``forces`` (N) are per finger, ``center`` is the grasp's
        reference point (m). Updates ``alpha`` of the adaptive allocator.
        """
        if self.method == "adaptive":
            rho = self._external_ratio(points, forces, contacts, center)
            self.alpha = self.adaptive.update(rho, self.dt)
        if not contacts:
            return None, NO_ACCURACY
        lam_a = self._solve(contacts, world, points, forces, center)
        onset = self.robust.contact_onset_n
        if len(contacts) >= 2 and onset > 0.0:
            # A contact that is just being made or broken joins the grasp gradually: without
            # this, the grasp matrix (and IF's squeeze) would jump when it appears or leaves.
            weakest = min(contacts, key=lambda i: _norm(forces[i]))
            beta = smoothstep(_norm(forces[weakest]) / onset)
            if beta < 1.0:
                rest = [i for i in contacts if i != weakest]
                lam_a = beta * lam_a + (1.0 - beta) * self._solve(
                    rest, world, points, forces, center
                )
        if not all(map(math.isfinite, lam_a.tolist())):  # a tenth of np.isfinite's cost here
            raise AllocationError(f"allocator {self.method!r} produced a non-finite force")
        return lam_a, self._measure(contacts, world, points, forces, center, lam_a)

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
        n = len(in_contact)
        out = np.zeros((n, self.actuation.n_actuators))
        touching, pos = np.asarray(in_contact).tolist(), np.asarray(device_pos).tolist()
        pts, lam, ctr = np.asarray(points).tolist(), np.asarray(forces).tolist(), centers.tolist()
        for k in range(n):
            contacts = [i for i, on in enumerate(touching[k]) if on]
            world = self.actuation.world_directions(pos[k]) if contacts else []
            lam_a, _ = self.allocate(contacts, world, pts[k], lam[k], tuple(ctr[k]))
            if lam_a is not None:
                out[k] = lam_a
        return out

    def _offsets(self, points: list[V3], contacts: list[int], center: V3) -> list[V3]:
        ox, oy, oz = center
        return [(points[i][0] - ox, points[i][1] - oy, points[i][2] - oz) for i in contacts]

    def _is_two_simple(self, contacts: list[int]) -> bool:
        counts = self.actuation.counts
        return len(contacts) == 2 and counts[contacts[0]] == 1 and counts[contacts[1]] == 1

    def _general(
        self, contacts: list[int], points: list[V3], forces: list[V3], center: V3
    ) -> tuple[np.ndarray, np.ndarray]:
        G = grasp_matrix(np.array([points[i] for i in contacts]), np.array(center))
        lam = np.array([c for i in contacts for c in forces[i]])
        return G, lam

    def _solve(
        self,
        contacts: list[int],
        world: list[list[V3]],
        points: list[V3],
        forces: list[V3],
        center: V3,
    ) -> np.ndarray:
        """lam_a over all r actuators (zero for fingers not in ``contacts``)."""
        act = self.actuation
        out = np.zeros(act.n_actuators)
        method = self.method
        rb = self.robust
        if len(contacts) == 1 and act.counts[contacts[0]] == 1 and method not in EXACT_METHODS:
            (i,) = contacts
            (r1,) = self._offsets(points, contacts, center)
            d1, l1 = world[i][0], forces[i]
            if not _finite(r1, d1, l1):
                raise AllocationError("non-finite contact geometry or force; refusing to allocate")
            out[act.columns[i][0]] = one_contact(method, r1, d1, l1, rb.eps, self.alpha)
            return out
        if self._is_two_simple(contacts) and method not in EXACT_METHODS:
            i, j = contacts
            r1, r2 = self._offsets(points, contacts, center)
            d1, d2 = world[i][0], world[j][0]
            l1, l2 = forces[i], forces[j]
            if not _finite(r1, r2, d1, d2, l1, l2):
                raise AllocationError("non-finite contact geometry or force; refusing to allocate")
            x0, x1 = two_contact(
                method, r1, r2, d1, d2, l1, l2, rb.eps, rb.min_separation_m, self.alpha
            )
            out[act.columns[i][0]] = x0
            out[act.columns[j][0]] = x1
            return out
        M, cols = act.submatrix(world, contacts)
        if cols:
            G, lam = self._general(contacts, points, forces, center)
            out[cols] = allocate(method, G, M, lam, robust=rb, alpha=self.alpha)
        return out

    def _measure(
        self,
        contacts: list[int],
        world: list[list[V3]],
        points: list[V3],
        forces: list[V3],
        center: V3,
        lam_a: np.ndarray,
    ) -> Accuracy4:
        act = self.actuation
        if len(contacts) == 1 and act.counts[contacts[0]] == 1:
            (i,) = contacts
            (r1,) = self._offsets(points, contacts, center)
            x = float(lam_a[act.columns[i][0]])
            a = one_contact_accuracy(r1, world[i][0], forces[i], x)
        elif self._is_two_simple(contacts):
            i, j = contacts
            r1, r2 = self._offsets(points, contacts, center)
            x0, x1 = float(lam_a[act.columns[i][0]]), float(lam_a[act.columns[j][0]])
            a = two_contact_accuracy(r1, r2, world[i][0], world[j][0], forces[i], forces[j], x0, x1)
        else:
            M, cols = act.submatrix(world, contacts)
            G, lam = self._general(contacts, points, forces, center)
            a = accuracy(G, M, lam, lam_a[cols])
        return (a.internal, a.external, a.total, a.amplification)

    def _external_ratio(
        self, points: list[V3], forces: list[V3], contacts: list[int], center: V3
    ) -> float:
        """The adaptive allocator's task state: |net force| / (|net force| + squeeze)."""
        if not contacts:
            return 0.0
        net = [sum(forces[i][k] for i in contacts) for k in range(3)]
        if len(contacts) == 1:
            squeeze = 0.0
        elif len(contacts) == 2:
            c1, c2 = points[contacts[0]], points[contacts[1]]
            l1, l2 = forces[contacts[0]], forces[contacts[1]]
            e = (c2[0] - c1[0], c2[1] - c1[1], c2[2] - c1[2])
            ne = _norm(e)
            q = (l1[0] - l2[0], l1[1] - l2[1], l1[2] - l2[2])
            squeeze = abs(e[0] * q[0] + e[1] * q[1] + e[2] * q[2]) / (2.0 * ne) if ne > 0 else 0.0
        else:
            G, lam = self._general(contacts, points, forces, center)
            P = soft_internal_projector(G, self.robust)
            squeeze = float(np.linalg.norm(P @ lam)) / math.sqrt(2.0)
        return external_ratio(_norm((net[0], net[1], net[2])), squeeze)
