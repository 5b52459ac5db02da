"""The renderer's stages, each one job on the tick frame: the fields it reads and writes,
the state it carries (``carries``) and its part of the one call (``kernel_stage``) or,
lacking one, ``run(frame)`` in Python. The picture: docs/architecture.md, "One tick".

Units: positions m, velocities m/s, forces N, stiffness N/m, damping N s/m.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np

from hapticd.allocation.actuation import Actuation
from hapticd.allocation.contacts import ContactAllocator
from hapticd.physics import kernels
from hapticd.physics.dynamics import auto_substeps
from hapticd.physics.frame import Frame
from hapticd.physics.passivity import PassivityParams
from hapticd.physics.scene import Scene
from hapticd.physics.tick import allocation as allocation_stage
from hapticd.physics.tick import contact, dynamics, environment, forces, friction, passivity
from hapticd.physics.tick.output import OUTPUT


class Stage(Protocol):
    """One step of a tick: reads and writes frame fields, nothing else of the tick (one that
    declares neither, a test's hook, touches none)."""

    name: str
    reads: tuple[str, ...]
    writes: tuple[str, ...]


# The accuracy's fields, in ContactAllocator.allocate's order.
_ACCURACY = ("residual_internal", "residual_external", "residual_total", "amplification")

HELD = friction.HELD
"""The proxy shown, the fingertip's centre held on the object, the contact point."""
FRICTIONLESS = friction.FRICTIONLESS
"""Contact's results when friction then moves them into ``HELD``."""


class Contact:
    """God-object contact of spherical fingertips with the object, the ground and the walls.

    Writes the proxy (outside every obstacle), the device pushed out of the object's
    active planes only, and the contact point into ``outputs`` (HELD or FRICTIONLESS),
    with ``in_contact``, ``contact_normal`` and ``env_force`` (the ground's and walls'
    spring-damper force). The call stops at a non-finite input; ``_non_finite`` names it.
    """

    name = "contact"
    reads = contact.DECLARATION.reads
    kernel_stage = kernels.STAGE_CONTACT

    def __init__(self, scene: Scene, radii: list[float], state: np.ndarray | None = None) -> None:
        self.scene = scene
        self.radii = radii
        # A view of the renderer's state, or its own.
        if state is None:
            state = np.zeros((len(radii), kernels.CONTACT_STATE))
        state[:, kernels._C_RADIUS] = radii
        self.state = state
        self._started = False  # the first tick: every proxy starts at its device
        self.outputs = HELD

    @property
    def state(self) -> np.ndarray:
        """(F, kernels.CONTACT_STATE): the proxies (columns 0-2, m), the radii, the active
        planes and their multipliers, the kernel's work space."""
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
        """Start every proxy at its device, until a tick whose positions are finite; whether
        they have started."""
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
        """The kernel's planes (P, kernels.PLANE_COLUMNS): the object's faces (the call
        moves them to its pose each tick), then the surfaces'."""
        blocks = [(self.scene.object.polytope, 0.0, 0.0)]
        blocks += [
            (sf.polytope, sf.material.stiffness, sf.material.damping) for sf in self.scene.surfaces
        ]
        rows = []
        lo = 0
        for j, (p, k, b) in enumerate(blocks):
            hi = lo + len(p.offsets)
            rows.append(
                np.column_stack([p.normals, p.offsets, np.tile((j, lo, hi, k, b), (hi - lo, 1))])
            )
            lo = hi
        return np.vstack(rows)


class Friction:
    """Coulomb stick/slip at each fingertip: reads FRICTIONLESS, writes HELD.

    ``anchors`` (F, kernels.FRICTION_COLUMNS): the anchor (3, m) in the object's body frame,
    so that a sticking finger moves with the object, 1.0 once set, the fingertip's radius (m).
    """

    name = "friction"
    reads = friction.DECLARATION.reads
    writes = friction.DECLARATION.writes
    kernel_stage = kernels.STAGE_FRICTION

    def __init__(self, radii: list[float], anchors: np.ndarray | None = None) -> None:
        # A view of the renderer's state, or its own.
        if anchors is None:
            anchors = np.zeros((len(radii), kernels.FRICTION_COLUMNS))
        anchors[:, kernels.FINGER_RADIUS] = radii
        self.anchors = anchors

    @property
    def carries(self) -> dict[str, object]:
        return {"friction_anchors": self.anchors}  # hapticd.physics.frame.STATE


class Forces:
    """The full contact force (F, 3) N: k (surface point - device) - b v_rel, zero out of
    contact; damping may slow the finger, never pull it into the object."""

    name = "forces"
    reads = forces.DECLARATION.reads
    writes = forces.DECLARATION.writes
    kernel_stage = kernels.STAGE_FORCES


class Allocation:
    """The contact forces onto the actuated directions (``ContactAllocator``): writes
    ``lam_a``, the accuracy, ``alpha`` and M_a lam_a (F, 3) N into ``output``."""

    name = "allocation"
    reads = allocation_stage.DECLARATION.reads

    def __init__(
        self, scene: Scene, allocator: ContactAllocator, kernel: Callable[..., int] | None = None
    ) -> None:
        self.scene = scene
        self.allocator = allocator
        self.kernel = kernel
        self.output = "rendered_force"  # or allocated_force, when the plan sums more into it

    @property
    def kernel(self) -> Callable[..., int]:
        """The allocator's allocation_step, compiled or (set to None) not."""
        return self.allocator.kernel

    @kernel.setter
    def kernel(self, fn: Callable[..., int] | None) -> None:
        self.allocator.kernel = fn

    @property
    def carries(self) -> dict[str, object]:
        return {"allocator_blend": self.allocator.alpha}  # hapticd.physics.frame.STATE

    @property
    def writes(self) -> tuple[str, ...]:
        return ("lam_a", *_ACCURACY, "alpha", self.output)

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
            getattr(frame, self.output),
        )
        frame.alpha[()] = alloc.alpha
        for name, value in zip(_ACCURACY, acc, strict=True):
            getattr(frame, name)[()] = value

    @property
    def kernel_stage(self) -> int | None:
        """STAGE_ALLOCATION when the call allocates for this allocator, else None (``run``)."""
        return kernels.STAGE_ALLOCATION if self.allocator.in_kernel else None


