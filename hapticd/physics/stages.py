"""The renderer's stages: each does one job on the tick frame (``hapticd.physics.frame``).

A stage declares the frame fields it reads and writes, the state it carries from tick
to tick (``carries``: hapticd.physics.frame.STATE) and its part of the tick's one call
(``kernel_stage``, a ``hapticd.physics.kernels.STAGE_`` index: the call runs its physics).
``Renderer`` (hapticd.physics.render) puts the stages a scene needs in order:

    contact -> friction -> forces -> allocation -> environment -> passivity -> output
    -> dynamics -> scene

A stage the call has is a declaration (no ``run``); a stage it does not have (Allocation
for what its kernel does not take, a stage inserted into the plan) runs in Python
(``run(frame)``) between the call's parts.

Units: positions m, velocities m/s, forces N, stiffness N/m, damping N s/m.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np

from hapticd.allocation.contacts import ContactAllocator
from hapticd.physics import kernels
from hapticd.physics.actuation import Actuation
from hapticd.physics.dynamics import auto_substeps
from hapticd.physics.frame import Frame
from hapticd.physics.passivity import PassivityParams
from hapticd.physics.scene import Scene, SceneObject, Surface


class Stage(Protocol):
    """One step of a tick: reads and writes fields of the frame, nothing else of the tick.

    ``reads`` and ``writes`` name the frame fields (hapticd.physics.frame) it reads and writes; the
    renderer refuses a plan in which two stages write one field. A stage that declares
    neither (a test's hook acting at a tick) is taken to touch no field; a test's fault
    injector names the fields it spoils after their writer in ``corrupts``. A stage of the
    tick's one call names its part (``kernel_stage``); any other runs in Python (``run``)."""

    name: str
    reads: tuple[str, ...]
    writes: tuple[str, ...]


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


class Contact:
    """God-object contact of spherical fingertips with the object, the ground and the walls.

    Writes the god-object proxy (outside every obstacle), the device pushed out of the
    object's active planes only (frictionless) and the contact point into ``outputs``
    (``HELD``: ``proxy_pos``, ``surface_point``, ``contact_point``; in a plan with friction
    the renderer makes them ``FRICTIONLESS``), and ``contact_normal``, ``in_contact`` and
    ``env_force`` (the ground and walls' spring-damper force on each finger). Its physics
    is the one call's (hapticd.physics.kernels.contact_step); a non-finite input stops the call,
    with nothing written, and ``_non_finite`` names it.
    """

    name = "contact"
    reads = ("device_pos", "device_vel")
    kernel_stage = kernels.STAGE_CONTACT

    def __init__(self, scene: Scene, radii: list[float], state: np.ndarray | None = None) -> None:
        self.scene = scene
        self.radii = radii
        # The proxies (m), the radii, the active planes and the kernel's work space: a view
        # of the renderer's state (hapticd.physics.kernels.TICK_STATE), or its own.
        if state is None:
            state = np.zeros((len(radii), kernels.CONTACT_STATE))
        state[:, kernels._C_RADIUS] = radii
        self.state = state
        self._started = False  # the first tick: every proxy starts at its device
        self.outputs = HELD

    @property
    def state(self) -> np.ndarray:
        """The proxies (columns 0-2, m), the radii, the active planes and their multipliers,
        and the kernel's work space (F, kernels.CONTACT_STATE), carried from tick to tick."""
        return self._state

    @state.setter
    def state(self, state: np.ndarray) -> None:
        self._state = state
        self._proxies = state[:, :3]
        self.carries = {"proxies": state}  # hapticd.physics.frame.STATE

    @property
    def writes(self) -> tuple[str, ...]:
        return ("in_contact", "contact_normal", "env_force", *self.outputs)

    def start(self, frame: Frame) -> bool:
        """Until a tick with finite device positions: every proxy starts at its device.
        Whether they have started."""
        if not self._started:
            self._proxies[...] = frame.device_pos
            self._started = bool(np.all(np.isfinite(self._proxies)))
        return self._started

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
        """The kernel's planes (hapticd.physics.kernels.PLANE_COLUMNS): the object's faces at
        its pose (the one call puts them there itself each tick: kernels.world_planes), then
        the surfaces'."""
        blocks = [(self.scene.object.polytope, 0, 0.0, 0.0)]
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
        return np.vstack(rows)


class Friction:
    """Coulomb stick/slip at each fingertip: moves ``surface_point`` within the friction cone.

    Keeps one anchor per finger in the object's body frame (so a sticking finger
    moves with the object); moves ``proxy_pos`` (the god-object proxy as contact
    wrote it) with the fingertip's point and updates ``contact_point`` to match.
    The anchors live in ``anchors`` (F, kernels.FRICTION_COLUMNS: the anchor (3, m, body
    frame), 1.0 if it is set, the fingertip's radius (m)). Its physics is the one call's
    (hapticd.physics.kernels.friction_step).

    Reads contact's results (``FRICTIONLESS``) and writes ``HELD``.
    """

    name = "friction"
    reads = ("in_contact", "device_pos", "contact_normal", *FRICTIONLESS)
    writes = HELD
    kernel_stage = kernels.STAGE_FRICTION

    def __init__(self, radii: list[float], anchors: np.ndarray | None = None) -> None:
        # A view of the renderer's state (hapticd.physics.kernels.TICK_STATE), or its own.
        if anchors is None:
            anchors = np.zeros((len(radii), kernels.FRICTION_COLUMNS))
        anchors[:, kernels.FINGER_RADIUS] = radii
        self.anchors = anchors

    @property
    def carries(self) -> dict[str, object]:
        return {"friction_anchors": self.anchors}  # hapticd.physics.frame.STATE


class Forces:
    """The full contact force on each finger: k (surface point - device) - b v_rel.

    Damping may slow the finger but never pull it into the object. Writes
    ``contact_force``; zero for a finger out of contact. Its physics is the one call's
    (hapticd.physics.kernels.forces_step).
    """

    name = "forces"
    reads = ("in_contact", "device_pos", "device_vel", "surface_point", "contact_normal")
    writes = ("contact_force",)
    kernel_stage = kernels.STAGE_FORCES


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
        """hapticd.physics.kernels.allocation_step, compiled (hapticd.physics.jit) or, set to None,
        not: the allocator's (it takes the robust methods; the exact ones run allocate())."""
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
        return {"allocator_blend": self.allocator.alpha}  # hapticd.physics.frame.STATE

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

    @property
    def kernel_stage(self) -> int | None:
        """kernels.STAGE_ALLOCATION when the one call allocates for this allocator (its
        ``kernel_inputs``), else None: the stage runs here, between the call's parts."""
        return None if self.kernel_inputs() is None else kernels.STAGE_ALLOCATION

    def kernel_inputs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """allocation_step's ``local``, ``counts`` and ``params`` for one call per tick, or
        None (``ContactAllocator.kernel_inputs``)."""
        return self.allocator.kernel_inputs()


class Environment:
    """Renders the ground's and walls' force through each finger's own actuated directions
    (its projection onto their span): writes ``env_rendered`` (the sum adds it to the
    rendered force). Its physics is in the tick's one call (hapticd.physics.kernels.tick_step)."""

    name = "environment"
    reads = ("env_force", "device_pos")
    writes = ("env_rendered",)
    kernel_stage = kernels.STAGE_ENVIRONMENT


class Output:
    """The rendered force: the allocated force plus the other contributions the plan has
    (``parts``: the environment's, then the passivity controller's fields), in that order;
    the only writer of ``rendered_force``. Its sum is in the tick's one call."""

    name = "output"
    writes = ("rendered_force",)
    kernel_stage = kernels.STAGE_SUM

    def __init__(self, parts: list[str]) -> None:
        if not parts:
            raise ValueError("the output stage sums two or more contributions")
        self.reads = ("allocated_force", *parts)


class Passivity:
    """Time-domain passivity per finger (hapticd.physics.passivity): observes the energy each
    finger's port has absorbed and adds the least damping along that finger's actuated directions
    that keeps it from going negative.

    Observes the sum of the contributions before it (``inputs``: the allocated force, and
    the environment's with ground or walls), the whole rendered force but its own;
    writes its damping force to ``passivity_force`` (the output stage adds it),
    ``passivity_energy`` (J) and ``passivity_damping`` (N s/m) every tick. Its physics is
    in the tick's one call (hapticd.physics.kernels.tick_step); it carries ``state`` (F,
    kernels.PASSIVITY_STATE): each finger's observed energy and last position.
    """

    name = "passivity"
    writes = ("passivity_force", "passivity_energy", "passivity_damping")
    kernel_stage = kernels.STAGE_PASSIVITY

    def __init__(
        self, params: PassivityParams, n_fingers: int, dt: float, state: np.ndarray | None = None
    ) -> None:
        self.params = params
        self.dt = dt
        # A view of the renderer's state (hapticd.physics.kernels.TICK_STATE), or its own.
        self.state = np.zeros((n_fingers, kernels.PASSIVITY_STATE)) if state is None else state
        self.inputs: tuple[str, ...] = ("allocated_force",)

    @property
    def reads(self) -> tuple[str, ...]:
        return ("device_pos", *self.inputs)

    @property
    def carries(self) -> dict[str, object]:
        # hapticd.physics.frame.STATE
        return {"passivity_energy": self.energy, "passivity_last_pos": self.last_pos}

    @property
    def energy(self) -> np.ndarray:
        """Each finger's observed energy (F,) J: a view of ``state``, settable."""
        return self.state[:, 0]

    @property
    def last_pos(self) -> np.ndarray | None:
        """Each finger's position on the last tick (F, 3) m, None before the first."""
        return self.state[:, 1:4] if self.state[:, 4].all() else None

    @last_pos.setter
    def last_pos(self, pos: object) -> None:
        self.state[:, 4] = 0.0 if pos is None else 1.0
        if pos is not None:
            self.state[:, 1:4] = pos

    @property
    def kernel_params(self) -> tuple[float, float, float]:
        """Its params in the one call: velocity threshold (m/s), most damping (N s/m), dt (s)."""
        p = self.params
        return (p.velocity_threshold, p.max_damping, self.dt)


class Dynamics:
    """Moves a free object one tick under the fingers' reactions, gravity, ground and walls.

    The fingers act as springs that move with the object during the tick's
    substeps; soft-finger contacts resist spin about their normals. Writes the
    object's pose to the scene (the next tick's contact sees it). Its physics is the one
    call's (hapticd.physics.kernels.free_body_step), for any shape, on ``arrays``.
    """

    name = "dynamics"
    reads = ("in_contact", "contact_point", "contact_force", "contact_normal")
    writes = ()  # the object's pose and motion (the scene's object)
    kernel_stage = kernels.STAGE_DYNAMICS

    def __init__(self, scene: Scene, n_fingers: int, dt: float) -> None:
        self.scene = scene
        obj = scene.object
        self.dt = dt
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
        return {"object_state": self.scene.object.state}  # hapticd.physics.frame.STATE

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


class _BodyArrays:
    """The free-body kernel's arrays for an object's shape and mass and the surfaces
    (hapticd.physics.kernels.free_body_step says the layouts): params, body (inertia, its inverse
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
    in one copy, by the one call), stiffness and mass, and the allocator in use (an index
    into hapticd.allocation.METHODS; written when the call binds the frame)."""

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
    kernel_stage = kernels.STAGE_SCENE


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
