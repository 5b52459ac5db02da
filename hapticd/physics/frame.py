"""The tick frame: everything the stages of one servo tick hand to each other, in one record.

``FIELDS`` is the one declaration: name, numpy dtype, per-tick shape (``"F"``
fingers, ``"r"`` actuated directions), SI unit and meaning. A ``Frame`` is one
preallocated numpy record of those fields; each field is an attribute that is a
view into it (``frame.device_pos`` (F, 3) m), so a stage writes in place and
nothing is allocated per tick. The recording's layout is the recorded fields of
the frame in this order (a tick is recorded by copying the record's leading
bytes), and the control server's status and telemetry read the frame.

Data flows one way through a tick: the device bank fills the device state, the
renderer's stages fill proxies, contact forces, allocation and the scene's
state, the safety chain fills ``device_force`` and the loop ``fault``, the device bank
writes ``device_force`` to the devices. Every field has one writer: ``LOOP_WRITERS``
names those outside the renderer; each stage declares what it reads and writes and
the renderer refuses a plan with two writers of a field.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FrameField:
    """One quantity of a tick: numpy dtype (little-endian), shape, SI unit, meaning.

    ``shape`` holds ints and the symbols ``"F"`` (fingers) and ``"r"`` (actuated
    directions); ``recorded`` fields go to the recording (hand-offs between stages
    that say nothing new are not recorded).
    """

    name: str
    dtype: str
    shape: tuple[int | str, ...]
    unit: str
    doc: str
    recorded: bool = True

    def resolve(self, n_fingers: int, n_actuators: int) -> tuple[int, ...]:
        sizes = {"F": n_fingers, "r": n_actuators}
        return tuple(sizes[s] if isinstance(s, str) else s for s in self.shape)


F3 = ("F", 3)

FIELDS: tuple[FrameField, ...] = (
    # Recorded, in the recording's order.
    FrameField("t", "<f8", (), "s", "nominal tick time k / rate"),
    FrameField("t_wall", "<f8", (), "s", "monotonic time the tick started, from the loop's start"),
    FrameField("compute_s", "<f8", (), "s", "time to read, render, make safe and write"),
    FrameField("device_pos", "<f8", F3, "m", "device (fingertip centre) positions, world frame"),
    FrameField("device_vel", "<f8", F3, "m/s", "device velocities, world frame"),
    FrameField("proxy_pos", "<f8", F3, "m", "proxy (god-object) positions"),
    FrameField("contact_force", "<f8", F3, "N", "full contact force lam_i on the finger"),
    FrameField(
        "rendered_force", "<f8", F3, "N", "finger i's rows of M_a lam_a, plus ground and walls"
    ),
    FrameField("device_force", "<f8", F3, "N", "force sent to the device, after the safety chain"),
    FrameField("lam_a", "<f8", ("r",), "N", "actuator forces, one per actuated direction"),
    FrameField(
        "residual_internal",
        "<f8",
        (),
        "N",
        "|N_G^T (lam - M_a lam_a)|: squeeze error (allocation.md)",
    ),
    FrameField(
        "residual_external", "<f8", (), "N", "|G lam - G M_a lam_a|: net wrench error (N and N m)"
    ),
    FrameField("residual_total", "<f8", (), "N", "|lam - M_a lam_a|"),
    FrameField("amplification", "<f8", (), "", "|M_a lam_a| / |lam| (0 without force)"),
    FrameField("alpha", "<f8", (), "", "external weight of the adaptive allocator (0 otherwise)"),
    FrameField("env_force", "<f8", F3, "N", "force on each finger from the ground and walls"),
    # The object's state in SceneObject.state's order (x, v, w, R): one copy publishes it.
    FrameField("object_pos", "<f8", (3,), "m", "object centre of mass (the grasp reference point)"),
    FrameField("object_vel", "<f8", (3,), "m/s", "object velocity (0 for a fixed object)"),
    FrameField("object_omega", "<f8", (3,), "rad/s", "object angular velocity, world frame"),
    FrameField("object_rot", "<f8", (3, 3), "", "object orientation (columns: body axes in world)"),
    FrameField("stiffness_n_per_m", "<f8", (), "N/m", "the object's stiffness on this tick"),
    FrameField("mass_kg", "<f8", (), "kg", "the object's mass on this tick"),
    FrameField("tick", "<u8", (), "", "tick number from the run's start"),
    FrameField(
        "contact_point",
        "<f8",
        F3,
        "m",
        "contact point on the object's surface (device position when free)",
    ),
    FrameField(
        "contact_normal",
        "<f8",
        F3,
        "",
        "the object's outward surface normal at each contact (0 when free)",
    ),
    FrameField(
        "passivity_energy",
        "<f8",
        ("F",),
        "J",
        "energy each finger's port absorbed, as the passivity observer sees it (negative: "
        "the display generated energy); 0 without the passivity stage",
    ),
    FrameField(
        "passivity_damping",
        "<f8",
        ("F",),
        "N s/m",
        "damping the passivity controller added along each finger's actuated directions; "
        "0 without the passivity stage",
    ),
    # The 4- and 1-byte fields after the 8-byte ones: every field stays aligned in the
    # record (a compiled kernel takes an aligned array at its fast door).
    FrameField(
        "control_seq",
        "<u4",
        (),
        "",
        "control changes applied so far: steps at the tick a change landed",
    ),
    FrameField("buttons", "<u4", ("F",), "", "each device's buttons, bit i for button i"),
    FrameField("in_contact", "u1", ("F",), "", "finger in contact (0/1)"),
    FrameField("fault", "u1", (), "", "a safety fault is latched (0/1)"),
    FrameField(
        "allocator", "u1", (), "", "index into meta.allocators of the allocator on this tick"
    ),
    # Hand-offs within a tick, not recorded.
    FrameField(
        "device_sample",
        "<f8",
        (2, "F", 3),
        "m, m/s",
        "each device's position then velocity as read (its own frame), before the "
        "plausibility check enters it into device_pos and device_vel",
        False,
    ),
    FrameField("surface_point", "<f8", F3, "m", "fingertip centre held on the object", False),
    # Contact's results before friction moves them (written only when friction is planned;
    # without friction contact writes proxy_pos, surface_point and contact_point itself).
    FrameField("frictionless_proxy", "<f8", F3, "m", "god-object proxy before friction", False),
    FrameField(
        "frictionless_point", "<f8", F3, "m", "fingertip centre on the object, frictionless", False
    ),
    FrameField(
        "frictionless_contact_point", "<f8", F3, "m", "contact point before friction", False
    ),
    # The rendered force's contributions, each with its own writer; the renderer's output
    # stage sums those in the plan into rendered_force (allocation writes rendered_force
    # itself when it is the only one).
    FrameField("allocated_force", "<f8", F3, "N", "finger i's rows of M_a lam_a", False),
    FrameField(
        "env_rendered",
        "<f8",
        F3,
        "N",
        "env_force through each finger's actuated directions (projected onto their span)",
        False,
    ),
    FrameField(
        "passivity_force",
        "<f8",
        F3,
        "N",
        "the passivity controller's damping force along each finger's actuated directions",
        False,
    ),
)

LOOP_WRITERS: dict[str, str] = {
    "t": "the loop",
    "t_wall": "the loop",
    "tick": "the loop",
    "compute_s": "the loop",
    "control_seq": "the loop",
    "fault": "the loop",
    "device_pos": "the device bank",
    "device_vel": "the device bank",
    "buttons": "the device bank",
    "device_sample": "the device bank",
    "device_force": "the safety chain",
}
"""The frame's fields written outside the renderer, and by whom: the loop (hapticd.loop.servo),
the device bank (hapticd.loop.device_bank) or the safety chain (hapticd.physics.safety). Every other
field is written by exactly one stage of the renderer's plan (hapticd.physics.render checks it
when it plans)."""


@dataclass(frozen=True)
class StateField:
    """One quantity a tick carries to the next: its one ``writer`` (a stage's name, or a
    part of the loop), the attribute it lives in (``where``), its shape and SI unit. What
    the renderer's stages carry lives in one array, ``Renderer.state``, whose blocks
    (hapticd.physics.kernels.TICK_STATE) the stages hold views of and the tick's one call takes.

    The frame holds what one tick hands from stage to stage; these are what the next tick
    starts from. Where one is also a frame field (``recorded_as``), the recording has it.
    """

    name: str
    writer: str
    where: str
    shape: str
    unit: str
    doc: str
    recorded_as: str = ""


STATE: tuple[StateField, ...] = (
    StateField(
        "proxies",
        "contact",
        "Renderer.state: contact (Contact.state)",
        "(F, kernels.CONTACT_STATE)",
        "m",
        "each finger's god-object proxy (columns 0-2), its radius, its active planes "
        "(-1 past the last) and their multipliers, and the contact kernel's work space; "
        "the first finite tick puts each proxy at its device",
    ),
    StateField(
        "friction_anchors",
        "friction",
        "Renderer.state: anchors (Friction.anchors)",
        "(F, kernels.FRICTION_COLUMNS)",
        "m",
        "each finger's sticking point in the object's body frame, its set flag (cleared "
        "out of contact) and the finger's radius",
    ),
    StateField(
        "object_state",
        "dynamics",
        "SceneObject.state",
        "(18,)",
        "m, m/s, rad/s",
        "the object's position, velocity, spin and rotation (row by row); a fixed object's "
        "never changes",
        "object_pos, object_vel, object_omega, object_rot",
    ),
    StateField(
        "allocator_blend",
        "allocation",
        "Renderer.state: alloc (ContactAllocator.alpha)",
        "()",
        "",
        "the adaptive allocator's weight of the external force, following the task",
        "alpha",
    ),
    StateField(
        "passivity_energy",
        "passivity",
        "Renderer.state: passive (Passivity.energy)",
        "(F,)",
        "J",
        "the energy each finger's port absorbed, as the observer sees it",
        "passivity_energy",
    ),
    StateField(
        "passivity_last_pos",
        "passivity",
        "Renderer.state: passive (Passivity.last_pos)",
        "(F, 3)",
        "m",
        "each finger's position on the last tick (its motion this tick is the difference)",
    ),
    StateField(
        "safety_output",
        "the safety chain",
        "SafetyChain.output",
        "(F, 3)",
        "N",
        "the force sent on the last tick, which the rate limiter starts from",
        "device_force",
    ),
    StateField(
        "safety_ramp",
        "the safety chain",
        "SafetyChain.kernel_arrays: its array (kernels.SAFETY_*)",
        "scalars and (F,)",
        "s",
        "when forces were enabled (ramp up) or the stop ramp began, each deadman's press time"
        " and gate, the clamped and rate-limited ticks' counts",
    ),
)
STATE_NAMES = frozenset(f.name for f in STATE)
STATE_WRITERS = {f.name: f.writer for f in STATE}

_NAMES = frozenset(f.name for f in FIELDS)
NAMES = _NAMES
if not LOOP_WRITERS.keys() <= _NAMES:
    raise RuntimeError("frame fields: LOOP_WRITERS names a field FIELDS does not declare")
if any(a.recorded < b.recorded for a, b in itertools.pairwise(FIELDS)):
    raise RuntimeError("frame fields: every recorded field must come before the unrecorded ones")


def fields_for(n_fingers: int, n_actuators: int) -> list[tuple[FrameField, tuple[int, ...]]]:
    """Every field with its shape resolved for F fingers and r actuated directions."""
    return [(f, f.resolve(n_fingers, n_actuators)) for f in FIELDS]


def _dtype(fields: Sequence[tuple[FrameField, tuple[int, ...]]]) -> np.dtype:
    return np.dtype([(f.name, f.dtype, shape) for f, shape in fields])


def _record_dtype(fields: Sequence[tuple[FrameField, tuple[int, ...]]]) -> np.dtype:
    """The frame's record: the recorded fields packed (the recording's bytes), then the
    others from the next multiple of 8 bytes, so that each field is aligned."""
    names, formats, offsets = [], [], []
    at = 0
    recorded = True
    for f, shape in fields:
        if recorded and not f.recorded:
            at = -(-at // 8) * 8
            recorded = False
        names.append(f.name)
        formats.append((f.dtype, shape))
        offsets.append(at)
        at += np.dtype((f.dtype, shape)).itemsize
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": at})


class Frame:
    """One tick's data for F fingers and r actuated directions (see ``FIELDS``).

    Every field is an attribute holding a view into ``record`` (scalars are 0-d
    views: write ``frame.alpha[()] = 0.5``, read ``float(frame.alpha)``).
    ``recorded`` is the recorded prefix of the record as bytes.
    """

    def __init__(self, n_fingers: int, n_actuators: int) -> None:
        self.n_fingers = n_fingers
        self.n_actuators = n_actuators
        resolved = fields_for(n_fingers, n_actuators)
        self.dtype = _record_dtype(resolved)
        self.recorded_dtype = _dtype([(f, s) for f, s in resolved if f.recorded])
        self.record = np.zeros((), dtype=self.dtype)
        for f, _ in resolved:
            setattr(self, f.name, self.record[f.name])
        # Recorded fields come first, so a tick's record is this prefix of the bytes.
        self.recorded = self.record.reshape(1).view(np.uint8)[: self.recorded_dtype.itemsize]

    def __getattr__(self, name: str) -> np.ndarray:
        # Only reached for names that are not fields: say which exist.
        raise AttributeError(f"the frame has no field {name!r}; fields: {sorted(_NAMES)}")

    def copy(self) -> Frame:
        """A frame holding a copy of this one's values."""
        out = Frame(self.n_fingers, self.n_actuators)
        out.record[()] = self.record
        return out

    def get(self, name: str) -> np.ndarray:
        """Field ``name`` as a view (KeyError for an unknown field)."""
        if name not in _NAMES:
            raise KeyError(f"no frame field {name!r}")
        return self.record[name]

    def sample(self, names: Sequence[str]) -> dict[str, object]:
        """Plain Python values (lists, floats, ints) of ``names``, for JSON."""
        return {n: self.record[n].tolist() for n in names}


def markdown_table() -> str:
    """The recorded fields as a Markdown table (docs/recording.md holds this table)."""
    lines = ["| field | shape | unit | meaning |", "|---|---|---|---|"]
    for f in FIELDS:
        if not f.recorded:
            continue
        shape = "(" + ", ".join(str(s) for s in f.shape) + ("," if len(f.shape) == 1 else "") + ")"
        doc = f.doc.replace("|", "\\|")
        lines.append(f"| `{f.name}` | {shape} | {f.unit} | {doc} |")
    return "\n".join(lines) + "\n"


def item_view(a: np.ndarray) -> memoryview | np.ndarray:
    """``a`` for storing single items (``v[i] = x``, ``v[i, j] = x``): a memoryview when
    Python's memoryview takes its item format (native, aligned), else ``a`` itself (a
    field the record leaves unaligned for some finger counts)."""
    view = memoryview(a)
    return view if view.format in _NATIVE_FORMATS else a


_NATIVE_FORMATS = frozenset("dBIL")