class Environment:
    """The ground's and walls' force projected onto the span of each finger's actuated
    directions: ``env_rendered`` (F, 3) N."""

    name = "environment"
    reads = environment.DECLARATION.reads
    writes = environment.DECLARATION.writes
    kernel_stage = kernels.STAGE_ENVIRONMENT


class Output:
    """The rendered force: the allocated force plus ``parts`` (the other contributions'
    fields), in that order. ValueError without parts."""

    name = "output"
    writes = OUTPUT.writes
    kernel_stage = kernels.STAGE_SUM

    def __init__(self, parts: list[str]) -> None:
        if not parts:
            raise ValueError("the output stage sums two or more contributions")
        self.reads = ("allocated_force", *parts)


class Passivity:
    """Time-domain passivity per finger (hapticd.physics.passivity): the least damping
    along the finger's actuated directions that keeps its port's observed energy from going
    negative. Observes ``inputs`` (every contribution before its own); writes
    ``passivity_force`` (N), ``passivity_energy`` (J), ``passivity_damping`` (N s/m).

    ``state`` (F, kernels.PASSIVITY_STATE): the observed energy, the last position, 1.0 once set.
    """

    name = "passivity"
    writes = passivity.DECLARATION.writes
    kernel_stage = kernels.STAGE_PASSIVITY

    def __init__(
        self, params: PassivityParams, n_fingers: int, dt: float, state: np.ndarray | None = None
    ) -> None:
        self.params = params
        self.dt = dt
        # A view of the renderer's state, or its own.
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
        """Velocity threshold (m/s), most damping (N s/m), dt (s): the call's params."""
        p = self.params
        return (p.velocity_threshold, p.max_damping, self.dt)


class Dynamics:
    """Moves a free object one tick under the fingers' reactions, gravity, ground and walls
    (docs/scene.md): writes the object's state, which the next tick's contact sees."""

    name = "dynamics"
    reads = dynamics.DECLARATION.reads
    writes = dynamics.DECLARATION.writes  # the object's pose and motion (the scene's object)
    kernel_stage = kernels.STAGE_DYNAMICS

    def __init__(self, scene: Scene, n_fingers: int, dt: float) -> None:
        self.scene = scene
        obj = scene.object
        self.dt = dt
        self.gravity = scene.gravity
        self.substeps = scene.substeps or auto_substeps(  # 0: auto
            obj, scene.surfaces, obj.material.stiffness, n_fingers, dt
        )

    @property
    def carries(self) -> dict[str, object]:
        return {"object_state": self.scene.object.state}  # hapticd.physics.frame.STATE

    @property
    def effects(self) -> list[str]:
        """What moves the object besides the fingers."""
        return (["gravity"] if self.gravity is not None else []) + (
            ["surfaces"] if self.scene.surfaces else []
        )

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """free_body_step's params, body (inertia, its inverse, the vertices; body frame)
        and surfaces (normal, offset, stiffness, damping, dynamic friction) for the object
        as it is now."""
        obj = self.scene.object
        local = obj.shape.vertices.tolist()
        # The farthest vertex from the centre of mass (m): surfaces farther away are skipped.
        reach = max((math.sqrt(x * x + y * y + z * z) for x, y, z in local), default=0.0)
        mat = obj.material
        gravity = (0.0, 0.0, 0.0) if self.gravity is None else self.gravity
        params = np.array(
            [mat.stiffness, mat.torsion, obj.mass, self.dt, self.substeps, reach, *gravity]
        )
        inertia = obj.inertia_body
        body = np.array(
            [*inertia.tolist(), *np.linalg.inv(inertia).tolist(), *local], dtype=float
        ).reshape(-1, 3)
        surf = np.zeros((len(self.scene.surfaces), kernels.SURFACE_COLUMNS))
        for row, surface in zip(surf, self.scene.surfaces, strict=True):
            m = surface.material
            row[:] = (*surface.normal, surface.offset, m.stiffness, m.damping, m.mu_dynamic)
        return params, body, surf


class SceneState:
    """Publishes the scene after the tick: the object's pose and motion, stiffness, mass and
    the allocator (an index into hapticd.allocation.METHODS, written when the call binds)."""

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
