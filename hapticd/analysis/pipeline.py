"""Barbagli & Salisbury's asymmetry analysis, run on the same stages the servo loop runs.

``Pipeline`` holds its own copy of a scene and renders it off-line with
``hapticd.physics.render.Renderer`` (contact, friction, forces, allocation, environment;
no devices, safety chain or timing), one renderer per evaluation, so it never
touches a live loop. Every quantity is quasi-static: fingers at rest (zero
velocity, so damping does no work), proxies settled, a free object held at its
pose, the adaptive allocator's alpha at its target (no lag).

- ``forces(x)``: the full contact force and the rendered force on each finger,
  (p, 3) N each, for finger positions ``x`` (p, 3) m in the world frame.
- ``linearize(x)``: K_full (3p, 3p) N/m, the derivative of the full forces (the
  seed's F_L, eq. 6), K_rendered, the derivative of the rendered forces (the
  seed's M_A F_L M_S with full sensing, eq. 8), and the seed's indices.
- ``linearize_coordinates(coords, q)``: the same in generalized coordinates
  q (m,) with x = coords(q), e.g. the seed's rod (L, alpha).
- ``loop_work(path)``: the work of the rendered forces along a closed path.

Everything is per allocator: each result is a dict keyed by allocator name.

Settling. Without a given state, each finger starts ``START_MARGIN_M`` outside
the object along the outward normal of the nearest face of the object grown by
its radius (the shortest way out), the renderer ticks once there and then at
``x`` until the proxies stop moving: the god-object enters through that face
and ends on the surface point nearest to the finger, as a finger pressed
straight in would leave it. With friction the contact sticks where it first
touched. Given a ``State`` (``settle``), the fingers move from the state's
positions to ``x`` in straight steps of at most ``MOVE_STEP_M``, friction
anchors and proxies carried along.

Finite differences. K's column j is (F(x + h e_j) - F(x - h e_j)) / (2 h) with
h = ``FD_STEP_M`` = 1e-6 m, each perturbed configuration settled the same way
as x (frictionless: from outside, independently; with friction or a given
state: from the settled state at x, so a sticking contact shows its anchor's
stiffness). A flat face's force is linear in x, so there the central
difference is exact up to rounding (about 1e-16 * depth / h, below 1e-12
relative); curvature from the grasp frame and the allocators' geometry, with
a length scale L of centimetres, leaves a truncation error of order
(h / L)^2 < 1e-8 relative. A step that straddles a kink (a face boundary, the
contact onset) shows up in ``fd_error``, the largest difference between the
estimates with h and 2 h.

Units: m, N, N/m, J. Pure: numpy in, numpy out.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from hapticd.allocation import (
    DEFAULT_ROBUSTNESS,
    METHODS,
    ROBUST_METHODS,
    AdaptiveState,
    Robustness,
)
from hapticd.allocation.actuation import Actuation
from hapticd.physics.frame import Frame
from hapticd.physics.render import Renderer
from hapticd.physics.scene import Material, Scene, SceneObject

FD_STEP_M = 1e-6
"""Central-difference step (m) for Cartesian linearizations (see the module's docstring)."""
COORD_STEPS = (1e-6, 1e-4)
"""Steps for generalized coordinates, in their own units: first and second derivatives of
coords(q) (fine for lengths in m and angles in rad)."""
COINCIDENT_M = 1e-5
"""Fingers closer than this (m) coincide: no grasp line, no grasp frame."""
START_MARGIN_M = 1e-3
"""How far outside the nearest face (m) a settle starts each finger."""
MOVE_STEP_M = 1e-4
"""Longest straight step (m) when fingers move from a given state to new positions."""
SETTLE_TICKS = 20
"""Most ticks spent at one configuration waiting for the proxies to stop moving."""
CLOSURE_TOL_M = 1e-6
"""Default tolerance (m) on how far a closed path's last point may be from its first."""
ZERO_STIFFNESS = 1e-9
"""A stiffness matrix with Frobenius norm below this (N/m) counts as zero."""
NULL_RTOL = 1e-7
"""Singular values below this fraction of the largest (or below ZERO_STIFFNESS) are null."""
KINK_RTOL = 1e-3
"""An error estimate above this fraction of K's largest entry marks a kink (see ``smooth``)."""
RANK_TOL = 1e-9
"""Singular-value tolerance for the rank of the (unit-direction) actuation matrix."""

_AXES = ("x", "y", "z")


class Forces(NamedTuple):
    """Full contact force and rendered force (before safety) on each finger, (p, 3) N each."""

    full: np.ndarray
    rendered: np.ndarray


class Work(NamedTuple):
    """Work (J) done on the fingers along a closed path by the full and the rendered forces;
    positive: the display delivers energy to the user (it feels active)."""

    full: float
    rendered: float


@dataclass(frozen=True)
class Linearization:
    """The seed's analysis at one configuration, for one allocator.

    ``K_full`` and ``K_rendered`` are (n, n) N/m (per coordinate unit squared in
    generalized coordinates): the derivatives of the full and rendered forces
    (generalized forces J^T F), sign as forces on the fingers, so a plain spring is
    negative definite. n = 3p Cartesian, or the number of generalized coordinates.

    ``asymmetry`` = ||(K - K^T) / 2||_F / ||K||_F of K_rendered, in [0, 1] (0 when
    K_rendered is zero). ``controllability`` k = s / n with s the sensed DOF (all of
    them: full sensing); ``observability`` o = r / n with r the rank of the actuation
    (seed eqs. 1-4). ``null_directions`` (n, m): orthonormal displacements along which
    no rendered stiffness is felt (the null space of K_rendered).
    ``work_per_area`` (N/m = J/m^2): the largest work of the rendered forces per unit
    area of a small planar loop, sigma_max(K - K^T), reached going around
    ``work_plane`` (n, 2) from its first column toward its second.
    """

    allocator: str
    x: np.ndarray  # (p, 3) m
    in_contact: np.ndarray  # (p,) bool
    full_force: np.ndarray  # (p, 3) N
    rendered_force: np.ndarray  # (p, 3) N
    K_full: np.ndarray
    K_rendered: np.ndarray
    asymmetry: float
    n: int
    s: int
    r: int
    controllability: float
    observability: float
    null_directions: np.ndarray
    work_per_area: float
    work_plane: np.ndarray
    fd_step: float
    fd_error: float  # N/m: largest |K(h) - K(2h)| over both matrices
    labels: tuple[str, ...]  # one per row/column of K
    q: np.ndarray | None = None  # generalized coordinates, when used
    Q_full: np.ndarray | None = None  # generalized forces J^T F
    Q_rendered: np.ndarray | None = None

    @property
    def smooth(self) -> bool:
        """False where the differences straddle a kink of the force (a face edge, contact
        onset, the weakest of two equally weak contacts changing): ``fd_error`` above
        KINK_RTOL of the largest entry. There K is a difference quotient across a jump, not
        a derivative."""
        scale = max(float(np.abs(self.K_full).max(initial=0.0)), ZERO_STIFFNESS)
        scale = max(scale, float(np.abs(self.K_rendered).max(initial=0.0)))
        return self.fd_error <= KINK_RTOL * scale

    def to_dict(self) -> dict[str, Any]:
        """Plain lists and floats, for JSON."""
        out: dict[str, Any] = {}
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            out[name] = v.tolist() if isinstance(v, np.ndarray) else v
        out["labels"] = list(self.labels)
        out["smooth"] = self.smooth
        return out


class State:
    """A settled pipeline at finger positions ``x`` (p, 3) m: proxies, friction anchors.

    Opaque; made by ``Pipeline.settle`` and passed back to start from it.
    """

    def __init__(self, renderer: Renderer, x: np.ndarray) -> None:
        self._renderer = renderer
        self.x = np.array(x, dtype=float)

    @property
    def in_contact(self) -> np.ndarray:
        """Which fingers touch the object, (p,) bool."""
        return self._renderer.frame.in_contact.astype(bool)

    @property
    def frame(self) -> Frame:
        """The settled tick's frame (read it; the state is reused as it is)."""
        return self._renderer.frame


def _still(v: np.ndarray) -> np.ndarray:
    return np.zeros_like(v)


def _copy_renderer(r: Renderer) -> Renderer:
    """A deep copy of ``r`` with its state. The frame is copied with ``Frame.copy``: a plain
    deep copy would detach the frame's field views from its record."""
    return copy.deepcopy(r, memo={id(r.frame): r.frame.copy()})


def _held_scene(scene: Scene | SceneObject) -> Scene:
    """A deep copy of ``scene`` with its object held fixed and at rest (quasi-static)."""
    sc = copy.deepcopy(scene if isinstance(scene, Scene) else Scene(scene, [], None))
    obj = sc.object
    obj.fixed = True
    obj.velocity = np.zeros(3)
    obj.omega = np.zeros(3)
    return sc


def asymmetry(K: np.ndarray) -> float:
    """||(K - K^T) / 2||_F / ||K||_F in [0, 1]; 0 for a zero matrix (below ZERO_STIFFNESS)."""
    norm = float(np.linalg.norm(K))
    if norm <= ZERO_STIFFNESS:
        return 0.0
    return float(np.linalg.norm(0.5 * (K - K.T)) / norm)


def null_directions(K: np.ndarray) -> np.ndarray:
    """Orthonormal basis (n, m) of the null space of K (n, n), readable and deterministic:
    coordinate axes where the null space holds them (reduced row echelon form, then
    Gram-Schmidt in pivot order, each vector's pivot entry positive)."""
    n = K.shape[0]
    if n == 0:
        return np.zeros((0, 0))
    _, sv, Vt = np.linalg.svd(K)
    tol = max(ZERO_STIFFNESS, NULL_RTOL * float(sv[0]) if sv.size else 0.0)
    N = Vt[sv > tol].shape[0]
    basis = Vt[N:].T  # (n, m)
    m = basis.shape[1]
    if m == 0:
        return np.zeros((n, 0))
    # Reduced row echelon form of basis^T: pivot on the largest remaining entries.
    A = basis.T.copy()
    pivots: list[int] = []
    for row in range(m):
        sub = np.abs(A[row:, :])
        sub[:, pivots] = 0.0
        # The largest entry, ties (to rounding) going to the first axis: a stable order.
        cols = np.flatnonzero(sub.max(axis=0) >= sub.max() * (1.0 - 1e-9))
        j = int(cols[0])
        i = int(np.argmax(sub[:, j]))
        A[[row, row + i]] = A[[row + i, row]]
        A[row] /= A[row, j]
        for other in range(m):
            if other != row:
                A[other] -= A[other, j] * A[row]
        pivots.append(int(j))
    order = np.argsort(pivots)
    A = A[order]
    A[np.abs(A) < 1e-12] = 0.0
    Q = np.zeros((n, m))
    for k in range(m):
        v = A[k].copy()
        for jj in range(k):
            v -= (Q[:, jj] @ v) * Q[:, jj]
        v /= np.linalg.norm(v)
        v[np.abs(v) < 1e-12] = 0.0
        Q[:, k] = v / np.linalg.norm(v)
    return Q + 0.0  # no negative zeros in printed bases


def loop_work_rate(K: np.ndarray) -> tuple[float, np.ndarray]:
    """Largest work per unit area (N/m = J/m^2) of a small planar loop in the force field
    with derivative K (n, n), and its plane (n, 2): sigma_max(K - K^T), going from the
    plane's first column toward its second (Green's theorem: W = A v^T (K - K^T) u)."""
    n = K.shape[0]
    W = K - K.T
    if n < 2 or float(np.linalg.norm(W)) <= ZERO_STIFFNESS:
        return 0.0, np.zeros((n, 2))
    _, sv, Vt = np.linalg.svd(W)
    u = Vt[0]
    v = W @ u / sv[0]
    return float(sv[0]), np.column_stack([u, v])


def _rank(M: np.ndarray) -> int:
    if M.size == 0:
        return 0
    return int(np.sum(np.linalg.svd(M, compute_uv=False) > RANK_TOL))


class Pipeline:
    """The loop's rendering stages on a private, quasi-static copy of a scene.

    ``scene`` (copied; its object is held fixed), fingertip ``radii`` (m),
    ``actuation`` (each finger's directions), ``robust`` and ``adaptive`` (its
    ratios; the lag is dropped) as the loop has them; ``allocators`` to compare
    (default: the robust ones); ``finger_names`` label the results.
    """

    def __init__(
        self,
        scene: Scene | SceneObject,
        radii: Sequence[float],
        actuation: Actuation,
        *,
        robust: Robustness = DEFAULT_ROBUSTNESS,
        adaptive: AdaptiveState | None = None,
        dt: float = 1e-3,
        allocators: Sequence[str] | None = None,
        finger_names: Sequence[str] | None = None,
    ) -> None:
        names = tuple(ROBUST_METHODS if allocators is None else allocators)
        unknown = [a for a in names if a not in METHODS]
        if unknown or not names:
            raise ValueError(
                f"unknown allocator(s) {unknown or names!r}; expected some of {list(METHODS)}"
            )
        if len(radii) != actuation.n_fingers:
            raise ValueError(
                f"{len(radii)} radii for {actuation.n_fingers} fingers: one radius per finger"
            )
        self.scene = _held_scene(scene)
        self.radii = [float(r) for r in radii]
        self.n_fingers = len(self.radii)
        self.actuation = actuation
        self.robust = robust
        ad = adaptive if adaptive is not None else AdaptiveState()
        self._ratios = (ad.ratio_low, ad.ratio_high)
        self.dt = dt
        self.allocators: tuple[str, ...] = tuple(dict.fromkeys(names))
        self.finger_names = (
            tuple(finger_names)
            if finger_names is not None
            else tuple(f"finger{i}" for i in range(self.n_fingers))
        )
        if len(self.finger_names) != self.n_fingers:
            raise ValueError(f"{len(self.finger_names)} finger names for {self.n_fingers} fingers")

    # -- construction ----------------------------------------------------------------------

    @classmethod
    def from_renderer(
        cls,
        renderer: Renderer,
        *,
        allocators: Sequence[str] | None = None,
        finger_names: Sequence[str] | None = None,
    ) -> Pipeline:
        """The pipeline of ``renderer`` (a live one is only read: its scene is copied).

        Stages added with ``Renderer.insert`` are not part of it: the analysis is of
        the planned stages at rest.
        """
        return cls(
            renderer.scene,
            renderer.radii,
            renderer.actuation,
            robust=renderer.allocator.robust,
            adaptive=renderer.allocator.adaptive,
            dt=renderer.dt,
            allocators=allocators,
            finger_names=finger_names,
        )

    def _clone(self, scene: Scene) -> Pipeline:
        return type(self)(
            scene,
            self.radii,
            self.actuation,
            robust=self.robust,
            adaptive=AdaptiveState(*self._ratios),
            dt=self.dt,
            allocators=self.allocators,
            finger_names=self.finger_names,
        )

    def at(
        self,
        position: np.ndarray | None = None,
        rotation: np.ndarray | None = None,
        stiffness: float | None = None,
    ) -> Pipeline:
        """This pipeline with the object moved to ``position`` (3,) m / ``rotation`` (3, 3)
        and/or its stiffness (N/m) changed (e.g. to a recorded tick's)."""
        sc = copy.deepcopy(self.scene)
        obj = sc.object
        if position is not None:
            obj.position = np.array(position, dtype=float).reshape(3)
        if rotation is not None:
            obj.rotation = np.array(rotation, dtype=float).reshape(3, 3)
        if stiffness is not None:
            m = obj.material
            obj.material = Material(
                float(stiffness), m.damping, m.mu_static, m.mu_dynamic, m.torsion
            )
        return self._clone(sc)

    # -- configurations --------------------------------------------------------------------

    @property
    def labels(self) -> tuple[str, ...]:
        """One label per Cartesian coordinate, e.g. 'thumb.x' (the rows of K)."""
        return tuple(f"{n}.{a}" for n in self.finger_names for a in _AXES)

    @property
    def has_friction(self) -> bool:
        return self.scene.object.material.has_friction

    def check(self, x: Any, what: str = "x") -> np.ndarray:
        """``x`` as a (p, 3) float array; ValueError for a wrong shape, a non-finite
        position or two coinciding fingers."""
        p = self.n_fingers
        try:
            arr = np.asarray(x, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"{what} must be finger positions of shape ({p}, 3) in m: {exc}"
            ) from None
        if arr.shape != (p, 3):
            raise ValueError(
                f"{what} must have shape ({p}, 3), one row (m) per finger "
                f"({', '.join(self.finger_names)}); got shape {arr.shape}"
            )
        bad = [self.finger_names[i] for i in range(p) if not np.all(np.isfinite(arr[i]))]
        if bad:
            raise ValueError(f"{what} holds non-finite positions (NaN or inf) for {', '.join(bad)}")
        for i in range(p):
            for j in range(i + 1, p):
                d = float(np.linalg.norm(arr[i] - arr[j]))
                if d < COINCIDENT_M:
                    raise ValueError(
                        f"{what}: fingers {self.finger_names[i]} and {self.finger_names[j]} "
                        f"coincide ({d:.3g} m apart; fingers closer than {COINCIDENT_M:g} m have "
                        "no grasp line, so the grasp frame and grasp matrix are undefined)"
                    )
        return arr.copy()

    def _inflated(self, r: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """Half-spaces (normals, offsets) the centre of a fingertip of radius ``r`` stays out
        of: the object's, then each ground or wall's."""
        poly = self.scene.object.polytope
        out = [(poly.normals, poly.offsets + r)]
        out += [
            (np.array([s.normal], dtype=float), np.array([s.offset + r]))
            for s in self.scene.surfaces
        ]
        return out

    def _outside(self, x: np.ndarray) -> np.ndarray:
        """Each finger moved START_MARGIN_M outside along the nearest face's outward normal
        (the shortest way out), if it is inside or nearer than that."""
        out = x.copy()
        for i, r in enumerate(self.radii):
            p = out[i]
            for _ in range(3):  # the object, then the ground and walls; twice for a crease
                moved = False
                for N, off in self._inflated(r):
                    d = N @ p - off
                    j = int(np.argmax(d))
                    if d[j] < START_MARGIN_M:
                        p = p + (START_MARGIN_M - d[j]) * N[j]
                        moved = True
                if not moved:
                    break
            out[i] = p
        return out

    def grasp_configuration(self, depth_m: float = 0.002) -> tuple[np.ndarray, str]:
        """A default configuration (p, 3) m and how it was chosen: each finger ``depth_m``
        inside the object (grown by its radius) along the grasp axis, the object's body x
        axis through its centre; the first finger on the -x side, the second on +x,
        further ones on -y, +y, -z, +z."""
        obj = self.scene.object
        c = obj.position
        R = obj.rotation
        sides = [-R[:, 0], R[:, 0], -R[:, 1], R[:, 1], -R[:, 2], R[:, 2]]
        if self.n_fingers > len(sides):
            raise ValueError(f"no default configuration for {self.n_fingers} fingers; give one")
        x = np.zeros((self.n_fingers, 3))
        poly = obj.polytope
        for i, (u, r) in enumerate(zip(sides, self.radii, strict=False)):
            # Where the ray from the centre along u leaves the grown object.
            nu = poly.normals @ u
            reach = (poly.offsets + r - poly.normals @ c)[nu > 1e-12] / nu[nu > 1e-12]
            x[i] = c + (float(np.min(reach)) - depth_m) * u
        names = ["-x", "+x", "-y", "+y", "-z", "+z"]
        where = ", ".join(
            f"{n} on the {s} side" for n, s in zip(self.finger_names, names, strict=False)
        )
        how = (
            f"each finger {depth_m * 1e3:g} mm inside the object (grown by the fingertip radius) "
            f"along the grasp axis, the object's x axis through its centre: {where}"
        )
        return x, how

    # -- settling --------------------------------------------------------------------------

    def renderer(self, allocator: str, scene: Scene | None = None) -> Renderer:
        """A fresh renderer as the pipeline ticks it, rendering with ``allocator`` (the
        pipeline's scene unless ``scene``)."""
        # tau = 0: the adaptive allocator's alpha sits at its target (quasi-static). The
        # object is fixed, so renderers may share the scene unless it is to be moved.
        return Renderer(
            self.scene if scene is None else scene,
            self.radii,
            self.actuation,
            allocator,
            robust=self.robust,
            adaptive=AdaptiveState(*self._ratios, time_constant_s=0.0),
            dt=self.dt,
        )

    @staticmethod
    def _hold(r: Renderer, x: np.ndarray) -> None:
        """Tick at ``x`` until the proxies and held points stop moving."""
        still = _still(x)
        prev = None
        for _ in range(SETTLE_TICKS):
            f = r.step(x, still)
            now = np.concatenate([f.proxy_pos.ravel(), f.surface_point.ravel()])
            if prev is not None and np.array_equal(now, prev):
                return
            prev = now

    def _move(self, r: Renderer, x0: np.ndarray, x1: np.ndarray) -> None:
        """Move the fingers from ``x0`` to ``x1`` in straight steps, then settle."""
        span = float(np.max(np.linalg.norm(x1 - x0, axis=1))) if x0.size else 0.0
        n = max(1, math.ceil(span / MOVE_STEP_M))
        still = _still(x1)
        for k in range(1, n):
            r.step(x0 + (x1 - x0) * (k / n), still)
        self._hold(r, x1)

    def _settle(self, x: np.ndarray, state: State | None) -> Renderer:
        if state is None:
            r = self.renderer(self.allocators[0])
            r.step(self._outside(x), _still(x))
            self._hold(r, x)
            return r
        r = _copy_renderer(state._renderer)
        self._move(r, state.x, x)
        return r

    def _read(self, r: Renderer, x: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Full force (p, 3) and, per allocator, the rendered force (p, 3) of a settled
        renderer at ``x`` (re-ticking at a settled configuration moves no proxy)."""
        f = r.frame
        full = f.contact_force + f.env_force
        rendered: dict[str, np.ndarray] = {}
        for m in self.allocators:
            if r.method != m:
                r.set_param("allocator", m)
            r.step(x, _still(x))  # the adaptive allocator's alpha reads this tick's forces
            rendered[m] = f.rendered_force.copy()
        return full.copy(), rendered

    def settle(self, x: Any, state: State | None = None) -> State:
        """The pipeline settled at ``x`` (p, 3) m: from outside, or moved from ``state``."""
        x = self.check(x)
        return State(self._settle(x, state), x)

    # -- the analysis ----------------------------------------------------------------------

    def forces(self, x: Any, state: State | None = None) -> dict[str, Forces]:
        """Per allocator, (full, rendered) forces (p, 3) N on the fingers at ``x`` (p, 3) m,
        settled from outside (or moved from ``state``). Zero out of contact."""
        x = self.check(x)
        full, rendered = self._read(self._settle(x, state), x)
        return {m: Forces(full.copy(), rendered[m]) for m in self.allocators}

    def _derivatives(
        self, x: np.ndarray, state: State | None, h: float
    ) -> tuple[Renderer, np.ndarray, dict[str, np.ndarray], float, dict[str, float]]:
        """Settled base renderer, K_full, K_rendered per allocator (central differences with
        step h) and the error estimates (largest change against step 2h)."""
        base = self._settle(x, state)
        # Perturbations start from the settled base when its state matters (friction, or a
        # given state); frictionless ones settle from outside like x itself.
        anchor = State(base, x) if (state is not None or self.has_friction) else None
        n = x.size
        est: dict[float, tuple[np.ndarray, dict[str, np.ndarray]]] = {}
        for step in (h, 2.0 * h):
            Kf = np.zeros((n, n))
            Kr = {m: np.zeros((n, n)) for m in self.allocators}
            for j in range(n):
                e = np.zeros(n)
                e[j] = step
                e = e.reshape(x.shape)
                fp, rp = self._read(self._settle(x + e, anchor), x + e)
                fm, rm = self._read(self._settle(x - e, anchor), x - e)
                Kf[:, j] = (fp - fm).ravel() / (2.0 * step)
                for m in self.allocators:
                    Kr[m][:, j] = (rp[m] - rm[m]).ravel() / (2.0 * step)
            est[step] = (Kf, Kr)
        Kf, Kr = est[h]
        Kf2, Kr2 = est[2.0 * h]
        err_full = float(np.max(np.abs(Kf - Kf2))) if n else 0.0
        err = {
            m: max(err_full, float(np.max(np.abs(Kr[m] - Kr2[m]))) if n else 0.0)
            for m in self.allocators
        }
        return base, Kf, Kr, err_full, err

    def linearize(
        self, x: Any, state: State | None = None, step: float = FD_STEP_M
    ) -> dict[str, Linearization]:
        """Per allocator, the seed's analysis at ``x`` (p, 3) m (see ``Linearization``).

        No contact gives zero matrices, asymmetry 0 and every direction null.
        """
        x = self.check(x)
        if not (step > 0 and math.isfinite(step)):
            raise ValueError(f"step must be a positive length in m, got {step!r}")
        base, Kf, Kr, _, err = self._derivatives(x, state, step)
        full, rendered = self._read(base, x)
        n = x.size
        M = self.actuation.matrix(x)
        r = _rank(M)
        out = {}
        for m in self.allocators:
            work, plane = loop_work_rate(Kr[m])
            out[m] = Linearization(
                allocator=m,
                x=x.copy(),
                in_contact=base.frame.in_contact.astype(bool),
                full_force=full.copy(),
                rendered_force=rendered[m],
                K_full=Kf.copy(),
                K_rendered=Kr[m],
                asymmetry=asymmetry(Kr[m]),
                n=n,
                s=n,
                r=r,
                controllability=1.0,
                observability=r / n,
                null_directions=null_directions(Kr[m]),
                work_per_area=work,
                work_plane=plane,
                fd_step=step,
                fd_error=err[m],
                labels=self.labels,
            )
        return out

    def linearize_coordinates(
        self,
        coords: Callable[[np.ndarray], Any],
        q: Any,
        state: State | None = None,
        steps: tuple[float, float] = COORD_STEPS,
        labels: Sequence[str] | None = None,
    ) -> dict[str, Linearization]:
        """Per allocator, the analysis in generalized coordinates q (m,), fingers at
        x = coords(q) (p, 3) m: generalized forces Q = J^T F with J = dx/dq, and
        K = dQ/dq = J^T K_x J + sum_a F_a d^2 x_a / dq^2 (the second term: the force
        turning with the coordinates). n = m, s = rank J, r = rank(J^T M_a).

        J and the second derivatives of coords are central differences with ``steps``
        (first, second), in the coordinates' units.
        """
        q = np.asarray(q, dtype=float).reshape(-1)
        if not np.all(np.isfinite(q)):
            raise ValueError(f"q must be finite, got {q.tolist()}")
        m_ = q.size
        h1, h2 = steps

        def at(v: np.ndarray) -> np.ndarray:
            return self.check(coords(v), "coords(q)").ravel()

        x0 = at(q)
        J = np.zeros((x0.size, m_))
        H = np.zeros((x0.size, m_, m_))
        for j in range(m_):
            e1 = np.zeros(m_)
            e1[j] = h1
            J[:, j] = (at(q + e1) - at(q - e1)) / (2.0 * h1)
            ej = np.zeros(m_)
            ej[j] = h2
            H[:, j, j] = (at(q + ej) - 2.0 * x0 + at(q - ej)) / (h2 * h2)
            for k in range(j + 1, m_):
                ek = np.zeros(m_)
                ek[k] = h2
                H[:, j, k] = H[:, k, j] = (
                    at(q + ej + ek) - at(q + ej - ek) - at(q - ej + ek) + at(q - ej - ek)
                ) / (4.0 * h2 * h2)
        cart = self.linearize(x0.reshape(-1, 3), state)
        M = self.actuation.matrix(x0.reshape(-1, 3))
        s = _rank(J)
        r = _rank(J.T @ M)
        names = tuple(labels) if labels is not None else tuple(f"q{i}" for i in range(m_))
        if len(names) != m_:
            raise ValueError(f"{len(names)} labels for {m_} coordinates")
        out = {}
        for name, lin in cart.items():
            Ff = lin.full_force.ravel()
            Fr = lin.rendered_force.ravel()
            Kf = J.T @ lin.K_full @ J + np.einsum("a,ajk->jk", Ff, H)
            Kr = J.T @ lin.K_rendered @ J + np.einsum("a,ajk->jk", Fr, H)
            work, plane = loop_work_rate(Kr)
            out[name] = Linearization(
                allocator=name,
                x=lin.x,
                in_contact=lin.in_contact,
                full_force=lin.full_force,
                rendered_force=lin.rendered_force,
                K_full=Kf,
                K_rendered=Kr,
                asymmetry=asymmetry(Kr),
                n=m_,
                s=s,
                r=r,
                controllability=s / m_,
                observability=r / m_,
                null_directions=null_directions(Kr),
                work_per_area=work,
                work_plane=plane,
                fd_step=lin.fd_step,
                fd_error=float(np.abs(J).max() ** 2 * lin.fd_error) if J.size else 0.0,
                labels=names,
                q=q.copy(),
                Q_full=J.T @ Ff,
                Q_rendered=J.T @ Fr,
            )
        return out

    def loop_work(
        self,
        path: Any,
        state: State | None = None,
        closure_tol_m: float = CLOSURE_TOL_M,
    ) -> dict[str, Work]:
        """Per allocator, the work (J) the full and rendered forces do on the fingers along
        the closed ``path`` (N, p, 3) m: sum over fingers of the integral of F . dx, by the
        trapezoid rule over the samples. Quasi-static: the fingers rest at each sample
        (the proxies settle; friction anchors and proxies carried from sample to sample),
        starting settled at path[0] (or moved there from ``state``).

        Positive work: the display delivers energy to the user (the contact feels
        active); negative: it absorbs energy (passive). A conservative force field does
        none. ValueError for a path whose last point is more than ``closure_tol_m`` (m)
        from its first.
        """
        p = self.n_fingers
        try:
            P = np.asarray(path, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"path must be an array of shape (N, {p}, 3) in m: {exc}") from None
        if P.ndim != 3 or P.shape[1:] != (p, 3) or P.shape[0] < 2:
            raise ValueError(
                f"path must have shape (N, {p}, 3) with N >= 2 samples, one row (m) per finger "
                f"({', '.join(self.finger_names)}); got shape {P.shape}"
            )
        for k in range(P.shape[0]):
            self.check(P[k], f"path[{k}]")
        if not (closure_tol_m >= 0 and math.isfinite(closure_tol_m)):
            raise ValueError(f"closure_tol_m must be a length >= 0 in m, got {closure_tol_m!r}")
        gaps = np.linalg.norm(P[-1] - P[0], axis=1)
        worst = int(np.argmax(gaps))
        if gaps[worst] > closure_tol_m:
            raise ValueError(
                f"the path is not closed: its last point is {gaps[worst]:.3g} m from its first "
                f"(finger {self.finger_names[worst]}); the tolerance is {closure_tol_m:g} m "
                "(end the path where it starts, or pass closure_tol_m)"
            )
        r = self._settle(P[0], state)
        full, rendered = self._read(r, P[0])
        w_full = 0.0
        w_rend = dict.fromkeys(self.allocators, 0.0)
        for k in range(1, P.shape[0]):
            self._move(r, P[k - 1], P[k])
            f2, r2 = self._read(r, P[k])
            dx = P[k] - P[k - 1]
            w_full += 0.5 * float(np.sum((full + f2) * dx))
            for m in self.allocators:
                w_rend[m] += 0.5 * float(np.sum((rendered[m] + r2[m]) * dx))
            full, rendered = f2, r2
        return {m: Work(w_full, w_rend[m]) for m in self.allocators}

    # -- along a recorded motion -------------------------------------------------------------

    def along(
        self,
        positions: Any,
        every: int = 1,
        *,
        object_pos: np.ndarray | None = None,
        object_rot: np.ndarray | None = None,
        stiffness: np.ndarray | None = None,
        progress: Callable[[int, int], None] | None = None,
    ) -> list[Sample]:
        """The analysis at every ``every``-th of ``positions`` (T, p, 3) m (a recording's
        device positions), with the object's pose and stiffness of that tick when given
        ((T, 3) m, (T, 3, 3), (T,) N/m). With friction the state is carried through every
        tick. A tick that cannot be analysed (non-finite, coinciding fingers) is a
        ``Sample`` with ``skipped`` saying why. ``progress(done, total)`` after each."""
        P = np.asarray(positions, dtype=float)
        if P.ndim != 3 or P.shape[1:] != (self.n_fingers, 3):
            raise ValueError(
                f"positions must have shape (T, {self.n_fingers}, 3) in m; got {P.shape}"
            )
        if every < 1:
            raise ValueError(f"every must be a positive number of ticks, got {every}")
        ticks = list(range(0, P.shape[0], every))
        carry = None
        if self.has_friction:  # its own scene: the recorded poses move it
            carry = self.renderer(self.allocators[0], copy.deepcopy(self.scene))
        carry_from = None
        out: list[Sample] = []
        last = -1
        for done, t in enumerate(ticks, 1):
            pose = (
                None if object_pos is None else object_pos[t],
                None if object_rot is None else object_rot[t],
                None if stiffness is None else float(stiffness[t]),
            )
            try:
                pipe = self.at(*pose) if any(v is not None for v in pose) else self
                state = None
                if carry is not None:
                    # Tick the carried renderer through every recorded tick up to t.
                    for u in range(last + 1, t + 1):
                        _place(carry.scene.object, object_pos, object_rot, stiffness, u)
                        xu = P[u]
                        if np.all(np.isfinite(xu)):
                            carry.step(xu, _still(xu))
                            carry_from = xu
                    last = t
                    if carry_from is not None:
                        state = State(carry, carry_from)
                lin = pipe.linearize(P[t], state)
                out.append(Sample(t, P[t].copy(), lin, None))
            except ValueError as exc:
                out.append(Sample(t, P[t].copy(), None, str(exc)))
            if progress is not None:
                progress(done, len(ticks))
        return out


def _place(
    obj: SceneObject,
    pos: np.ndarray | None,
    rot: np.ndarray | None,
    stiffness: np.ndarray | None,
    t: int,
) -> None:
    if pos is None and rot is None and stiffness is None:
        return
    if pos is not None:
        obj.position = np.array(pos[t], dtype=float)
    if rot is not None:
        obj.rotation = np.array(rot[t], dtype=float)
    if stiffness is not None:
        m = obj.material
        obj.material = Material(
            float(stiffness[t]), m.damping, m.mu_static, m.mu_dynamic, m.torsion
        )


class Sample(NamedTuple):
    """One analysed tick of a motion: its index, positions (p, 3) m, and per allocator the
    ``Linearization`` (None when ``skipped`` says why it could not be analysed)."""

    tick: int
    x: np.ndarray
    result: dict[str, Linearization] | None
    skipped: str | None
