"""The renderer's stages: each does one job on the tick frame (``hapticd.frame``).

A stage reads the frame fields earlier stages wrote and writes its own; a stage
that carries state from tick to tick (proxies, friction anchors, the adaptive
allocator, the passivity observer, the object's motion) keeps it itself.
``Renderer`` (hapticd.render) puts the stages a scene needs in order:

    contact -> friction -> forces -> allocation -> environment -> passivity -> dynamics -> scene

Units: positions m, velocities m/s, forces N, stiffness N/m, damping N s/m.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np

from hapticd import kernels
from hapticd.actuation import Actuation
from hapticd.allocation.contacts import ContactAllocator
from hapticd.contact import Polytope
from hapticd.dynamics import auto_substeps
from hapticd.frame import Frame
from hapticd.passivity import PassivityParams, control, observe, orthonormal, project
from hapticd.scene import Material, Scene, SceneObject, Surface

V3 = tuple[float, float, float]
ZERO3: V3 = (0.0, 0.0, 0.0)


class Stage(Protocol):
    """One step of a tick: reads and writes fields of the frame, nothing else of the tick.

    ``reads`` and ``writes`` name the frame fields (hapticd.frame) it reads and writes; the
    renderer refuses a plan in which two stages write one field. A stage that declares
    neither (a test's hook acting at a tick) is taken to touch no field; a test's fault
    injector names the fields it spoils after their writer in ``corrupts``."""

    name: str
    reads: tuple[str, ...]
    writes: tuple[str, ...]

    def run(self, frame: Frame) -> None: ...


HELD = ("proxy_pos", "surface_point", "contact_point")
"""What friction makes of contact's results: the proxy shown, the fingertip's centre held
on the object, the contact point."""
FRICTIONLESS = ("frictionless_proxy", "frictionless_point", "frictionless_contact_point")
"""Contact's results in a plan with friction (friction reads them and writes ``HELD``)."""


class _Fields:
    """The views of some fields of a frame, looked up once per frame and names (a stage
    whose fields the plan binds keeps one: a lookup per tick costs more than the check)."""

    __slots__ = ("_frame", "_names", "views")

    def __init__(self) -> None:
        self._frame: Frame | None = None
        self._names: tuple[str, ...] = ()
        self.views: tuple[np.ndarray, ...] = ()

    def of(self, frame: Frame, names: tuple[str, ...]) -> tuple[np.ndarray, ...]:
        if frame is not self._frame or names is not self._names:
            self.views = tuple(getattr(frame, n) for n in names)
            self._frame, self._names = frame, names
        return self.views


def _kernel(name: str) -> property:
    """A stage's kernel ``name`` (a function of hapticd.kernels): the compiled function
    hapticd.jit gave it, or, set to None, the very same function uncompiled
    (``kernels.uncompiled``: ``rendering.kernels=python``). The stage calls ``_kernel``."""

    def get(stage: object) -> Callable[..., object]:
        return stage._kernel  # type: ignore[attr-defined]

    def put(stage: object, fn: Callable[..., object] | None) -> None:
        stage._kernel = kernels.uncompiled(name) if fn is None else fn  # type: ignore[attr-defined]

    return property(get, put, doc=f"hapticd.kernels.{name}, compiled or not")


def _projector(directions: list[V3]) -> np.ndarray:
    """Orthogonal projector (3, 3) onto the span of a finger's actuated directions."""
    if not directions:
        return np.zeros((3, 3))
    D = np.array(directions).T
    return D @ np.linalg.pinv(D)


class Contact:
    """God-object contact of spherical fingertips with the object, the ground and the walls.

    Writes the god-object proxy (outside every obstacle), the device pushed out of the
    object's active planes only (frictionless) and the contact point into ``outputs``
    (``HELD``: ``proxy_pos``, ``surface_point``, ``contact_point``; in a plan with friction
    the renderer makes them ``FRICTIONLESS``), and ``contact_normal``, ``in_contact`` and
    ``env_force`` (the ground and walls' spring-damper force on each finger). The physics
    is hapticd.kernels.contact_step, compiled or not (``kernel``); a non-finite input
    raises ValueError naming it, with nothing written.
    """

    name = "contact"
    reads = ("device_pos", "device_vel")
    kernel = _kernel("contact_step")

    def __init__(
        self, scene: Scene, radii: list[float], kernel: Callable[..., int] | None = None
    ) -> None:
        self.scene = scene
        self.radii = radii
        self.kernel = kernel
        # hapticd.kernels.world_planes compiled, or None: a free object's planes for the
        # kernel each tick from its pose, without making its polytope.
        self.planes_kernel: Callable[..., None] | None = None
        self._body: tuple[object, np.ndarray, np.ndarray] | None = None  # shape, N, d
        # The proxies (m), the radii, the active planes and the kernel's work space.
        self._state = np.zeros((len(radii), kernels.CONTACT_STATE))
        self._state[:, kernels._C_RADIUS] = radii
        self._proxies = self._state[:, :3]
        self._started = False  # the first tick: every proxy starts at its device
        self._planes: np.ndarray | None = None  # the kernel's planes (PLANE_COLUMNS)
        self._planes_for: Polytope | None = None
        self.outputs = HELD
        self._out = _Fields()
        self.carries = {"proxies": self._state}  # hapticd.frame.STATE

    @property
    def state(self) -> np.ndarray:
        """The proxies (columns 0-2, m), the radii, the active planes and their multipliers,
        and the kernel's work space (F, kernels.CONTACT_STATE), carried from tick to tick."""
        return self._state

    @property
    def writes(self) -> tuple[str, ...]:
        return ("in_contact", "contact_normal", "env_force", *self.outputs)

    def start(self, frame: Frame) -> None:
        """Until a tick with finite device positions: every proxy starts at its device."""
        if not self._started:
            self._proxies[...] = frame.device_pos
            self._started = bool(np.all(np.isfinite(self._proxies)))

    def run(self, frame: Frame) -> None:
        self.start(frame)
        planes = self._kernel_planes()
        out_proxy, out_surface, out_point = self._out.of(frame, self.outputs)
        outcome = self._kernel(
            frame.device_pos,
            frame.device_vel,
            planes,
            self._state,
            out_proxy,
            frame.in_contact,
            out_surface,
            out_point,
            frame.contact_normal,
            frame.env_force,
        )
        if outcome != kernels.CONTACT_DONE:
            raise ValueError(self._non_finite(frame, planes))

    def _non_finite(self, frame: Frame, planes: np.ndarray) -> str:
        """What the kernel refused: the first non-finite input, named."""
        for i in range(len(self.radii)):
            for name, row in (
                ("device_pos", frame.device_pos[i]),
                ("device_vel", frame.device_vel[i]),
                ("proxy", self._proxies[i]),
                ("radius", self._state[i, kernels._C_RADIUS : kernels._C_RADIUS + 1]),
            ):
                if not np.all(np.isfinite(row)):
                    return f"contact: finger {i}'s {name} is not finite ({row.tolist()})"
        bad = np.flatnonzero(~np.all(np.isfinite(planes[:, :4]), axis=1))
        if not len(bad):
            return "contact: the kernel refused the tick with no input non-finite"
        j = int(planes[bad[0], 4])
        what = "the object" if j == 0 else f"surface {self.scene.surfaces[j - 1].name!r}"
        return f"contact: a plane of {what} is not finite (its pose or offset)"

    def _kernel_planes(self) -> np.ndarray:
        """The kernel's planes (hapticd.kernels.PLANE_COLUMNS): the object's, copied again
        only when its polytope changed (a free object's: from its pose, by the planes
        kernel, when there is one), then the surfaces'."""
        obj = self.scene.object
        planes = self._planes
        body = self._body
        move = self.planes_kernel
        if move is not None and not obj.fixed and planes is not None and body is not None:
            try:
                if body[0] is obj.shape:
                    move(obj.rotation, obj.position, body[1], body[2], planes)
                    return planes
            except TypeError:  # a pose the signature does not take: the polytope's way
                pass
        poly = obj.polytope
        if poly is self._planes_for and planes is not None:
            return planes
        m = len(poly.offsets)
        if planes is None or int(planes[0, 6]) != m:
            blocks = [(poly, 0, 0.0, 0.0)]
            blocks += [
                (sf.polytope, j, sf.material.stiffness, sf.material.damping)
                for j, sf in enumerate(self.scene.surfaces, start=1)
            ]
            rows = []
            lo = 0
            for p, j, k, b in blocks:
                hi = lo + len(p.offsets)
                block = np.empty((hi - lo, kernels.PLANE_COLUMNS))
                block[:, 0:3] = p.normals
                block[:, 3] = p.offsets
                block[:, 4:] = (j, lo, hi, k, b)
                rows.append(block)
                lo = hi
            planes = self._planes = np.ascontiguousarray(np.vstack(rows))
        else:
            planes[:m, 0:3] = poly.normals
            planes[:m, 3] = poly.offsets
        self._planes_for = poly
        shape = obj.shape
        if body is None or body[0] is not shape:
            self._body = (
                shape,
                np.ascontiguousarray(shape.normals, dtype=float),
                np.ascontiguousarray(shape.offsets, dtype=float),
            )
        return planes


class Friction:
    """Coulomb stick/slip at each fingertip: moves ``surface_point`` within the friction cone.

    Keeps one anchor per finger in the object's body frame (so a sticking finger
    moves with the object); moves ``proxy_pos`` (the god-object proxy as contact
    wrote it) with the fingertip's point and updates ``contact_point`` to match.
    The anchors live in ``anchors`` (F, kernels.FRICTION_COLUMNS: the anchor (3, m, body
    frame), 1.0 if it is set, the fingertip's radius (m)). The physics is
    hapticd.kernels.friction_step, compiled or not (``kernel``).

    Reads contact's results from ``inputs`` (``FRICTIONLESS`` in the renderer's plan;
    ``HELD`` when run on its own: then it moves them in place) and writes ``HELD``.
    """

    name = "friction"
    outputs = HELD
    kernel = _kernel("friction_step")

    def __init__(
        self, scene: Scene, radii: list[float], kernel: Callable[..., None] | None = None
    ) -> None:
        self.scene = scene
        self.radii = radii
        self.kernel = kernel
        self.anchors = np.zeros((len(radii), kernels.FRICTION_COLUMNS))
        self.anchors[:, kernels.FINGER_RADIUS] = radii
        self.holding = False  # an anchor may be set (out of contact, clear them only then)
        self._params = np.zeros(kernels.FRICTION_PARAMS)
        self._params_for: Material | None = None
        self._inputs = HELD
        self._in = _Fields()
        self.carries = {"friction_anchors": self.anchors}  # hapticd.frame.STATE

    @property
    def inputs(self) -> tuple[str, ...]:
        """The fields it reads contact's results from (``FRICTIONLESS`` or ``HELD``)."""
        return self._inputs

    @inputs.setter
    def inputs(self, names: tuple[str, ...]) -> None:
        self._inputs = HELD if tuple(names) == HELD else tuple(names)

    @property
    def reads(self) -> tuple[str, ...]:
        return ("in_contact", "device_pos", "contact_normal", *self.inputs)

    @property
    def writes(self) -> tuple[str, ...]:
        return self.outputs

    def run(self, frame: Frame) -> None:
        # Contact's results (its proxy, surface point and contact point), where friction
        # starts from.
        god_in, plain_in, point_in = self._in.of(frame, self._inputs)
        # Out of contact the kernel would only copy them: cheaper here than a call.
        if not any(frame.in_contact.tolist()):
            if self.holding:
                self.anchors[:, kernels.ANCHOR_SET] = 0.0
                self.holding = False
            if self._inputs is not HELD:
                frame.proxy_pos[...] = god_in
                frame.surface_point[...] = plain_in
                frame.contact_point[...] = point_in
            return
        self.holding = True
        obj = self.scene.object
        mat = obj.material
        params = self._params
        if mat is not self._params_for:  # a Material is frozen: a change is a new one
            params[0] = mat.mu_static
            params[1] = mat.mu_dynamic
            self._params_for = mat
        self._kernel(
            frame.in_contact,
            frame.device_pos,
            plain_in,
            god_in,
            point_in,
            frame.surface_point,
            frame.contact_normal,
            frame.proxy_pos,
            frame.contact_point,
            self.anchors,
            obj.state,
            params,
        )


class Forces:
    """The full contact force on each finger: k (surface point - device) - b v_rel.

    Damping may slow the finger but never pull it into the object. Writes
    ``contact_force``; zero for a finger out of contact. The physics is
    hapticd.kernels.forces_step, compiled or not (``kernel``).
    """

    name = "forces"
    reads = ("in_contact", "device_pos", "device_vel", "surface_point", "contact_normal")
    writes = ("contact_force",)
    kernel = _kernel("forces_step")

    def __init__(self, scene: Scene, kernel: Callable[..., None] | None = None) -> None:
        self.scene = scene
        self.kernel = kernel
        self._params = np.zeros(kernels.FORCES_PARAMS)
        self._params_for: tuple[Material, bool] | None = None
        self._still = np.zeros(kernels.STATE)  # a fixed object's motion: none is read

    def run(self, frame: Frame) -> None:
        # Out of contact: zero, cheaper here than a call to the kernel.
        if not any(frame.in_contact.tolist()):
            frame.contact_force.fill(0.0)
            return
        obj = self.scene.object
        mat, fixed = obj.material, obj.fixed
        made = self._params_for
        if made is None or made[0] is not mat or made[1] != fixed:
            self._params[0] = mat.stiffness
            self._params[1] = mat.damping
            self._params[2] = 0.0 if fixed else 1.0
            self._params_for = (mat, fixed)
        self._kernel(
            frame.in_contact,
            frame.device_pos,
            frame.device_vel,
            frame.surface_point,
            frame.contact_normal,
            frame.contact_force,
            self._still if fixed else obj.state,
            self._params,
        )


class Allocation:
    """Projects the full contact forces onto the actuated directions (``ContactAllocator``).

    Writes ``lam_a``, M_a lam_a per finger (zero out of contact) into ``output``
    (``rendered_force``, or ``allocated_force`` when the plan sums more than this into the
    rendered force), the four accuracy measures and ``alpha``.
    """

    name = "allocation"
    reads = ("in_contact", "device_pos", "contact_point", "contact_force")

    def __init__(
        self, scene: Scene, allocator: ContactAllocator, kernel: Callable[..., int] | None = None
    ) -> None:
        self.scene = scene
        self.allocator = allocator
        self.kernel = kernel
        self._out = _Fields()
        self._output = ("rendered_force",)

    @property
    def kernel(self) -> Callable[..., int]:
        """hapticd.kernels.allocation_step, compiled (hapticd.jit) or, set to None, not: the
        allocator's (it takes the robust methods with one direction per finger, any number
        of contacts, and adaptive's alpha; the rest run allocate())."""
        return self.allocator.kernel

    @kernel.setter
    def kernel(self, fn: Callable[..., int] | None) -> None:
        self.allocator.kernel = fn

    @property
    def output(self) -> str:
        """The field M_a lam_a goes to: ``rendered_force`` or ``allocated_force``."""
        return self._output[0]

    @output.setter
    def output(self, name: str) -> None:
        if name != self._output[0]:
            self._output = (name,)

    @property
    def carries(self) -> dict[str, object]:
        return {"allocator_blend": self.allocator.alpha}  # hapticd.frame.STATE

    @property
    def writes(self) -> tuple[str, ...]:
        return (
            "lam_a",
            "residual_internal",
            "residual_external",
            "residual_total",
            "amplification",
            "alpha",
            self.output,
        )

    @property
    def actuation(self) -> Actuation:
        return self.allocator.actuation

    def run(self, frame: Frame) -> None:
        alloc = self.allocator
        acc = alloc.allocate(
            frame.in_contact,
            frame.device_pos,
            frame.contact_point,
            frame.contact_force,
            self.scene.object.position,
            frame.lam_a,
            self._out.of(frame, self._output)[0],
        )
        frame.alpha[()] = alloc.alpha
        frame.residual_internal[()] = acc[0]
        frame.residual_external[()] = acc[1]
        frame.residual_total[()] = acc[2]
        frame.amplification[()] = acc[3]

    def kernel_inputs(self) -> tuple[np.ndarray, np.ndarray] | None:
        """allocation_step's ``local`` and ``params`` for one call per tick, or None
        (``ContactAllocator.kernel_inputs``)."""
        return self.allocator.kernel_inputs()


class Environment:
    """Renders the ground's and walls' force through each finger's own actuated directions:
    writes ``env_rendered`` (the output stage adds it to the rendered force)."""

    name = "environment"
    reads = ("env_force", "device_pos")
    writes = ("env_rendered",)

    def __init__(self, actuation: Actuation) -> None:
        self.actuation = actuation
        self.zero_on: Frame | None = None  # the frame whose env_rendered is all zero

    def run(self, frame: Frame) -> None:
        env = frame.env_force.tolist()
        if not any(any(e) for e in env):  # plain floats: numpy's any() costs more here
            if frame is not self.zero_on:
                frame.env_rendered.fill(0.0)
                self.zero_on = frame
            return
        self.zero_on = None
        out = frame.env_rendered
        world = self.actuation.world_directions(frame.device_pos.tolist())
        for i, e in enumerate(env):
            if any(e):
                out[i] = _projector(world[i]) @ np.array(e)
            else:
                out[i] = 0.0


class Output:
    """The rendered force: the allocated force plus the other contributions the plan has
    (``parts``: field and stage, the environment's, then the passivity controller's), in
    that order; the only writer of ``rendered_force``. A contribution whose stage says it
    is all zero on this frame (its ``zero_on``) is not added: the same numbers."""

    name = "output"
    writes = ("rendered_force",)

    def __init__(self, parts: list[tuple[str, Environment | Passivity]]) -> None:
        if not parts:
            raise ValueError("the output stage sums two or more contributions")
        self.reads = ("allocated_force", *(name for name, _ in parts))
        self._parts = parts
        self._frame: Frame | None = None
        self._more: list[tuple[np.ndarray, Environment | Passivity]] = []

    def run(self, frame: Frame) -> None:
        if frame is not self._frame:
            self._frame = frame
            self._more = [(getattr(frame, name), stage) for name, stage in self._parts]
        out = frame.rendered_force
        total = frame.allocated_force
        for view, stage in self._more:
            if stage.zero_on is not frame:
                np.add(total, view, out=out)
                total = out
        if total is not out:
            out[...] = total


class Passivity:
    """Time-domain passivity per finger (hapticd.passivity): observes the energy each finger's
    port has absorbed and adds the least damping along that finger's actuated directions
    that keeps it from going negative.

    Observes the sum of the contributions before it (``inputs``: the allocated force, and
    the environment's with ground or walls), the whole rendered force but its own;
    writes its damping force to ``passivity_force`` (the output stage adds it),
    ``passivity_energy`` (J) and ``passivity_damping`` (N s/m) every tick. Keeps each
    finger's observed energy and last position; the first tick sees no motion.
    """

    name = "passivity"
    writes = ("passivity_force", "passivity_energy", "passivity_damping")

    def __init__(
        self, allocator: ContactAllocator, params: PassivityParams, n_fingers: int, dt: float
    ) -> None:
        self.allocator = allocator  # its actuation is read every tick: it may change live
        self.params = params
        self.dt = dt
        # The state it carries (hapticd.frame.STATE): each finger's observed energy (J) and
        # last position (m; None before the first tick, which sees no motion).
        self.energy = [0.0] * n_fingers
        self._damping = [0.0] * n_fingers
        self.last_pos: list[list[float]] | None = None
        self._basis_for: Actuation | None = None
        self._basis: list[list[V3]] = []
        self.inputs: tuple[str, ...] = ("allocated_force",)
        self.zero_on: Frame | None = None  # the frame whose passivity_force is all zero

    @property
    def reads(self) -> tuple[str, ...]:
        return ("device_pos", *self.inputs)

    @property
    def carries(self) -> dict[str, object]:
        # hapticd.frame.STATE
        return {"passivity_energy": self.energy, "passivity_last_pos": self.last_pos}

    def _bases(self, pos: list[list[float]]) -> list[list[V3]]:
        """Orthonormal bases of each finger's actuated directions in the world (cached while
        they cannot change: world-frame directions of the same actuation)."""
        act = self.allocator.actuation
        if act is self._basis_for:
            return self._basis
        world = act.world_directions(pos)  # type: ignore[arg-type]
        self._basis = [orthonormal(ds) for ds in world]
        self._basis_for = act if act.frame == "world" else None
        return self._basis

    def run(self, frame: Frame) -> None:
        pos = frame.device_pos.tolist()
        prev = self.last_pos if self.last_pos is not None else pos
        self.last_pos = pos
        first, *rest = self.inputs
        forces = getattr(frame, first).tolist()
        for name in rest:  # the same sums the output stage makes
            more = getattr(frame, name).tolist()
            forces = [
                [a[0] + b[0], a[1] + b[1], a[2] + b[2]] for a, b in zip(forces, more, strict=True)
            ]
        added = [ZERO3] * len(forces)
        energy, damping = self.energy, self._damping
        dt, params = self.dt, self.params
        bases = None
        damped = False
        for i, f in enumerate(forces):
            x, xp = pos[i], prev[i]
            dx = (x[0] - xp[0], x[1] - xp[1], x[2] - xp[2])
            e = observe(energy[i], f, dx)
            alpha = 0.0
            if e < 0.0:  # only then the controller needs the actuated motion
                if bases is None:
                    bases = self._bases(pos)
                du = project(bases[i], dx)
                e, alpha = control(e, du, dt, params)
                if alpha > 0.0:
                    c = alpha / dt  # the damping force is -alpha P_a v, v = dx / T
                    added[i] = (-(c * du[0]), -(c * du[1]), -(c * du[2]))
                    damped = True
            elif not e >= 0.0:  # NaN: a non-finite position or force; keep the last energy
                e = energy[i]
            energy[i] = e
            damping[i] = alpha
        frame.passivity_energy[...] = energy
        frame.passivity_damping[...] = damping
        if damped:
            frame.passivity_force[...] = added
            self.zero_on = None
        elif frame is not self.zero_on:  # zero once per frame (a reload keeps the loop's)
            frame.passivity_force.fill(0.0)
            self.zero_on = frame


class Dynamics:
    """Moves a free object one tick under the fingers' reactions, gravity, ground and walls.

    The fingers act as springs that move with the object during the tick's
    substeps; soft-finger contacts resist spin about their normals. Writes the
    object's pose to the scene (the next tick's contact sees it). The physics is
    hapticd.kernels.free_body_step, compiled or not (``kernel``), for any shape.
    """

    name = "dynamics"
    reads = ("in_contact", "contact_point", "contact_force", "contact_normal")
    writes = ()  # the object's pose and motion (the scene's object)
    kernel = _kernel("free_body_step")

    def __init__(
        self, scene: Scene, n_fingers: int, dt: float, kernel: Callable[..., None] | None = None
    ) -> None:
        self.scene = scene
        obj = scene.object
        self.dt = dt
        self.kernel = kernel
        self.gravity = scene.gravity
        self.substeps = scene.substeps
        if scene.substeps == 0:  # auto
            self.substeps = auto_substeps(
                obj, scene.surfaces, obj.material.stiffness, n_fingers, dt
            )
        self._arrays: _BodyArrays | None = None  # the kernel's (shape, mass, surfaces)
        self._scratch = np.zeros((n_fingers, kernels.SCRATCH_COLUMNS))
        self._gravity = np.zeros(3) if self.gravity is None else np.array(self.gravity, float)

    @property
    def carries(self) -> dict[str, object]:
        return {"object_state": self.scene.object.state}  # hapticd.frame.STATE

    @property
    def effects(self) -> list[str]:
        """What moves the object besides the fingers."""
        return (["gravity"] if self.gravity is not None else []) + (
            ["surfaces"] if self.scene.surfaces else []
        )

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """free_body_step's params, body, surfaces and scratch for the object as it is now
        (its shape, mass and material)."""
        obj = self.scene.object
        arr = self._arrays
        if arr is None or not arr.fits(obj):
            arr = self._arrays = _BodyArrays(obj, self.scene.surfaces, self.dt, self.substeps)
            arr.params[6:9] = self._gravity
        mat = obj.material
        arr.params[0] = mat.stiffness
        arr.params[1] = mat.torsion
        return arr.params, arr.body, arr.surf, self._scratch

    def run(self, frame: Frame) -> None:
        """The step on the frame's arrays and the object's ``state`` (its position,
        velocity, omega and rotation are views of it)."""
        obj = self.scene.object
        params, body, surf, scratch = self.arrays()
        self._kernel(
            frame.in_contact,
            frame.contact_point,
            frame.contact_force,
            frame.contact_normal,
            params,
            obj.state,
            body,
            surf,
            scratch,
        )
        obj.update_world()


class _BodyArrays:
    """The free-body kernel's arrays for an object's shape and mass and the surfaces
    (hapticd.kernels.free_body_step says the layouts): params, body (inertia, its inverse
    and the vertices, body frame) and surfaces (normal, offset, stiffness, damping, dynamic
    friction). The object's state is its ``state``."""

    def __init__(self, obj: SceneObject, surfaces: list[Surface], dt: float, substeps: int) -> None:
        self.shape, self.mass = obj.shape, obj.mass
        local = obj.shape.vertices.tolist()
        # The farthest vertex from the centre of mass (m): surfaces farther away are skipped.
        reach = max((math.sqrt(x * x + y * y + z * z) for x, y, z in local), default=0.0)
        self.params = np.zeros(kernels.PARAMS)
        self.params[2:6] = (obj.mass, dt, substeps, reach)
        inertia = obj.inertia_body
        self.body = np.array(
            [*inertia.tolist(), *np.linalg.inv(inertia).tolist(), *local], dtype=float
        ).reshape(-1, 3)
        self.surf = np.zeros((len(surfaces), kernels.SURFACE_COLUMNS))
        for row, surface in zip(self.surf, surfaces, strict=True):
            m = surface.material
            row[:] = (*surface.normal, surface.offset, m.stiffness, m.damping, m.mu_dynamic)

    def fits(self, obj: SceneObject) -> bool:
        return obj.shape is self.shape and obj.mass == self.mass


class SceneState:
    """Publishes the scene's state after the tick: the object's pose and motion (its state,
    in one copy), stiffness and mass, and the allocator in use (an index into ``methods``).

    Made anew whenever the plan changes, so the parameters are written once per frame
    and the pose on every tick only when the object can move.
    """

    name = "scene"
    reads = ()
    writes = (
        "object_pos",
        "object_vel",
        "object_omega",
        "object_rot",
        "stiffness_n_per_m",
        "mass_kg",
        "allocator",
    )

    def __init__(self, scene: Scene, allocator: ContactAllocator, methods: tuple[str, ...]) -> None:
        self.scene = scene
        self.allocator = allocator
        self.methods = methods
        self._written: Frame | None = None
        self._state = np.zeros(18)

    def run(self, frame: Frame) -> None:
        obj = self.scene.object
        if frame is self._written and obj.fixed:
            return
        if frame is not self._written:
            self._state = _object_fields(frame)
        self._state[...] = obj.state
        if frame is not self._written:
            frame.stiffness_n_per_m[()] = obj.material.stiffness
            frame.mass_kg[()] = obj.mass
            frame.allocator[()] = self.methods.index(self.allocator.method)
            self._written = frame


def _object_fields(frame: Frame) -> np.ndarray:
    """The frame's object_pos, object_vel, object_omega and object_rot as one (18,) float
    view, in SceneObject.state's order (they are adjacent in the record)."""
    return adjacent(frame, ("object_pos", "object_vel", "object_omega", "object_rot"))


def adjacent(frame: Frame, names: tuple[str, ...]) -> np.ndarray:
    """The frame's float64 fields ``names``, adjacent in the record in this order, as one
    flat view (RuntimeError if they are not)."""
    fields = frame.dtype.fields
    start = at = fields[names[0]][1]
    for name in names:
        if fields[name][1] != at or fields[name][0].base != np.float64:
            raise RuntimeError(f"frame fields: {', '.join(names)} must be adjacent float64")
        at += fields[name][0].itemsize
    raw = frame.record.reshape(1).view(np.uint8)[start:at]
    return raw.view("<f8")
