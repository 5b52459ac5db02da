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
    one_contact,
    one_contact_accuracy,
    smoothstep,
    soft_internal_projector,
    two_contact_accuracy,
    two_contact_ef,
    two_contact_if,
    two_contact_pinv,
)
from hapticd.contact import MultiResult, ObstacleSet, proxy_step_multi
from hapticd.dynamics import (
    SMALL_SHAPE,
    SurfaceSet,
    auto_substeps,
    step_body,
    step_body_small,
)
from hapticd.friction import friction_proxy
from hapticd.grasp import grasp_matrix
from hapticd.scene import Material, Scene, SceneObject

V3 = tuple[float, float, float]


_PARAMS = {
    "stiffness_n_per_m",
    "damping_n_s_per_m",
    "friction",
    "mass_kg",
    "fixed",
    "allocator",
    "actuated_directions",
}


def _unit(v: V3, fallback: V3) -> V3:
    n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return (v[0] / n, v[1] / n, v[2] / n) if n > 1e-15 else fallback


def _projector(directions: list[V3]) -> np.ndarray:
    """Orthogonal projector (3, 3) onto the span of a finger's actuated directions."""
    if not directions:
        return np.zeros((3, 3))
    D = np.array(directions).T
    return D @ np.linalg.pinv(D)


def _norm(v: V3) -> float:
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def _finite(*vecs: V3) -> bool:
    return all(math.isfinite(c) for v in vecs for c in v)


