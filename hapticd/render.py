"""One rendering step: device positions -> proxies -> contact forces -> allocation.

``Renderer.step`` runs once per servo tick. Outputs live in preallocated
arrays on the renderer (F fingers, r actuators):

- proxy_pos (F, 3) m, in_contact (F,) bool, contact_point (F, 3) m;
- contact_force (F, 3) N: the full force lam_i = k (proxy - device) - b v on
  each finger (the negative of the seed's force on the object; every allocator
  is linear, so this only flips the sign of lam_a);
- lam_a (r,) N and rendered_force (F, 3) N = finger i's rows of M_a lam_a,
  zero for a finger out of contact;
- accuracy (4,): internal, external, total residual and amplification of this
  tick's allocation (see hapticd.allocation.Accuracy); alpha: the adaptive
  allocator's external weight.

The common case, two fingers in contact with one actuated direction each, runs
on plain floats through the allocators' closed forms; anything else takes the
general numpy path. Both give the same numbers (a test checks).
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.actuation import Actuation
from hapticd.allocation import (
    DEFAULT_ROBUSTNESS,
    EXACT_METHODS,
    AdaptiveState,
    AllocationError,
    Robustness,
    accuracy,
    allocate,
    external_ratio,
    smoothstep,
    soft_internal_projector,
    two_contact_accuracy,
    two_contact_ef,
    two_contact_if,
    two_contact_pinv,
)
from hapticd.contact import proxy_step
from hapticd.grasp import grasp_matrix
from hapticd.scene import SceneObject

V3 = tuple[float, float, float]


def _norm(v: V3) -> float:
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def _finite(*vecs: V3) -> bool:
    return all(math.isfinite(c) for v in vecs for c in v)


class Renderer:
    """Proxy contact of F spherical fingertips on one object, then force allocation."""

    def __init__(
        self,
        obj: SceneObject,
        radii: list[float],
        actuation: Actuation,
        allocator: str,
        *,
        robust: Robustness = DEFAULT_ROBUSTNESS,
        adaptive: AdaptiveState | None = None,
        dt: float = 1e-3,
    ) -> None:
        if len(radii) != actuation.n_fingers:
            raise ValueError("one radius per finger is needed")
        self.obj = obj
        self.radii = [float(r) for r in radii]
        self._planes = [obj.polytope.inflated(r) for r in self.radii]
        self.actuation = actuation
        self.allocator = allocator
        self.robust = robust
        self.adaptive = adaptive if adaptive is not None else AdaptiveState()
        self.dt = dt
        F, r = actuation.n_fingers, actuation.n_actuators
        self.n_fingers = F
        self.proxy_pos = np.zeros((F, 3))
        self.in_contact = np.zeros(F, dtype=bool)
        self.contact_point = np.zeros((F, 3))
        self.contact_force = np.zeros((F, 3))
        self.rendered_force = np.zeros((F, 3))
        self.lam_a = np.zeros(r)
        self.accuracy = np.zeros(4)
        self.alpha = 0.0
        self._proxy: list[V3] | None = None
        self._zero3 = [(0.0, 0.0, 0.0)] * F

    def reset(self, device_pos: np.ndarray) -> None:
        """Start every proxy at its device (pushed out of the object if inside)."""
        self._proxy = [tuple(map(float, p)) for p in device_pos]

    def step(self, device_pos: np.ndarray, device_vel: np.ndarray) -> None:
        """Update proxies and forces for device positions (F, 3) m and velocities (F, 3) m/s."""
        pos: list[V3] = [tuple(p) for p in device_pos.tolist()]
        if self._proxy is None:
            self._proxy = list(pos)
        k, b = self.obj.stiffness, self.obj.damping
        proxies = self._proxy
        forces = list(self._zero3)
        points = list(pos)
        contacts: list[int] = []
        for i in range(self.n_fingers):
            poly = self._planes[i]
            g = pos[i]
            p, n_active, n = proxy_step(poly.normals_list, poly.offsets_list, proxies[i], g)
            proxies[i] = p
            if n_active:
                f = (k * (p[0] - g[0]), k * (p[1] - g[1]), k * (p[2] - g[2]))
                if b:
                    v = device_vel[i]
                    f = (f[0] - b * v[0], f[1] - b * v[1], f[2] - b * v[2])
                    # Damping may slow the finger but never pull it into the object.
                    fn = f[0] * n[0] + f[1] * n[1] + f[2] * n[2]
                    if fn < 0.0:
                        f = (f[0] - fn * n[0], f[1] - fn * n[1], f[2] - fn * n[2])
                forces[i] = f
                r = self.radii[i]
                points[i] = (p[0] - r * n[0], p[1] - r * n[1], p[2] - r * n[2])
                contacts.append(i)
            else:
                points[i] = p
        self.proxy_pos[:] = proxies
        self.contact_force[:] = forces
        self.contact_point[:] = points
        self.in_contact[:] = False
        self.in_contact[contacts] = True
        self._allocate(pos, points, forces, contacts)

    def _allocate(
        self, pos: list[V3], points: list[V3], forces: list[V3], contacts: list[int]
    ) -> None:
        self.rendered_force[:] = 0.0
        self.lam_a[:] = 0.0
        self.accuracy[:] = 0.0
        act = self.actuation
        if self.allocator == "adaptive":
            self.alpha = self.adaptive.update(
                self._external_ratio(points, forces, contacts), self.dt
            )
        if not contacts:
            return
        world = act.world_directions(pos)
        lam_a = self._solve(contacts, world, points, forces)
        onset = self.robust.contact_onset_n
        if len(contacts) >= 2 and onset > 0.0:
            # A contact that is just being made or broken joins the grasp gradually: without
            # this, the grasp matrix (and IF's squeeze) would jump when it appears or leaves.
            weakest = min(contacts, key=lambda i: _norm(forces[i]))
            beta = smoothstep(_norm(forces[weakest]) / onset)
            if beta < 1.0:
                rest = [i for i in contacts if i != weakest]
                lam_a = beta * lam_a + (1.0 - beta) * self._solve(rest, world, points, forces)
        if not np.all(np.isfinite(lam_a)):
            raise AllocationError(f"allocator {self.allocator!r} produced a non-finite force")
        self.lam_a[:] = lam_a
        for i in contacts:
            f = [0.0, 0.0, 0.0]
            for col, d in zip(act.columns[i], world[i], strict=True):
                x = lam_a[col]
                f[0] += x * d[0]
                f[1] += x * d[1]
                f[2] += x * d[2]
            self.rendered_force[i] = f
        self._measure(contacts, world, points, forces, lam_a)

    def _offsets(self, points: list[V3], contacts: list[int]) -> list[V3]:
        o = self.obj.center
        ox, oy, oz = float(o[0]), float(o[1]), float(o[2])
        return [(points[i][0] - ox, points[i][1] - oy, points[i][2] - oz) for i in contacts]

    def _is_two_simple(self, contacts: list[int]) -> bool:
        counts = self.actuation.counts
        return len(contacts) == 2 and counts[contacts[0]] == 1 and counts[contacts[1]] == 1

    def _solve(
        self, contacts: list[int], world: list[list[V3]], points: list[V3], forces: list[V3]
    ) -> np.ndarray:
        """lam_a over all r actuators (zero for fingers not in ``contacts``)."""
        act = self.actuation
        out = np.zeros(act.n_actuators)
        method = self.allocator
        if self._is_two_simple(contacts) and method not in EXACT_METHODS:
            i, j = contacts
            r1, r2 = self._offsets(points, contacts)
            d1, d2 = world[i][0], world[j][0]
            l1, l2 = forces[i], forces[j]
            if not _finite(r1, r2, d1, d2, l1, l2):
                raise AllocationError("non-finite contact geometry or force; refusing to allocate")
            x0, x1 = self._two(r1, r2, d1, d2, l1, l2)
            out[act.columns[i][0]] = x0
            out[act.columns[j][0]] = x1
            return out
        M, cols = act.submatrix(world, contacts)
        if cols:
            G = grasp_matrix(np.array([points[i] for i in contacts]), self.obj.center)
            lam = np.array([c for i in contacts for c in forces[i]])
            out[cols] = allocate(method, G, M, lam, robust=self.robust, alpha=self.alpha)
        return out

    def _two(self, r1: V3, r2: V3, d1: V3, d2: V3, l1: V3, l2: V3) -> tuple[float, float]:
        eps, sep = self.robust.eps, self.robust.min_separation_m
        method = self.allocator
        if method == "pinv":
            return two_contact_pinv(d1, d2, l1, l2, eps)
        if method == "ef":
            return two_contact_ef(r1, r2, d1, d2, l1, l2, eps)
        x_if = two_contact_if(r1, r2, d1, d2, l1, l2, eps, sep)
        alpha = self.alpha if method == "adaptive" else 0.0
        if alpha == 0.0:
            return x_if
        y0, y1 = two_contact_ef(r1, r2, d1, d2, l1, l2, eps)
        return (1.0 - alpha) * x_if[0] + alpha * y0, (1.0 - alpha) * x_if[1] + alpha * y1

    def _measure(
        self,
        contacts: list[int],
        world: list[list[V3]],
        points: list[V3],
        forces: list[V3],
        lam_a: np.ndarray,
    ) -> None:
        act = self.actuation
        if self._is_two_simple(contacts):
            i, j = contacts
            r1, r2 = self._offsets(points, contacts)
            x0, x1 = float(lam_a[act.columns[i][0]]), float(lam_a[act.columns[j][0]])
            a = two_contact_accuracy(r1, r2, world[i][0], world[j][0], forces[i], forces[j], x0, x1)
        else:
            M, cols = act.submatrix(world, contacts)
            G = grasp_matrix(np.array([points[i] for i in contacts]), self.obj.center)
            lam = np.array([c for i in contacts for c in forces[i]])
            a = accuracy(G, M, lam, lam_a[cols])
        self.accuracy[:] = (a.internal, a.external, a.total, a.amplification)

    def _external_ratio(self, points: list[V3], forces: list[V3], contacts: list[int]) -> float:
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
            G = grasp_matrix(np.array([points[i] for i in contacts]), self.obj.center)
            lam = np.array([c for i in contacts for c in forces[i]])
            P = soft_internal_projector(G, self.robust)
            squeeze = float(np.linalg.norm(P @ lam)) / math.sqrt(2.0)
        return external_ratio(_norm((net[0], net[1], net[2])), squeeze)
