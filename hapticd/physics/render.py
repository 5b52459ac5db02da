"""The renderer: the stages a scene needs, in tick order, run as one call per tick.

``Renderer`` plans the stages (hapticd.physics.stages) and owns their carried state;
``check_plan`` checks a plan; ``OneCall`` runs it (kernels.tick_step, compiled or not).
The picture: docs/architecture.md, "One tick".
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from hapticd.allocation import DEFAULT_ROBUSTNESS, AdaptiveState, Robustness
from hapticd.allocation import plugins as allocation_plugins
from hapticd.allocation.actuation import Actuation
from hapticd.allocation.contacts import ContactAllocator
from hapticd.params import PARAMS, ParamError
from hapticd.physics import kernels as kn
from hapticd.physics.dynamics import MAX_SUBSTEPS, lightest_mass, needed_substeps
from hapticd.physics.frame import LOOP_WRITERS, NAMES, STATE_WRITERS, Frame, item_view
from hapticd.physics.live import Change
from hapticd.physics.passivity import PassivityParams
from hapticd.physics.safety import SafetyChain
from hapticd.physics.scene import Material, Scene, SceneObject
from hapticd.physics.stages import (
    FRICTIONLESS,
    HELD,
    Allocation,
    Contact,
    Dynamics,
    Environment,
    Forces,
    Friction,
    Output,
    Passivity,
    SceneState,
    Stage,
)
from hapticd.physics.tick.forces import pack as pack_forces
from hapticd.physics.tick.friction import pack as pack_friction


class PlanError(ValueError):
    """A plan that breaks the frame's rules: one writer a field, every field read written."""


def check_plan(stages: list[Stage]) -> dict[str, str]:
    """The writer of each field the plan or the loop writes (field -> who).

    PlanError names the field and the stage: two writers of a field, a field the frame
    lacks, a read (or ``corrupts``) nobody writes, state ``carries`` that frame.STATE
    gives to another writer."""
    order = " -> ".join(s.name for s in stages)
    writers = dict(LOOP_WRITERS)
    for stage in stages:
        for name in getattr(stage, "writes", ()):
            if name not in NAMES:
                raise PlanError(f"stage {stage.name!r} writes {name!r}, which is no frame field")
            if name in writers:
                raise PlanError(
                    f"two writers of the frame's {name!r}: {writers[name]} and stage "
                    f"{stage.name!r} (plan: {order}); every field has one writer"
                )
            writers[name] = f"stage {stage.name!r}"
    carriers: dict[str, str] = {}
    for stage in stages:
        for name in getattr(stage, "carries", {}):
            if STATE_WRITERS.get(name) != stage.name:
                raise PlanError(
                    f"stage {stage.name!r} carries {name!r} from tick to tick, which "
                    f"hapticd.physics.frame.STATE gives to {STATE_WRITERS.get(name, 'no one')!r}"
                )
            if name in carriers:
                raise PlanError(f"two stages named {stage.name!r} carry {name!r}")
            carriers[name] = stage.name
    for stage in stages:
        for name in (*getattr(stage, "reads", ()), *getattr(stage, "corrupts", ())):
            if name not in NAMES:
                raise PlanError(f"stage {stage.name!r} reads {name!r}, which is no frame field")
            if name not in writers:
                raise PlanError(
                    f"stage {stage.name!r} reads {name!r}, which nothing writes (plan: {order})"
                )
    return writers