class Renderer:
    """One tick of the scene for F spherical fingertips: contact, friction, forces, allocation,
    dynamics. Stages the scene does not need (friction without a friction coefficient,
    dynamics for a fixed object) are not in the plan and never run."""

    def __init__(
        self,
        scene: Scene | SceneObject,
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
        self.scene = scene if isinstance(scene, Scene) else Scene(scene, [], None)
        self.obj = self.scene.object
        self.radii = [float(r) for r in radii]
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
        self.env_force = np.zeros((F, 3))
        self.rendered_force = np.zeros((F, 3))
        self.lam_a = np.zeros(r)
        self.accuracy = np.zeros(4)
        self.alpha = 0.0
        self._proxy: list[V3] | None = None
        self._anchor: list[V3 | None] = [None] * F  # friction anchors, object body frame
        self._normals: list[V3] = [(0.0, 0.0, 0.0)] * F  # contact normals of this tick
        self._zero3 = [(0.0, 0.0, 0.0)] * F
        self._pending: dict[str, object] = {}
        self.plan()

    # -- planning -----------------------------------------------------------------------

    def plan(self) -> None:
        """Choose the stages this scene needs and prepare the obstacles."""
        sc = self.scene
        self.friction_on = self.obj.material.has_friction
        self.dynamics_on = not self.obj.fixed
        self.gravity = sc.gravity if self.dynamics_on else None
        self.body_surfaces = SurfaceSet(sc.surfaces) if self.dynamics_on and sc.surfaces else None
        self.substeps = sc.substeps
        if self.dynamics_on and sc.substeps == 0:  # auto
            self.substeps = auto_substeps(
                self.obj, sc.surfaces, self.obj.material.stiffness, self.n_fingers, self.dt
            )
        self._surface_obstacles = [
            [s.polytope.inflated(r) for s in sc.surfaces] for r in self.radii
        ]
        self._rebuild_obstacles()

    @property
    def stages(self) -> list[str]:
        """Names of the stages in the current plan, in tick order."""
        out = ["contact"]
        if self.friction_on:
            out.append("friction")
        out += ["forces", "allocation"]
        if self.dynamics_on:
            out.append("dynamics")
            if self.gravity is not None:
                out.append("gravity")
            if self.body_surfaces:
                out.append("surfaces")
        return out

    def _rebuild_obstacles(self) -> None:
        self._sets = []
        for i, r in enumerate(self.radii):
            obj_poly = self.obj.polytope.inflated(r)
            obstacles = [(obj_poly.normals_list, obj_poly.offsets_list)]
            obstacles += [(p.normals_list, p.offsets_list) for p in self._surface_obstacles[i]]
            self._sets.append(ObstacleSet(obstacles))

    def update(self, **params: object) -> None:
        """Change scene or rendering parameters; applied at the start of the next tick.

        Keys: stiffness_n_per_m, damping_n_s_per_m, friction (static, dynamic), mass_kg,
        fixed, allocator, actuated_directions (per finger, unit vectors in the actuation
        frame; the number per finger cannot change: it fixes the recording's layout).
        ValueError, with nothing changed, for an unknown key or a bad actuation.
        """
        unknown = set(params) - _PARAMS
        if unknown:
            raise ValueError(f"unknown parameter(s) {sorted(unknown)}; known: {sorted(_PARAMS)}")
        if "actuated_directions" in params:
            new = Actuation(params["actuated_directions"], self.actuation.frame)  # type: ignore[arg-type]
            if new.counts != self.actuation.counts:
                raise ValueError(
                    f"actuated directions per finger must stay {self.actuation.counts}, "
                    f"got {new.counts} (change the count in the profile and reload)"
                )
            params = {**params, "actuated_directions": new}
        self._pending.update(params)

    def _apply_pending(self) -> None:
        p, self._pending = self._pending, {}
        m = self.obj.material
        mat = {
            "stiffness": m.stiffness,
            "damping": m.damping,
            "mu_static": m.mu_static,
            "mu_dynamic": m.mu_dynamic,
        }
        if "stiffness_n_per_m" in p:
            mat["stiffness"] = float(p["stiffness_n_per_m"])
        if "damping_n_s_per_m" in p:
            mat["damping"] = float(p["damping_n_s_per_m"])
        if "friction" in p:
            mat["mu_static"], mat["mu_dynamic"] = (float(v) for v in p["friction"])
        self.obj.material = Material(**mat)
        if "mass_kg" in p:
            self.obj.mass = float(p["mass_kg"])
        if "fixed" in p:
            self.obj.fixed = bool(p["fixed"])
        if "allocator" in p:
            self.allocator = str(p["allocator"])
        if "actuated_directions" in p:
            self.actuation = p["actuated_directions"]  # type: ignore[assignment]
        self.plan()

    def reset(self, device_pos: np.ndarray) -> None:
        """Start every proxy at its device (pushed out of the object if inside)."""
        self._proxy = [tuple(map(float, p)) for p in device_pos]

    # -- the tick ---------------------------------------------------------------------

    def step(self, device_pos: np.ndarray, device_vel: np.ndarray) -> None:
        """One tick for device positions (F, 3) m and velocities (F, 3) m/s."""
        if self._pending:
            self._apply_pending()
        pos: list[V3] = [tuple(p) for p in device_pos.tolist()]
        if self._proxy is None:
            self._proxy = list(pos)
        obj = self.obj
        mat = obj.material
        k, b = mat.stiffness, mat.damping
        proxies = self._proxy
        forces = list(self._zero3)
        env = list(self._zero3)
        shown = list(pos)
        points = list(pos)
        contacts: list[int] = []
        R, x0 = obj.rotation, obj.position
        for i in range(self.n_fingers):
            g = pos[i]
            oset = self._sets[i]
            res = proxy_step_multi(oset, proxies[i], g)
            p = res.proxy
            proxies[i] = p
            shown[i] = p
            obj_planes = [(pl, m) for (j, pl), m in zip(res.active, res.mu, strict=True) if j == 0]
            if len(obj_planes) < len(res.active):
                env[i] = self._env_force(oset, res, g, device_vel[i])
            if not obj_planes:
                self._anchor[i] = None
                points[i] = p
                continue
            # The proxy's displacement due to the object's planes alone.
            onorm = oset.obstacles[0][0]
            po = [g[0], g[1], g[2]]
            for pl, m in obj_planes:
                n = onorm[pl]
                po[0] += m * n[0]
                po[1] += m * n[1]
                po[2] += m * n[2]
            pf: V3 = (po[0], po[1], po[2])
            if len(obj_planes) == 1:
                n = onorm[obj_planes[0][0]]
            else:
                n = _unit((pf[0] - g[0], pf[1] - g[1], pf[2] - g[2]), onorm[obj_planes[0][0]])
            if self.friction_on:
                pf = self._friction(i, pf, g, n, R, x0)
            f = (k * (pf[0] - g[0]), k * (pf[1] - g[1]), k * (pf[2] - g[2]))
            if b:
                v = self._relative_velocity(device_vel[i], pf)
                f = (f[0] - b * v[0], f[1] - b * v[1], f[2] - b * v[2])
                # Damping may slow the finger but never pull it into the object.
                fn = f[0] * n[0] + f[1] * n[1] + f[2] * n[2]
                if fn < 0.0:
                    f = (f[0] - fn * n[0], f[1] - fn * n[1], f[2] - fn * n[2])
            forces[i] = f
            shown[i] = (p[0] + pf[0] - po[0], p[1] + pf[1] - po[1], p[2] + pf[2] - po[2])
            r = self.radii[i]
            points[i] = (pf[0] - r * n[0], pf[1] - r * n[1], pf[2] - r * n[2])
            self._normals[i] = n
            contacts.append(i)
        self.proxy_pos[:] = shown
        self.contact_force[:] = forces
        self.env_force[:] = env
        self.contact_point[:] = points
        self.in_contact[:] = False
        self.in_contact[contacts] = True
        self._allocate(pos, points, forces, contacts)
        if any(e != (0.0, 0.0, 0.0) for e in env):
            # Ground and walls are rendered through each finger's own actuated directions.
            world = self.actuation.world_directions(pos)
            for i in range(self.n_fingers):
                if env[i] != (0.0, 0.0, 0.0):
                    self.rendered_force[i] += _projector(world[i]) @ np.array(env[i])
        if self.dynamics_on:
            self._dynamics(points, forces, contacts)

    def _friction(self, i: int, pf: V3, g: V3, n: V3, R: np.ndarray, x0: np.ndarray) -> V3:
        anchor = self._anchor[i]
        aw = None
        if anchor is not None:
            a = R @ np.array(anchor) + x0
            aw = (float(a[0]), float(a[1]), float(a[2]))
        m = self.obj.material
        pf, _ = friction_proxy(pf, g, n, aw, m.mu_static, m.mu_dynamic)
        local = R.T @ (np.array(pf) - x0)
        self._anchor[i] = (float(local[0]), float(local[1]), float(local[2]))
        return pf

    def _relative_velocity(self, v_dev: np.ndarray, point: V3) -> V3:
        obj = self.obj
        if obj.fixed:
            return (float(v_dev[0]), float(v_dev[1]), float(v_dev[2]))
        rel = np.array(point) - obj.position
        w = obj.omega
        spin = (
            w[1] * rel[2] - w[2] * rel[1],
            w[2] * rel[0] - w[0] * rel[2],
            w[0] * rel[1] - w[1] * rel[0],
        )
        v = v_dev - obj.velocity - spin
        return (float(v[0]), float(v[1]), float(v[2]))

    def _env_force(self, oset: ObstacleSet, res: MultiResult, g: V3, v_dev: np.ndarray) -> V3:
        """Force on a finger from the ground and walls it touches, N."""
        f = [0.0, 0.0, 0.0]
        for (j, pl), m in zip(res.active, res.mu, strict=True):
            if j == 0:
                continue
            n = oset.obstacles[j][0][pl]
            mat = self.scene.surfaces[j - 1].material
            vn = float(v_dev[0] * n[0] + v_dev[1] * n[1] + v_dev[2] * n[2])
            mag = max(mat.stiffness * m - mat.damping * vn, 0.0)
            f[0] += mag * n[0]
            f[1] += mag * n[1]
            f[2] += mag * n[2]
        return (f[0], f[1], f[2])

    def _dynamics(self, points: list[V3], forces: list[V3], contacts: list[int]) -> None:
        obj = self.obj
        F = np.zeros(3)
        T = np.zeros(3)
        k = obj.material.stiffness
        # The object feels the reaction of the full (virtual) contact force, as springs
        # that move with it during the tick's substeps.
        springs = [(points[i], (-forces[i][0], -forces[i][1], -forces[i][2]), k) for i in contacts]
        torsion = None
        mu_t = obj.material.torsion
        if mu_t > 0.0 and contacts:
            # Soft-finger contacts resist the object's spin about each contact normal.
            torsion = []
            for i in contacts:
                n, f = self._normals[i], forces[i]
                fn = abs(f[0] * n[0] + f[1] * n[1] + f[2] * n[2])
                if fn > 0.0:
                    torsion.append((n, mu_t * fn))
        small = len(obj.shape.vertices) <= SMALL_SHAPE
        (step_body_small if small else step_body)(
            obj,
            (float(F[0]), float(F[1]), float(F[2])) if small else F,
            (float(T[0]), float(T[1]), float(T[2])) if small else T,
            self.dt,
            gravity=self.gravity,
            surfaces=self.body_surfaces,
            substeps=self.substeps,
            torsion=torsion,
            springs=springs,
        )
        self._rebuild_obstacles()

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
        if len(contacts) == 1 and act.counts[contacts[0]] == 1 and method not in EXACT_METHODS:
            (i,) = contacts
            (r1,) = self._offsets(points, contacts)
            d1, l1 = world[i][0], forces[i]
            if not _finite(r1, d1, l1):
                raise AllocationError("non-finite contact geometry or force; refusing to allocate")
            out[act.columns[i][0]] = one_contact(method, r1, d1, l1, self.robust.eps, self.alpha)
            return out
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
        if len(contacts) == 1 and act.counts[contacts[0]] == 1:
            (i,) = contacts
            (r1,) = self._offsets(points, contacts)
            x = float(lam_a[act.columns[i][0]])
            a = one_contact_accuracy(r1, world[i][0], forces[i], x)
        elif self._is_two_simple(contacts):
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