class Renderer:
    """One tick of the scene for F spherical fingertips of ``radii`` (m), through
    ``actuation`` with ``allocator`` (a name of hapticd.allocation.plugins.names()); ``passivity``
    adds the passivity controller. ValueError for a wrong count of radii or allocator."""

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
        passivity: PassivityParams | None = None,
    ) -> None:
        if len(radii) != actuation.n_fingers:
            raise ValueError("one radius per finger is needed")
        if not allocation_plugins.is_known(allocator):
            raise ValueError(allocation_plugins.unknown(allocator))
        self.scene = scene if isinstance(scene, Scene) else Scene(scene, [], None)
        self.radii = [float(r) for r in radii]
        self.n_fingers = len(self.radii)
        self.dt = dt
        self.allocator = ContactAllocator(
            actuation,
            allocator,
            robust,
            adaptive if adaptive is not None else AdaptiveState(),
            dt,
        )
        # The carried state in one array (kernels.TICK_STATE), which the call takes whole;
        # the stages, made once, hold views of their blocks.
        layout = kn.state_layout(self.n_fingers, actuation.n_actuators)
        self.state = np.zeros(sum(math.prod(shape) for _, shape in layout.values()))
        views = self._state_views()
        self._contact = Contact(self.scene, self.radii, views["contact"])
        self._friction = Friction(self.radii, views["anchors"])
        self._allocation = Allocation(self.scene, self.allocator)
        self._passivity = (
            None
            if passivity is None
            else Passivity(passivity, self.n_fingers, dt, views["passive"])
        )
        self._adopt()
        self._inserted: list[tuple[str, Stage]] = []
        self._output: Stage | None = None  # a stage writing rendered_force instead of the sum
        self.kernels: dict[str, Callable[..., None]] = {}
        self.frame = Frame(self.n_fingers, actuation.n_actuators)
        self.plan()

    # -- the carried state ------------------------------------------------------------------

    def _state_views(self) -> dict[str, np.ndarray]:
        """Each block of ``state`` as a view, made anew when they are not (a copy's)."""
        views = getattr(self, "_views", None)
        if views is None or views["loop"].base is not self.state:
            layout = kn.state_layout(self.n_fingers, self.actuation.n_actuators)
            views = {
                name: self.state[at : at + math.prod(shape)].reshape(shape)
                for name, (at, shape) in layout.items()
            }
            self._views = views
        return views

    def _carriers(self) -> list[tuple[object, str, str]]:
        """Who holds a view of which block of ``state``: (holder, attribute, block)."""
        held: list[tuple[object, str, str]] = [
            (self._contact, "state", "contact"),
            (self._friction, "anchors", "anchors"),
            (self.allocator, "state", "alloc"),
            (self.allocator, "work", "work"),
        ]
        if self._passivity is not None:
            held.append((self._passivity, "state", "passive"))
        return held

    def _adopt(self) -> None:
        """Make every carrier hold its view of ``state``, copying in the values of an array
        of its own (the allocator's at first, a copy's)."""
        views = self._state_views()
        for holder, attr, block in self._carriers():
            view = views[block]
            mine = getattr(holder, attr)
            if mine is not view:
                if mine.shape == view.shape:
                    view[...] = mine
                setattr(holder, attr, view)

    @property
    def loop(self) -> np.ndarray:
        """The servo loop's block of ``state`` (kernels.LOOP_*)."""
        return self._state_views()["loop"]

    # -- the plan -------------------------------------------------------------------------

    def plan(self) -> None:
        """Choose the stages the scene needs, in tick order, and the fields each writes
        (PlanError: ``check_plan`` refuses the plan).

        With friction, contact writes FRICTIONLESS and friction HELD. Allocation writes
        ``rendered_force`` itself when it is the only contribution; else the output stage
        (or ``set_output``'s) does."""
        planned = self._planned(self._contact, self._allocation, self.obj.material)
        self.writers = check_plan(planned.stages)
        self.stages: list[Stage] = planned.stages
        # The running plan's call reads the object's material as it is at each bind.
        self.one_call = OneCall(self, self.kernels.get("tick_step"), planned.live())

    def _planned(self, contact: Contact, allocation: Allocation, material: Material) -> Planned:
        """The stages for ``material``, with ``contact`` and ``allocation`` (the renderer's,
        or copies for a plan prepared beside the running one: only they are set)."""
        sc = self.scene
        obj = sc.object
        stages: list[Stage] = [contact]
        friction = material.has_friction
        contact.outputs = FRICTIONLESS if friction else HELD
        if friction:
            stages.append(self._friction)
        allocation.kernel = self.kernels.get("allocation_step")
        stages += [Forces(), allocation]
        parts: list[str] = []
        if sc.surfaces:
            stages.append(Environment())
            parts.append("env_rendered")
        if self._passivity is not None:  # it sees every other contribution
            inputs = ("allocated_force", *parts)
            if self._passivity.inputs != inputs:  # the scene's surfaces fix them
                self._passivity.inputs = inputs
            stages.append(self._passivity)
            parts.append("passivity_force")
        output = self._output
        if output is None and parts:
            output = Output(parts)
        allocation.output = "rendered_force" if output is None else "allocated_force"
        if output is not None:
            stages.append(output)
        if not obj.fixed:
            stages.append(Dynamics(sc, self.n_fingers, self.dt))
        stages.append(SceneState())
        for after, stage in self._inserted:
            names = [s.name for s in stages]
            stages.insert(names.index(after) + 1, stage)
        return Planned(stages, contact, allocation, material)

    # The kernels a renderer runs: the tick's call, and the allocator's own (for
    # ``ContactAllocator.replay``, outside the call).
    kernel_names = ("tick_step", "allocation_step")

    def use_kernels(self, kernels: dict[str, Callable[..., None]]) -> None:
        """Run the compiled ``kernels`` (name -> function, of ``kernel_names``) from the
        next tick on; {}: none compiled."""
        self.kernels = dict(kernels)
        self.plan()

    @property
    def passivity(self) -> Passivity | None:
        """The passivity stage, or None without its parameters."""
        return self._passivity

    @property
    def stage_names(self) -> list[str]:
        """Names of the stages in the plan, in tick order."""
        return [s.name for s in self.stages]

    def insert(self, stage: Stage, *, after: str) -> None:
        """Run ``stage`` after the stage named ``after`` from the next tick on. ValueError
        for no such stage; PlanError, the plan unchanged, for a plan ``check_plan`` refuses."""
        if after not in self.stage_names:
            raise ValueError(f"no stage {after!r} in the plan {self.stage_names}")
        self._replan(_inserted=[*self._inserted, (after, stage)])

    def set_output(self, stage: Stage | None) -> None:
        """Let ``stage`` write ``rendered_force`` in place of the sum from the next tick on;
        None: the sum again. PlanError, the plan unchanged, if it does not declare it."""
        if stage is not None and "rendered_force" not in getattr(stage, "writes", ()):
            raise PlanError(f"stage {stage.name!r} does not write 'rendered_force'")
        self._replan(_output=stage)

    def _replan(self, **change: object) -> None:
        """Set the attributes ``change`` and plan; PlanError: set them back, plan as before."""
        before = {name: getattr(self, name) for name in change}
        self.__dict__.update(change)
        try:
            self.plan()
        except PlanError:
            self.__dict__.update(before)
            self.plan()
            raise

    # -- the tick -------------------------------------------------------------------------

    def run(self, frame: Frame, safety: SafetyChain | None = None) -> int | None:
        """One tick on ``frame``, whose device_pos (F, 3) m and device_vel (F, 3) m/s are set.

        With ``safety`` (a ``ready`` chain) the call makes the chain's tick too: its outcome,
        for ``SafetyChain.done``; None when it did not (the caller checks the object and runs
        the chain); SAMPLES_REFUSED when the devices' samples failed the call's check.
        ValueError (contact) or AllocationError for a non-finite input or result."""
        return self.one_call.run(frame, safety)

    def step(self, device_pos: np.ndarray, device_vel: np.ndarray) -> Frame:
        """One tick off-line for device positions (F, 3) m and velocities (F, 3) m/s, on the
        renderer's own frame (no devices, timing or safety), which it returns."""
        frame = self.frame
        frame.device_pos[:] = device_pos
        frame.device_vel[:] = device_vel
        self.run(frame)
        return frame

    # -- parameters ---------------------------------------------------------------------------

    @property
    def obj(self) -> SceneObject:
        return self.scene.object

    @property
    def actuation(self) -> Actuation:
        return self.allocator.actuation

    @property
    def method(self) -> str:
        """The allocator's name."""
        return self.allocator.method

    def param(self, name: str) -> Any:
        """The current value of a renderer parameter (hapticd.params), JSON-friendly."""
        return _GETTERS[_own(name)](self)

    def set_param(self, name: str, value: Any) -> None:
        """Change a renderer parameter now (between ticks, in this thread): ``prepare_set``
        and apply it. ParamError or ValueError, nothing changed, as ``prepare_set``."""
        call = self.one_call
        self.prepare_set(name, value, call._frame, call._safety).apply()

    def prepare_set(
        self,
        name: str,
        value: Any,
        frame: Frame | None = None,
        safety: SafetyChain | None = None,
    ) -> Change:
        """Check a new value of a renderer parameter and prepare its change, changing
        nothing yet (in the caller's thread: the servo thread only applies it).

        A number (stiffness, damping, mass, friction that stays on or off) becomes stores
        into its slots in the running call's arrays; the allocator, the actuated directions
        or friction turned on or off, a new plan and call bound to ``frame`` (the loop's,
        with ``safety``'s tick in it; None: bound on its first tick), swapped in by
        attribute stores. The value is taken as given (the control protocol checks it
        against its range). ParamError for a name the renderer does not own; ValueError for
        another count of actuated directions per finger (it fixes the recording's layout),
        a free object the change leaves needing more substeps than its step takes, or any
        other failure of the change."""
        _own(name)
        try:
            if name in _NUMBERS:
                mat = self.obj.material
                new = _NUMBERS[name](mat, value)
                if new.has_friction == mat.has_friction:
                    return self._prepare_number(name, value, new)
            return self._prepare_plan(name, value, frame, safety)
        except Exception as exc:
            if type(exc) in (ValueError, ParamError, PlanError):  # already says what and why
                raise
            raise ValueError(
                f"{name} {value!r} cannot be used ({type(exc).__name__}: {exc}); nothing changed"
            ) from exc

    def _prepare_number(self, name: str, value: Any, material: Material) -> Change:
        """A number's change: its new value into the slots the running call reads (and the
        object's, which a later bind reads), a free object's step and substeps remade."""
        obj, call = self.obj, self.one_call
        mass = float(value) if name == "mass_kg" else obj.mass
        trial = copy.copy(obj)  # the object as the change leaves it (its state shared, unread)
        trial.material, trial.mass = material, mass
        self._check_integrable(name, value, self._needed_substeps(obj), trial)
        change = Change(name, value)
        # What it was prepared against (a new plan comes with a new call).
        change.guards += [
            (obj, "material", obj.material),
            (obj, "mass", obj.mass),
            (self, "one_call", call),
        ]
        change.attrs.append((obj, "material", material))
        if mass != obj.mass:
            change.attrs.append((obj, "mass", mass))
        dynamics = next((s for s in self.stages if isinstance(s, Dynamics)), None)
        body_params = body = None
        if dynamics is not None:
            scene = copy.copy(self.scene)
            scene.object = trial
            step = Dynamics(scene, self.n_fingers, self.dt)
            body_params, body, _ = step.arrays()
            if step.substeps != dynamics.substeps:
                change.attrs.append((dynamics, "substeps", step.substeps))
        frame = call._frame
        if frame is None:  # not bound yet: its first tick binds the object's new values
            return change
        change.attrs.append((call, "_material", material))  # no bind for the new material
        plan = call._plan
        change.guards += [(call, "_plan", plan), (call, "_frame", frame)]
        view = memoryview(plan)
        # The same packing as the bind's (the stages' own ``pack``), into the same slots.
        p = kn.TICK_AT
        friction = pack_friction(material.mu_static, material.mu_dynamic)
        forces = pack_forces(material.stiffness, material.damping, not obj.fixed)
        slots = [(p + kn.TICK_FRICTION_AT + j, x) for j, x in enumerate(friction)]
        slots += [(p + kn.TICK_FORCES_AT + j, x) for j, x in enumerate(forces)]
        if body_params is not None and body is not None:
            slots += [(p + kn.TICK_BODY_AT + j, x) for j, x in enumerate(body_params.tolist())]
            # The body block's head rows: the inertia and its inverse (they scale with mass).
            at = call._layout[kn.TICK_PLAN.index("body")]
            head = body[: kn.BODY_HEAD].reshape(-1).tolist()
            slots += [(at + j, x) for j, x in enumerate(head)]
        stores = [(view, i, float(x)) for i, x in slots]
        stores += [
            (item_view(frame.stiffness_n_per_m), (), material.stiffness),
            (item_view(frame.mass_kg), (), mass),
        ]
        # Only the slots the change changes: a stiffness set is a few stores, not the step's.
        change.stores += [(v, i, x) for v, i, x in stores if v[i] != x]
        change.replaced = [None] * len(change.attrs)
        return change

    def _prepare_plan(
        self, name: str, value: Any, frame: Frame | None, safety: SafetyChain | None
    ) -> Change:
        """A change of the plan's structure: a new plan and call, made and bound here with
        copies of what the running one's stages hold, swapped in by ``Change.apply``."""
        obj, old = self.obj, self.one_call
        material = obj.material
        allocator = self.allocator
        if name == "allocator":
            _check_allocator(value)
            allocator = allocator.changed(method=str(value))
        elif name == "actuated_directions":
            allocator = allocator.changed(actuation=_actuation(self, value))
        else:
            material = _NUMBERS[name](material, value)
            allocator = allocator.changed()
        contact = copy.copy(self._contact)
        allocation = Allocation(self.scene, allocator)
        planned = self._planned(contact, allocation, material)
        writers = check_plan(planned.stages)
        call = OneCall(self, self.kernels.get("tick_step"), planned)
        if frame is not None:
            call._bind(frame, publish=False)
            if safety is not None:
                call._with(safety)
        change = Change(name, value, structural=True)
        change.guards += [
            (self.scene, "object", obj),
            (obj, "material", obj.material),
            (self, "one_call", old),
            (self, "allocator", self.allocator),
            (self, "_contact", self._contact),
        ]
        # Whether the proxies have started, as the running tick leaves it.
        change.copies += [(call, "_started", old, "_started")]
        change.copies += [(contact, "_started", self._contact, "_started")]
        change.attrs += [
            (obj, "material", material),
            (self, "_contact", contact),
            (self, "_allocation", allocation),
            (self, "allocator", allocator),
            (self, "stages", planned.stages),
            (self, "writers", writers),
            (self, "one_call", call),
        ]
        if frame is not None:
            change.stores += call._published(frame)
        change.replaced = [None] * len(change.attrs)
        return change

    def _needed_substeps(self, obj: SceneObject) -> float:
        """The substeps free ``obj``'s step needs (0 for a fixed object)."""
        if obj.fixed:
            return 0.0
        return needed_substeps(
            obj, self.scene.surfaces, obj.material.stiffness, self.n_fingers, self.dt
        )

    def _check_integrable(self, name: str, value: Any, before: float, obj: SceneObject) -> None:
        """ValueError if the change leaves free ``obj`` (the object as it would be) needing
        more substeps than its step takes (and more than ``before``: a profile's own choice
        stays), naming the limit."""
        takes = self.scene.substeps or MAX_SUBSTEPS
        needed = self._needed_substeps(obj)
        if needed <= takes or needed <= before:
            return
        lightest = lightest_mass(
            obj, self.scene.surfaces, obj.material.stiffness, self.n_fingers, self.dt, takes
        )
        raise ValueError(
            f"{name} {value!r} refused: the free object would need {needed:.3g} substeps a "
            f"{self.dt * 1e3:g} ms tick, its step takes {takes}; with stiffness "
            f"{obj.material.stiffness:g} N/m and damping {obj.material.damping:g} N s/m the "
            f"mass must be at least {lightest:.3g} kg; nothing changed"
        )


@dataclasses.dataclass
class Planned:
    """A plan: its ``stages`` in tick order, the ``contact`` and ``allocation`` stages among
    them, and the object's ``material`` it was made for (None: the object's own at each
    bind, the running plan's)."""

    stages: list[Stage]
    contact: Contact
    allocation: Allocation
    material: Material | None

    def live(self) -> Planned:
        """This plan reading the object's material as it is when its call binds."""
        return dataclasses.replace(self, material=None)


class OneCall:
    """The renderer's plan (``planned``) as one call per tick of kernels.tick_step,
    compiled or not.

    A stage the kernel lacks runs in Python between the call's parts, each a run of the
    kernel's stages."""

    def __init__(self, renderer: Renderer, fn: Callable[..., int] | None, planned: Planned) -> None:
        self.renderer = renderer
        self.planned = planned
        self._fn = kn.uncompiled("tick_step") if fn is None else fn
        self._call: Callable[..., int] = self._fn  # ``direct(fn, args)``, made with the args
        self._frame: Frame | None = None
        self._args: tuple[np.ndarray, ...] = ()
        self._scene = renderer.scene
        self._obj: SceneObject | None = None
        self._material: Material | None = None
        self._started = False
        self._safety: SafetyChain | None = None  # the chain whose tick the call makes
        self._plan = np.zeros(0)  # tick_step's plan (kernels.TICK_PLAN), made by _bind
        self._params = self._plan  # the plan's params (kernels.TICK_PARAMS, a view)
        self._planes = np.zeros((0, kn.PLANE_COLUMNS))  # the plan's planes block (a view)
        self._layout: list[int] = []  # each TICK_PLAN block's offset in the plan
        # The tick in parts: runs of the kernel's stages (first, last) and Python stages.
        self._parts = _parts(planned.stages)
        self._single = len(self._parts) == 1  # one part: the whole tick

    def __getstate__(self) -> dict[str, object]:
        # A copy (a deep copy, a pickle) binds its own frame's fields on its first tick:
        # the arguments are views of this one's frame, which a copy would detach.
        unbound = {"_frame": None, "_args": (), "_obj": None, "_material": None, "_call": self._fn}
        return {**self.__dict__, **unbound, "_safety": None}

    def _bind(self, frame: Frame, *, publish: bool = True) -> None:
        """Make the call's arguments for ``frame`` and the plan as it is now; ``publish``:
        write the scene's scalars into the frame too (not for a plan prepared beside the
        running one, whose swap stores them: ``_published``)."""
        r = self.renderer
        src = self.planned
        obj = r.scene.object
        mat = obj.material if src.material is None else src.material
        allocator = src.allocation.allocator
        act = allocator.actuation
        n = r.n_fingers
        names = {s.name: s for s in src.stages}
        friction = "friction" in names
        free = "dynamics" in names
        passivity = r._passivity if "passivity" in names else None
        # The directions and counts are the environment's and passivity's too.
        directions, counts, alloc_params = allocator.kernel_inputs()
        body_params, body, surf = names["dynamics"].arrays() if free else _NO_BODY
        blocks = {
            "planes": src.contact._kernel_planes(),
            "body": body,
            "surf": surf,
            "normals": np.asarray(obj.shape.normals, dtype=float).reshape(-1, 3),
            "offsets": np.asarray(obj.shape.offsets, dtype=float).reshape(-1),
            "scratch": np.zeros((n, kn.SCRATCH_COLUMNS)),
            "directions": directions,
            "counts": counts,
        }
        head = kn.TICK_AT + kn.TICK_PARAMS
        size = head + sum(b.size for b in blocks.values())
        if self._plan.size != size:
            self._plan = np.zeros(size)
        plan = self._plan
        layout: list[int] = []  # each block's offset in the plan; "rows": the last one's rows
        start = rows = head
        for name in kn.TICK_PLAN:
            if name == "rows":
                layout.append(rows)
                continue
            block = blocks[name]
            plan[start : start + block.size] = block.reshape(-1)
            layout.append(start)
            start, rows = start + block.size, len(block)
        at_planes = layout[kn.TICK_PLAN.index("planes")]
        self._planes = plan[at_planes : at_planes + blocks["planes"].size].reshape(
            -1, kn.PLANE_COLUMNS
        )
        p = self._params = plan[kn.TICK_AT : head]
        p[:] = 0.0
        p[kn.TICK_FRICTION] = friction
        p[kn.TICK_FREE] = free
        p[kn.TICK_SURFACES] = bool(r.scene.surfaces)
        p[kn.TICK_SUM] = "output" in names
        p[kn.TICK_PASSIVITY] = passivity is not None
        if passivity is not None:
            p[kn.TICK_PASSIVITY_AT : kn.TICK_FRICTION_AT] = passivity.kernel_params
        p[kn.TICK_FRICTION_AT : kn.TICK_FORCES_AT] = pack_friction(mat.mu_static, mat.mu_dynamic)
        p[kn.TICK_FORCES_AT : kn.TICK_ALLOCATION_AT] = pack_forces(
            mat.stiffness, mat.damping, not obj.fixed
        )
        # Its item 4, the actuation's frame, is the environment's and passivity's too.
        p[kn.TICK_ALLOCATION_AT : kn.TICK_BODY_AT] = alloc_params
        p[kn.TICK_BODY_AT :] = body_params
        at = {name: _float_offset(frame, name) for name in kn.TICK_FIELDS}
        if not friction:  # contact writes the final fields itself
            at.update({plain: at[held] for plain, held in zip(FRICTIONLESS, HELD, strict=True)})
        at["allocated_force"] = at[src.allocation.output]
        r._adopt()
        state = kn.state_layout(n, act.n_actuators)
        plan[: kn.TICK_AT] = [
            *(at[name] for name in kn.TICK_FIELDS),
            *layout,
            *(state[name][0] for name in kn.TICK_STATE),
            *state["work"][1],
            frame.dtype.fields["in_contact"][1],
            frame.dtype.fields["buttons"][1],
            n,
        ]
        self._args = (
            frame.record.reshape(1).view(np.uint8).view(np.float64),
            r.state,
            plan,
            obj.state,
            *_NO_SAFETY,
        )
        if self._single:
            p[kn.TICK_FIRST], p[kn.TICK_LAST] = self._parts[0]  # type: ignore[misc]
        self._layout = layout
        if publish:
            for view, index, x in self._published(frame):
                view[index] = x
        self._frame = frame
        self._obj, self._material = obj, mat
        self._safety = None  # the arguments hold no chain's arrays
        self._call = direct(self._fn, self._args)

    def _published(self, frame: Frame) -> list[tuple[Any, Any, float | int]]:
        """The scene's scalars this plan publishes in ``frame`` (SceneState's stiffness, mass
        and allocator), as item stores (``hapticd.physics.live.Change.stores``)."""
        obj = self.renderer.scene.object
        src = self.planned
        mat = obj.material if src.material is None else src.material
        method = src.allocation.allocator.method
        return [
            (item_view(frame.stiffness_n_per_m), (), mat.stiffness),
            (item_view(frame.mass_kg), (), obj.mass),
            (item_view(frame.allocator), (), allocation_plugins.names().index(method)),  # u1
        ]

    def run(self, frame: Frame, safety: SafetyChain | None = None) -> int | None:
        """The tick: ``Renderer.run``."""
        # Set without a new plan (set_param plans anew): the object, or its material (an
        # analysis replaying a recording's stiffness tick by tick).
        obj = self._scene.object
        if frame is not self._frame or obj is not self._obj or obj.material is not self._material:
            self._bind(frame)
        if not self._started:  # every proxy starts at its device, on the first finite tick
            self._started = self.planned.contact.start(frame)
        if safety is not self._safety:  # the chain in the call changed (None: no chain)
            self._with(safety)
        if self._single:
            outcome = self._call(*self._args)
            if outcome < _FINISHED:
                if outcome == kn.TICK_SAMPLES:
                    return SAMPLES_REFUSED
                self._stopped(frame, outcome)
        else:
            outcome = self._in_parts(frame)
            if outcome == kn.TICK_SAMPLES:
                return SAMPLES_REFUSED
        # The chain's outcome, or None: no chain (or the object's state to check).
        return outcome - _SAFE if outcome >= _SAFE else None

    @property
    def started(self) -> bool:
        """Whether the devices' samples may wait in the frame for the call's check: every
        proxy has started, and the call's first part is the kernel's (a Python stage first
        would read them unchecked)."""
        return self._started and (self._single or isinstance(self._parts[0], tuple))

    def _in_parts(self, frame: Frame) -> int:
        """The tick in its parts: the kernel's runs of stages and the Python stages."""
        p = self._params
        outcome = kn.TICK_DONE
        for part in self._parts:
            if isinstance(part, tuple):
                p[kn.TICK_FIRST], p[kn.TICK_LAST] = part
                outcome = self._call(*self._args)
                if outcome == kn.TICK_SAMPLES:
                    return outcome
                if outcome < _FINISHED:
                    self._stopped(frame, outcome)
            else:
                part.run(frame)
        return outcome

    def _stopped(self, frame: Frame, outcome: int) -> None:
        """A tick the kernel refused: ValueError or AllocationError, by name."""
        src = self.planned
        if outcome == kn.TICK_FROM_CONTACT:
            raise ValueError(src.contact._non_finite(frame, self._planes))
        at = kn.TICK_ALLOCATION_AT
        params = self._params[at : at + kn.ALLOCATION_PARAMS]  # the call's, with its status
        bad_input = outcome == kn.TICK_NON_FINITE_INPUT
        raise src.allocation.allocator.refusal(bad_input=bad_input, params=params)

    def _with(self, safety: SafetyChain | None) -> None:
        """Run ``safety``'s tick in the call from now on (None: no chain's)."""
        self._safety = safety
        arrays = _NO_SAFETY if safety is None else safety.kernel_arrays
        self._args = (*self._args[:-2], *arrays)
        self._call = direct(self._fn, self._args)
        self._params[kn.TICK_SAFETY] = 0.0 if safety is None else 1.0


def direct(fn: Callable[..., int], args: tuple[np.ndarray, ...]) -> Callable[..., int]:
    """What to call ``fn`` with ``args`` through each tick: a numba dispatcher's one
    overload's entry point when every argument is exactly the array its signature declares,
    else ``fn`` (whose own check refuses a wrong argument by name).

    The dispatcher checks every argument's type on each call (about 1 us a tick); the entry
    point trusts them, so they are checked here, once per set (bound once per frame, plan
    and chain), as numba's typing would."""
    sigs = getattr(fn, "signatures", None)
    overloads = getattr(fn, "overloads", None)
    if not sigs or len(sigs) != 1 or overloads is None or len(sigs[0]) != len(args):
        return fn
    for a, ty in zip(args, sigs[0], strict=True):
        if not (
            type(a) is np.ndarray
            and getattr(ty, "ndim", None) == a.ndim
            and a.dtype == np.dtype(str(getattr(ty, "dtype", "")))
            and a.dtype.isnative
            and (ty.layout == "A" or (ty.layout == "C" and a.flags.c_contiguous))
            and a.flags.writeable == ty.mutable
            and a.flags.aligned == ty.aligned
        ):
            return fn
    return overloads[sigs[0]].entry_point


def _parts(stages: list[Stage]) -> list[tuple[int, int] | Stage]:
    """The plan as the call's parts: each run of the kernel's stages as (first, last)
    STAGE_ indices, each other stage itself; the last part runs the kernel to the end (the
    safety chain's tick)."""
    parts: list[tuple[int, int] | Stage] = []
    run: list[int] = []
    for stage in stages:
        k = getattr(stage, "kernel_stage", None)
        if k is not None:
            run.append(k)
            continue
        if run:
            parts.append((run[0], run[-1] + 1))
            run = []
        parts.append(stage)
    parts.append((run[0] if run else kn.STAGE_SAFETY, kn.STAGE_END))
    return parts


# ``OneCall.run``'s outcome when the devices' samples fail the call's check
# (kernels.TICK_SAMPLES): nothing written; the device bank checks them itself, with its
# messages, and runs the tick again.
SAMPLES_REFUSED = -1
# tick_step's safety arrays when the safety chain does not run in the call (never read).
_NO_SAFETY = (np.zeros(kn.SAFETY_PARAMS), np.zeros((2, 1, 3)))
# The free-body arrays of a plan with no dynamics (copied into the plan, never written).
_NO_BODY = (np.zeros(kn.PARAMS), np.zeros((0, 3)), np.zeros((0, kn.SURFACE_COLUMNS)))
_SAFE = kn.TICK_SAFE
_FINISHED = kn.TICK_FINISHED


def _float_offset(frame: Frame, name: str) -> int:
    """Where field ``name`` starts in the frame's record, in float64 items."""
    start = frame.dtype.fields[name][1]
    if start % 8:
        raise RuntimeError(f"frame field {name!r} is not aligned to 8 bytes")
    return start // 8


def _own(name: str) -> str:
    spec = PARAMS.get(name)
    if spec is None or spec.owner != "renderer":
        raise ParamError(
            "unknown_param", f"unknown parameter {name!r} for the renderer; known: {list(_SETTERS)}"
        )
    return name


def _actuation(r: Renderer, value: Any) -> Actuation:
    """The actuation ``value`` names, as many directions per finger as now (ValueError)."""
    new = value if isinstance(value, Actuation) else Actuation(value, r.actuation.frame)
    if new.counts != r.actuation.counts:
        raise ValueError(
            f"actuated directions per finger must stay {r.actuation.counts}, got {new.counts} "
            "(change the count in the profile and reload)"
        )
    return new


def _check_allocator(value: Any) -> None:
    if not isinstance(value, str) or not allocation_plugins.is_known(value):
        raise ParamError("bad_value", f"allocator: {allocation_plugins.unknown(value)}")


# The numbers: each one's new material (the mass is the object's own, not its material's).
_NUMBERS: dict[str, Callable[[Material, Any], Material]] = {
    "stiffness_n_per_m": lambda m, v: dataclasses.replace(m, stiffness=float(v)),
    "damping_n_s_per_m": lambda m, v: dataclasses.replace(m, damping=float(v)),
    "friction": lambda m, v: dataclasses.replace(m, mu_static=float(v[0]), mu_dynamic=float(v[1])),
    "mass_kg": lambda m, v: m,
}

# How the renderer changes each parameter it owns (hapticd.params, owner "renderer"): a
# number writes its slots, the others (and friction turned on or off) a new plan; a test
# checks these and the getters cover exactly those.
_SETTERS: dict[str, str] = {
    **dict.fromkeys(_NUMBERS, "slots"),
    "allocator": "plan",
    "actuated_directions": "plan",
}

_GETTERS: dict[str, Callable[[Renderer], Any]] = {
    "stiffness_n_per_m": lambda r: r.obj.material.stiffness,
    "damping_n_s_per_m": lambda r: r.obj.material.damping,
    "friction": lambda r: [r.obj.material.mu_static, r.obj.material.mu_dynamic],
    "mass_kg": lambda r: r.obj.mass,
    "allocator": lambda r: r.allocator.method,
    "actuated_directions": lambda r: [[list(d) for d in ds] for ds in r.actuation.local],
}
