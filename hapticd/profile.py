"""Profiles: YAML files to a frozen, typed configuration that rejects unknown keys.

Every quantity is SI and its unit is in the key name (``_m``, ``_n``,
``_n_per_m``, ``_hz``, ``_s``). ``load_profile`` raises ``ProfileError`` naming
the file, the dotted key path and what was expected. See docs/profiles.md.
"""

from __future__ import annotations

import difflib
import functools
import math
import os
import re
import stat
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar, Union, get_args

import yaml
import yaml.composer
import yaml.constructor
import yaml.parser
import yaml.reader
import yaml.resolver
import yaml.scanner
from annotated_types import Ge, Le
from hapticd_drivers import registry
from hapticd_drivers.registry import BACKENDS, REQUIRED, Backend
from pydantic import (
    AfterValidator,
    AllowInfNan,
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    StringConstraints,
    ValidationError,
    create_model,
    field_validator,
    model_validator,
)

from hapticd import params
from hapticd.loop.mount import mount_rotation
from hapticd.loop.pacing import SPIN_MARGIN_S
from hapticd.loop.realtime import cpu_problem
from hapticd.params import flow_nesting_beyond as _flow_nesting_beyond

PROFILE_VERSION = 1
DOCS = "docs/profiles.md"
UNIT_TOL = 1e-3

# Strict scalars: a YAML bool or string is not a number, a float is not an integer, and no
# number is NaN or infinite. Every number also has a physical range where it is declared.
Float = Annotated[float, Strict(), AllowInfNan(False)]
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
# Strings: bounded, so no message echoes a megabyte; a path at most as long as Linux's.
Name = Annotated[str, Strict(), StringConstraints(min_length=1, max_length=64)]
PathText = Annotated[str, Strict(), StringConstraints(min_length=1, max_length=4096)]
Vec3 = tuple[Float, Float, Float]
# A position in the workspace, m; an angle of at most one turn either way, rad; an
# acceleration of at most about 10 g, m/s^2.
Position = tuple[
    Annotated[Float, Ge(-1.0), Le(1.0)],
    Annotated[Float, Ge(-1.0), Le(1.0)],
    Annotated[Float, Ge(-1.0), Le(1.0)],
]
_Angle = Annotated[Float, Ge(-math.tau), Le(math.tau)]
Angles = tuple[_Angle, _Angle, _Angle]
_Accel = Annotated[Float, Ge(-100.0), Le(100.0)]
Acceleration = tuple[_Accel, _Accel, _Accel]
_SCALAR_TYPES: dict[type, Any] = {float: Float, int: Int, bool: Bool, str: PathText}
M = TypeVar("M", bound=BaseModel)


class ProfileError(ValueError):
    """A profile that cannot be used; the message names file, key path and expectation."""


def param_field(name: str, **kwargs: Any) -> Any:
    """A pydantic Field for the profile key where the settable parameter ``name`` starts,
    with that parameter's range (hapticd.params), so a profile and the control protocol
    accept the same values. ``kwargs`` go to Field (default, description, ...)."""
    spec = params.PARAMS[name]
    if spec.lo is not None:
        kwargs["gt" if spec.lo_open else "ge"] = spec.lo
    if spec.hi is not None:
        kwargs["le"] = spec.hi
    if spec.max_per_finger is not None:
        kwargs["max_length"] = spec.max_per_finger
    kwargs.setdefault("description", spec.doc)
    return Field(**kwargs)


# Built from the spec's names at import, so a type checker sees only str here.
def _allocator_name(value: object) -> object:
    """A built-in allocator's name, or an installed plugin's (looked for only then)."""
    if isinstance(value, str) and value not in params.ALLOCATORS:
        from hapticd.allocation import plugins

        if not plugins.is_known(value):
            raise ValueError(plugins.unknown(value[:200]))
    return value


# A built-in's name, or an installed allocator plugin's (hapticd.allocation.plugins).
AllocatorName = Annotated[str, AfterValidator(_allocator_name)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MountConfig(_Strict):
    """Where a device's frame sits in the world: x_world = s R x_dev + t, v_world = s R v_dev,
    force to the device R^T f_world (docs/devices.md, "Mounting")."""

    position_m: Position = Field(
        default=(0.0, 0.0, 0.0),
        description="the device frame's origin in the world, m (within 1 m of the world's "
        "origin, as any position of the rig)",
    )
    orientation_rpy_rad: Vec3 = Field(
        default=(0.0, 0.0, 0.0),
        description="the device frame's roll, pitch, yaw in the world (fixed x, y, z axes), rad",
    )
    workspace_scale: Float = Field(
        default=1.0,
        gt=0.0,
        le=10.0,
        description="s: device motion is scaled by s into the world; the hand feels a world "
        "stiffness k as k s",
    )

    @field_validator("position_m")
    @classmethod
    def _finite_position(cls, v: Vec3) -> Vec3:
        if not all(math.isfinite(c) for c in v):
            raise ValueError(f"the mount position must be 3 finite numbers in m, got {list(v)}")
        return v

    @field_validator("orientation_rpy_rad")
    @classmethod
    def _rotation(cls, v: Vec3) -> Vec3:
        mount_rotation(v)  # ValueError saying what is wrong
        return v

    @field_validator("workspace_scale")
    @classmethod
    def _finite_scale(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError(f"the workspace scale must be a finite number, got {v}")
        return v


def _device_model(b: Backend) -> type[_Strict]:
    """The profile model of one backend's ``device`` section, built from its registry keys,
    and the mount every device has."""
    fields: dict[str, Any] = {"backend": (Literal[b.name], ...)}  # type: ignore[valid-type]
    fields["mount"] = (MountConfig, Field(default=MountConfig(), description=MountConfig.__doc__))
    for k in b.keys:
        strict = _SCALAR_TYPES[k.type]
        kind: Any = strict | None if k.optional else strict
        bounds = {n: v for n, v in (("gt", k.gt), ("ge", k.ge), ("le", k.le)) if v is not None}
        default = ... if k.default is REQUIRED else k.default
        fields[k.name] = (kind, Field(default=default, description=k.doc, **bounds))
    name = f"{b.name.capitalize()}DeviceConfig"
    model = create_model(name, __base__=_Strict, __doc__=b.doc, **fields)
    return model


# One model per registered backend (drivers/registry.py declares their keys).
DEVICE_MODELS: dict[str, type[_Strict]] = {name: _device_model(b) for name, b in BACKENDS.items()}

DeviceConfig = Annotated[
    Union[tuple(DEVICE_MODELS.values())],  # type: ignore[valid-type]  # noqa: UP007
    Field(discriminator="backend"),
]


def _unit(v: Vec3, what: str) -> Vec3:
    n = math.sqrt(sum(c * c for c in v))  # inf for huge components: not a unit vector
    if not math.isfinite(n) or abs(n - 1.0) > UNIT_TOL:
        raise ValueError(
            f"{what} must be a unit vector (norm 1 within {UNIT_TOL}), got norm {n:.6g}"
        )
    return (v[0] / n, v[1] / n, v[2] / n)


class DeadmanButtonConfig(_Strict):
    """A deadman button: the finger gets force only while it is held."""

    button: Int = Field(
        ge=0, le=31, description="the button's index on the finger's device (bit of buttons)"
    )
    role: Literal["deadman"]
    ramp_s: Float = Field(
        default=0.25,
        ge=0,
        le=10,
        description="after a press, the finger's force ramps from zero to full over this "
        "time, s; a release zeroes it at once",
    )


class ResponseButtonConfig(_Strict):
    """A response key for experiments: its presses are button_down events tagged
    ``response`` (docs/control.md)."""

    button: Int = Field(
        ge=0, le=31, description="the button's index on the finger's device (bit of buttons)"
    )
    role: Literal["response"]
    label: Name | None = Field(
        default=None,
        description="the tag its events carry as response; default FINGER-BUTTON, e.g. thumb-1",
    )


ButtonConfig = Annotated[DeadmanButtonConfig | ResponseButtonConfig, Field(discriminator="role")]
BUTTON_ROLES: tuple[str, ...] = tuple(
    get_args(c.model_fields["role"].annotation)[0]
    for c in (DeadmanButtonConfig, ResponseButtonConfig)
)


class FingerConfig(_Strict):
    """One fingertip: its thimble sphere, its device, its actuated force directions and what
    its device's buttons do."""

    name: Name
    radius_m: Float = Field(default=0.008, gt=0, le=0.05, description="fingertip sphere radius, m")
    device: DeviceConfig
    actuated_directions: tuple[Vec3, ...] = param_field(
        "actuated_directions",
        min_length=0,
        description="unit force directions the device renders for this finger (0-3)",
    )

    buttons: tuple[ButtonConfig, ...] = Field(
        default=(),
        max_length=32,
        description="roles of the device's buttons: at most one deadman, any response keys",
    )

    @field_validator("actuated_directions")
    @classmethod
    def _units(cls, v: tuple[Vec3, ...]) -> tuple[Vec3, ...]:
        return tuple(_unit(d, f"direction {i}") for i, d in enumerate(v))

    @field_validator("buttons")
    @classmethod
    def _one_role_each(
        cls, v: tuple[DeadmanButtonConfig | ResponseButtonConfig, ...]
    ) -> tuple[DeadmanButtonConfig | ResponseButtonConfig, ...]:
        seen = [b.button for b in v]
        dup = sorted({b for b in seen if seen.count(b) > 1})
        if dup:
            raise ValueError(f"each button may have one role; repeated: {dup}")
        if sum(b.role == "deadman" for b in v) > 1:
            raise ValueError("at most one deadman button per finger")
        return v

    @property
    def deadman(self) -> DeadmanButtonConfig | None:
        """This finger's deadman button, if it has one."""
        return next((b for b in self.buttons if isinstance(b, DeadmanButtonConfig)), None)

    def responses(self) -> dict[int, str]:
        """Button index -> response label of this finger's response keys."""
        return {
            b.button: b.label or f"{self.name}-{b.button}"
            for b in self.buttons
            if isinstance(b, ResponseButtonConfig)
        }


class FrictionConfig(_Strict):
    """Coulomb friction coefficients (dimensionless); 0 and 0 turn friction off."""

    static: Float = param_field("friction", default=0.0, description="static coefficient")
    dynamic: Float = param_field("friction", default=0.0, description="dynamic coefficient")
    torsion_m: Float = Field(
        default=0.0,
        ge=0,
        le=0.05,
        description="soft-finger torsional friction: largest moment about the contact normal "
        "per newton of normal force, m (about contact patch radius x friction)",
    )

    @model_validator(mode="after")
    def _order(self) -> FrictionConfig:
        if self.dynamic > self.static:
            raise ValueError("dynamic friction must not exceed static friction")
        return self

    @property
    def enabled(self) -> bool:
        return self.static > 0.0


class ObjectConfig(_Strict):
    """The grasped object: a box or a convex mesh, fixed or free, and its contact material."""

    shape: Literal["box", "mesh"] = "box"
    size_m: Vec3 | None = Field(default=None, description="box edge lengths along x, y, z, m")
    mesh: PathText | None = Field(
        default=None,
        description="STL/OBJ/PLY file (relative to the profile); its convex hull is used",
    )
    mesh_scale: Float = Field(default=1.0, gt=0, le=1000, description="factor from mesh units to m")
    position_m: Position = Field(
        default=(0.0, 0.0, 0.0), description="centre of mass, each coordinate in [-1, 1] m"
    )
    orientation_rpy_rad: Angles = Field(
        default=(0.0, 0.0, 0.0),
        description="roll, pitch, yaw (x, y, z fixed axes), each in [-2 pi, 2 pi] rad",
    )
    fixed: Bool = True
    mass_kg: Float | None = param_field("mass_kg", default=None, description="needed when free, kg")
    stiffness_n_per_m: Float = param_field("stiffness_n_per_m")
    damping_n_s_per_m: Float = param_field("damping_n_s_per_m", default=0.0)
    friction: FrictionConfig = FrictionConfig()

    @field_validator("size_m")
    @classmethod
    def _positive(cls, v: Vec3 | None) -> Vec3 | None:
        if v is not None and any(not (0 < s <= 1.0) for s in v):
            raise ValueError(f"every edge length must be in (0, 1] m, got {list(v)}")
        return v

    @model_validator(mode="after")
    def _complete(self) -> ObjectConfig:
        if self.shape == "box" and self.size_m is None:
            raise ValueError("a box needs size_m")
        if self.shape == "mesh" and self.mesh is None:
            raise ValueError("a mesh object needs mesh: PATH")
        if not self.fixed and self.mass_kg is None:
            raise ValueError("a free object needs mass_kg")
        return self


class SurfaceConfig(_Strict):
    """Material of the ground or the walls."""

    stiffness_n_per_m: Float = Field(default=2000.0, gt=0, le=1e5)
    damping_n_s_per_m: Float = Field(default=5.0, ge=0, le=1e3)
    friction: FrictionConfig = FrictionConfig(static=0.6, dynamic=0.5)


class GroundConfig(SurfaceConfig):
    """A horizontal ground plane: nothing goes below height_m."""

    height_m: Float = Field(ge=-1, le=1, description="height of the ground plane (world z), m")


class WallsConfig(SurfaceConfig):
    """Workspace walls: vertical planes bounding |x| and |y| around the origin."""

    half_width_m: tuple[Float, Float] = Field(
        description="wall distance from the origin in x, y, m"
    )

    @field_validator("half_width_m")
    @classmethod
    def _positive(cls, v: tuple[float, float]) -> tuple[float, float]:
        if any(not (0 < s <= 1.0) for s in v):
            raise ValueError(f"half widths must be in (0, 1] m, got {list(v)}")
        return v


class SceneConfig(_Strict):
    object: ObjectConfig
    gravity_m_s2: Acceleration | None = Field(
        default=None,
        description="gravity acceleration, m/s^2, each component in [-100, 100] "
        "(e.g. [0, 0, -9.81]); none: off",
    )
    ground: GroundConfig | None = None
    walls: WallsConfig | None = None
    substeps: int | Literal["auto"] = Field(
        default="auto",
        description="dynamics integration steps per tick (1-64), or auto: enough for the "
        "object's mass, the contact stiffness and damping",
    )

    @field_validator("substeps", mode="before")
    @classmethod
    def _substeps(cls, v: object) -> object:
        # Checked before the union, so a bad value gets one message, not one per member.
        if v == "auto" or (type(v) is int and 1 <= v <= 64):
            return v
        raise ValueError("substeps must be 1-64 or auto (an integer, or the word auto)")


BoxConfig = ObjectConfig  # the name used before meshes and free objects


class RealtimeConfig(_Strict):
    """Real-time settings for the servo thread (docs/daemon.md); each falls back with a
    message when not permitted, unless ``required``."""

    enabled: Bool = Field(default=True, description="try SCHED_FIFO, mlockall and timer slack")
    priority: Int = Field(default=80, ge=1, le=99, description="SCHED_FIFO priority")
    cpu: Int | None = Field(
        default=None,
        ge=0,
        le=4095,
        description="pin the servo thread to this CPU, one this process may run on "
        "(its affinity: os.sched_getaffinity)",
    )
    lock_memory: Bool = Field(default=True, description="mlockall: no page faults in the loop")
    timer_slack_ns: Int = Field(default=1, ge=1, le=50_000_000, description="timer slack, ns")
    required: Bool = Field(
        default=False, description="refuse to run when a setting cannot be applied"
    )

    @field_validator("cpu")
    @classmethod
    def _usable_cpu(cls, v: int | None) -> int | None:
        if v is not None and (why := cpu_problem(v)) is not None:
            raise ValueError(why)
        return v


class LoopConfig(_Strict):
    rate_hz: Float = Field(default=1000.0, ge=100.0, le=8000.0, description="servo rate, Hz")
    max_consecutive_overruns: Int = Field(
        default=200,
        ge=0,
        le=1_000_000,
        description="this many periods in a row longer than 1.1x nominal latch a fault; 0: off",
    )
    realtime: RealtimeConfig = RealtimeConfig()
    gil_switch_interval_s: Float = Field(
        default=5e-4,
        ge=1e-6,
        le=0.1,
        description="Python's GIL switch interval while the loop runs, s: the longest the "
        "loop waits for the GIL held by the control thread (Python's default is 0.005)",
    )
    spin_s: Float = Field(
        default=SPIN_MARGIN_S,
        ge=0.0,
        le=0.01,
        description="the last part of each period the paced loop spins instead of sleeping, s "
        "(at most half the period): less spin, less CPU and more period error",
    )


class RobustnessConfig(_Strict):
    """Singularity-robust allocation (docs/allocation.md)."""

    eps: Float = Field(
        default=0.2, gt=0, lt=1, description="singular-value threshold below which gains are damped"
    )
    min_separation_m: Float = Field(
        default=0.005,
        gt=0,
        lt=1,
        description="contacts closer than this blend internal subspaces, m",
    )
    contact_onset_n: Float = Field(
        default=0.05, ge=0, lt=10, description="a contact weaker than this joins gradually, N"
    )


class AdaptiveConfig(_Strict):
    """The task-adaptive allocator's switch from internal to external forces."""

    ratio_low: Float = Field(default=0.2, ge=0, lt=1, description="external ratio where it starts")
    ratio_high: Float = Field(default=0.6, gt=0, le=1, description="external ratio where it ends")
    time_constant_s: Float = Field(default=0.1, ge=0, le=10, description="lag of the switch, s")

    @model_validator(mode="after")
    def _ordered(self) -> AdaptiveConfig:
        if not self.ratio_low < self.ratio_high:
            raise ValueError("ratio_low must be below ratio_high")
        return self


class PassivityConfig(_Strict):
    """The time-domain passivity controller (docs/analysis.md, "Passivity controller")."""

    enabled: bool = Field(
        default=False, description="run the passivity observer and controller on every tick"
    )
    velocity_threshold_m_per_s: float = Field(
        default=0.005,
        gt=0,
        le=1.0,
        description="speed along a finger's actuated directions below which the controller "
        "does not act (full authority at twice it), m/s",
    )
    max_damping_n_s_per_m: float = Field(
        default=20.0,
        gt=0,
        le=100.0,
        description="most damping the controller adds along a finger's actuated directions, N s/m",
    )


class RenderingConfig(_Strict):
    allocator: AllocatorName = "if"
    robustness: RobustnessConfig = RobustnessConfig()
    adaptive: AdaptiveConfig = AdaptiveConfig()
    passivity: PassivityConfig = PassivityConfig()
    actuation_frame: Literal["world", "grasp"] = Field(
        default="world",
        description="frame of actuated_directions: world, or the grasp frame "
        "(x from the first finger to the second, z up)",
    )
    kernels: Literal["python", "compiled", "auto"] = Field(
        default="auto",
        description="per-tick physics kernels: python (the readable reference code), "
        "compiled (numba, compiled before the first tick and cached on disk) or auto "
        "(compiled); without a working numba the Python code renders, with a message "
        "(docs/daemon.md)",
    )


class RecordingConfig(_Strict):
    directory: str | None = Field(
        default=None,
        min_length=1,
        description="where record_start over the control socket may write (relative to the "
        "profile's folder); none: the service's state directory",
    )
    rate_hz: Float | None = Field(
        default=None,
        gt=0,
        description="record this many ticks per second, Hz: every (loop.rate_hz / rate_hz)-th "
        "tick, a whole number (docs/recording.md says what is lost); none: every tick",
    )

    def record_every(self, loop_rate_hz: float) -> int:
        """Every how many ticks one is recorded (1: each)."""
        if self.rate_hz is None:
            return 1
        return max(1, round(loop_rate_hz / self.rate_hz))


class LslConfig(_Strict):
    """Lab Streaming Layer outlets (docs/lsl.md); read at start (a reload keeps them)."""

    enabled: Bool = Field(
        default=False,
        description="publish the loop's ticks and events as LSL streams, as hapticd run --lsl "
        "does (needs pylsl: pip install 'hapticd[lsl]')",
    )
    decimation: Int = Field(
        default=1,
        ge=1,
        le=1000,
        description="publish every Nth tick: the numeric stream's rate is loop.rate_hz / N, "
        "Hz (markers keep their own tick's time)",
    )


class SafetyConfig(_Strict):
    max_force_n: Float = param_field(
        "force_limit_n",
        description="force limit per finger, N (the device's own limit also applies)",
    )
    ramp_s: Float = Field(default=0.5, ge=0, le=10, description="force ramp after enabling, s")
    stop_ramp_s: Float = Field(
        default=0.05, ge=0, le=2, description="forces ramp to zero over this time on a stop, s"
    )
    max_force_rate_n_per_s: Float | None = Field(
        default=5000.0,
        gt=0,
        le=1e6,
        description="largest change of a finger's force, N/s; none: off",
    )
    workspace_center_m: Position = (0.0, 0.0, 0.0)
    workspace_radius_m: Float | None = Field(
        default=None, gt=0, le=2, description="fingers beyond this sphere latch a fault, m"
    )
    watchdog_s: Float | None = Field(
        default=0.1,
        gt=0,
        le=10,
        description="longest wall time between ticks, s; none: off (refused with a hardware "
        "backend unless allow_no_watchdog)",
    )
    allow_no_watchdog: Bool = Field(
        default=False,
        description="run a hardware backend with watchdog_s none all the same: a stalled loop "
        "then leaves its last force on the device until the device's own watchdog, if any, "
        "acts; warned about at every start (bench work only, never a subject)",
    )
    max_device_speed_m_per_s: Float = Field(
        default=5.0,
        gt=0,
        le=100,
        description="a device reporting a faster speed (its own frame), or a non-finite "
        "position or velocity, latches a fault: a glitched sample, not a hand, m/s",
    )
    reconnect: Bool = Field(
        default=False,
        description="on a device error keep running (forces off) and reopen the device when "
        "it returns; false: end the run",
    )


class Profile(_Strict):
    """A complete hapticd profile (see docs/profiles.md)."""

    version: Literal[1] = 1
    name: Annotated[str, Strict(), StringConstraints(min_length=1, max_length=200)]
    description: Annotated[str, Strict(), StringConstraints(max_length=10_000)] = ""
    loop: LoopConfig = LoopConfig()
    fingers: tuple[FingerConfig, ...] = Field(min_length=1, max_length=5)
    rendering: RenderingConfig = RenderingConfig()
    scene: SceneConfig
    safety: SafetyConfig
    recording: RecordingConfig = RecordingConfig()
    lsl: LslConfig = LslConfig()

    source: Path | None = Field(default=None, exclude=True, description="file it was loaded from")

    @field_validator("version", mode="before")
    @classmethod
    def _version(cls, v: object) -> object:
        if type(v) is not int:  # true == 1, but a bool is no version number
            raise ValueError(f"version must be the number {PROFILE_VERSION}")
        return v

    @field_validator("fingers", mode="after")
    @classmethod
    def _unique_names(cls, fingers: tuple[FingerConfig, ...]) -> tuple[FingerConfig, ...]:
        # Here, not in the model's check, so the error points at `fingers`, not the top level.
        names = [f.name for f in fingers]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"finger names must be unique, repeated: {sorted(dup)}")
        return fingers

    @model_validator(mode="after")
    def _consistent(self) -> Profile:
        if self.rendering.actuation_frame == "grasp" and len(self.fingers) < 2:
            raise ValueError("actuation_frame 'grasp' needs at least two fingers")
        rec, loop = self.recording.rate_hz, self.loop.rate_hz
        if rec is not None and (
            rec > loop or abs(loop / rec - round(loop / rec)) > 1e-9 * loop / rec
        ):
            raise ValueError(
                f"recording.rate_hz {rec:g} Hz must divide loop.rate_hz {loop:g} Hz a whole "
                f"number of times (e.g. {loop / 2:g}, {loop / 5:g} or {loop / 10:g} Hz)"
            )
        return self

    @property
    def finger_names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fingers)

    def resolve_path(self, path: str) -> Path:
        """A path from the profile, relative to the profile's folder."""
        p = Path(path)
        if p.is_absolute() or self.source is None:
            return p
        return self.source.parent / p


# -- reading a profile: YAML without aliases or duplicate keys, within bounds -------------

# A profile is a few kilobytes and a few hundred values; these bounds are far above any
# real one and keep a hostile file's parsing, validation and error message short.
MAX_BYTES = 256 << 10
MAX_NODES = 1_000
MAX_DEPTH = 64
MAX_ERRORS_SHOWN = 20
_SHOWN_CHARS = 60

Path_ = tuple[int | str, ...]


class _Refused(yaml.YAMLError):
    """A YAML construct a profile may not use; ``line`` is 1-based."""

    def __init__(self, line: int, message: str) -> None:
        super().__init__(message)
        self.line = line
        self.message = message


if yaml.__with_libyaml__:
    # YAML events from libyaml: about ten times faster than PyYAML's own parser.
    from yaml.cyaml import CParser as _Events
else:  # pragma: no cover - PyYAML built without libyaml

    class _Events(yaml.reader.Reader, yaml.scanner.Scanner, yaml.parser.Parser):  # type: ignore[no-redef]
        """YAML events from PyYAML's pure-Python parser."""

        def __init__(self, stream: str) -> None:
            yaml.reader.Reader.__init__(self, stream)
            yaml.scanner.Scanner.__init__(self)
            yaml.parser.Parser.__init__(self)


class _ProfileLoader(
    yaml.composer.Composer, _Events, yaml.constructor.SafeConstructor, yaml.resolver.Resolver
):
    """A safe loader (PyYAML's composer, safe constructor and resolver on YAML events)
    that refuses anchors and aliases (an alias bomb expands to billions of values), merge
    keys and duplicate keys, and bounds nesting and size."""

    def __init__(self, stream: str) -> None:
        _Events.__init__(self, stream)
        yaml.composer.Composer.__init__(self)
        yaml.constructor.SafeConstructor.__init__(self)
        yaml.resolver.Resolver.__init__(self)
        self._nodes = 0
        self._depth = 0

    def compose_node(self, parent: yaml.Node | None, index: object) -> yaml.Node:
        event = self.peek_event()
        line = event.start_mark.line + 1
        if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None) is not None:
            raise _Refused(
                line,
                "anchors and aliases (&name, *name) are not allowed in a profile; "
                "write the value out in full",
            )
        self._nodes += 1
        if self._nodes > MAX_NODES:
            raise _Refused(line, f"more than {MAX_NODES} values; a profile is far smaller")
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise _Refused(line, f"values nested more than {MAX_DEPTH} levels deep")
            return super().compose_node(parent, index)  # type: ignore[misc]
        finally:
            self._depth -= 1

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[object, int] = {}
        for key_node, _ in node.value:
            line = key_node.start_mark.line + 1
            if key_node.tag == "tag:yaml.org,2002:merge":
                raise _Refused(line, "merge keys (<<) are not allowed in a profile")
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.get(key)
            except TypeError:
                raise _Refused(line, "a key must be a name, not a list or mapping") from None
            if first is not None:
                raise _Refused(
                    line, f"duplicate key {key!r} (first at line {first}); give each key once"
                )
            seen[key] = line
        return super().construct_mapping(node, deep=deep)

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep=deep)
        except yaml.YAMLError:
            raise
        except (ValueError, OverflowError, TypeError) as exc:
            # e.g. an integer of more digits than Python converts.
            raise _Refused(node.start_mark.line + 1, f"cannot read this value: {exc}") from None


def _line_map(node: yaml.Node) -> dict[Path_, int]:
    """The 1-based line of every key and list item of a document, by key path."""
    lines: dict[Path_, int] = {(): node.start_mark.line + 1}
    todo: list[tuple[Path_, yaml.Node]] = [((), node)]
    while todo:
        path, n = todo.pop()
        if isinstance(n, yaml.MappingNode):
            for k, v in n.value:
                if isinstance(k, yaml.ScalarNode):
                    sub = (*path, k.value)
                    lines[sub] = k.start_mark.line + 1
                    todo.append((sub, v))
        elif isinstance(n, yaml.SequenceNode):
            for i, v in enumerate(n.value):
                lines[(*path, i)] = v.start_mark.line + 1
                todo.append(((*path, i), v))
    return lines


def _read_yaml(
    raw: bytes, p: Path, what: str = "profile", error: type[ValueError] = ProfileError
) -> tuple[object, dict[Path_, int]]:
    """The document in ``raw`` and the line of each key path (``error`` naming ``p``)."""
    if len(raw) > MAX_BYTES:
        raise error(
            f"{p}: larger than {MAX_BYTES // 1024} KiB; a {what} is a few kilobytes "
            "(is this the right file?)"
        )
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise error(
            f"{p}: not UTF-8 text: byte 0x{raw[exc.start]:02x} at line {line}; save the "
            f"{what} as UTF-8"
        ) from None
    loader = _ProfileLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None, {}
        return loader.construct_document(node), _line_map(node)
    except _Refused as exc:
        raise error(f"{p}: line {exc.line}: {exc.message}") from None
    except yaml.YAMLError as exc:
        deep = _flow_nesting_beyond(text, MAX_DEPTH)
        if deep is not None:
            raise error(
                f"{p}: line {deep}: values nested more than {MAX_DEPTH} levels deep"
            ) from None
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise error(f"{p}: not valid YAML{where}: {problem}") from None
    finally:
        loader.dispose()


def _format_loc(
    loc: tuple[int | str, ...], data: object, root: type[BaseModel] | None = None
) -> tuple[str, Path_]:
    """The dotted key path of pydantic's ``loc`` in ``data`` (list indices with the item's
    name where it has one), and that path as keys and indices. Pydantic's own labels (a
    union member such as ``int``, a discriminator tag such as ``replay``) are left out:
    they are not keys the user wrote."""
    parts: list[str] = []
    path: list[int | str] = []
    node: object = data
    known = _all_keys(root or Profile)
    for n, item in enumerate(loc):
        last = n == len(loc) - 1
        if isinstance(item, int) and isinstance(node, list | tuple):
            child = node[item] if 0 <= item < len(node) else None
            name = child.get("name") if isinstance(child, dict) else None
            shown = name if isinstance(name, str) and 0 < len(name) <= 40 else None
            parts.append(f"[{item}]" if shown is None else f"[{item}:{shown}]")
            path.append(item)
            node = child
        elif isinstance(node, dict) and (item in node or (last and item in known)):
            parts.append(("." if parts else "") + str(item))
            path.append(item)
            node = node.get(item)
        # else: pydantic's label, not the user's key
    return "".join(parts) or "(top level)", tuple(path)


@functools.cache
def _all_keys(root: type[BaseModel]) -> frozenset[str]:
    """Every key of ``root`` and the models nested in it (for "did you mean" hints)."""
    keys: set[str] = set()
    todo: list[type[BaseModel]] = [root]
    while todo:
        model = todo.pop()
        for name, field in model.model_fields.items():
            keys.add(name)
            for sub in _models_in(field.annotation):
                if sub not in todo:
                    todo.append(sub)
    return frozenset(keys)


def _models_in(annotation: object) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    out: list[type[BaseModel]] = []
    for arg in getattr(annotation, "__args__", ()) or ():
        out.extend(_models_in(arg))
    return out


def _explain(err: dict, root: type[BaseModel] | None = None, docs: str = DOCS) -> str:
    kind = err["type"]
    if kind == "extra_forbidden":
        key = str(err["loc"][-1])
        keys = sorted(_all_keys(root or Profile))
        if key in keys:  # a real key, in the wrong place: suggesting itself would not help
            backend = next((str(p) for p in err["loc"][:-1] if p in BACKENDS), None)
            where = f"the {backend} backend" if backend else "this section"
            return (
                f"unknown key: {where} has no key {key!r} (the keys of each section are "
                f"listed in {docs})"
            )
        # Keys carry their unit ("mass_kg"): a key written without it is the likeliest slip.
        close = [k for k in keys if k.startswith(key + "_")][:1]
        close = close or difflib.get_close_matches(key, keys, n=1, cutoff=0.75)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        return f"unknown key{hint} (the keys are listed in {docs})"
    if kind == "missing":
        if isinstance(err["loc"][-1], int):
            return f"too few items (item {err['loc'][-1]} is missing)"
        return "required key is missing"
    if kind == "tuple_type":
        return "Input should be a list"  # pydantic's tuple is a YAML list
    if kind == "union_tag_invalid":  # pydantic's own message repeats the whole tag
        loc = err["loc"]
        if len(loc) >= 2 and loc[-2] == "buttons":  # a button's role
            got = err["input"].get("role") if isinstance(err["input"], dict) else None
            return f"unknown role {_shown(got)}; the roles: {', '.join(BUTTON_ROLES)}"
        got = err["input"].get("backend") if isinstance(err["input"], dict) else None
        refused = registry.problem(got) if isinstance(got, str) else None
        if refused is not None:  # an installed backend that was refused: say why
            return f"backend {_shown(got)} is refused: {refused.message()}"
        return f"unknown backend {_shown(got)}; the backends: {', '.join(BACKENDS)}"
    msg = str(err["msg"]).removeprefix("Value error, ")
    return msg if len(msg) <= 300 else msg[:297] + "..."


def _shown(value: object) -> str:
    """A short repr of a rejected value (a long one is cut)."""
    text = repr(value) if not isinstance(value, int) or abs(value) < 10**40 else "a huge integer"
    return text if len(text) <= _SHOWN_CHARS else text[: _SHOWN_CHARS - 3] + "..."


def _line_note(path: Path_, lines: dict[Path_, int | str], missing: bool) -> str:
    """`` (line N)`` for the key at ``path``; for a missing key, the mapping that lacks it.
    A line that is a string says where the value came from instead (``from --set``)."""

    def note(line: int | str) -> str:
        return f" ({line})" if isinstance(line, str) else f" (line {line})"

    if missing:
        line = lines.get(path[:-1])
        if line is None or not path[:-1]:
            return ""
        return note(line) if isinstance(line, str) else f" (in the mapping at line {line})"
    for n in range(len(path), 0, -1):
        if path[:n] in lines:
            return note(lines[path[:n]])
    return ""


def validate_document(
    model: type[M],
    data: object,
    source: str | Path,
    lines: dict[Path_, int | str] | None = None,
    *,
    what: str = "profile",
    docs: str = DOCS,
    error: type[ValueError] = ProfileError,
) -> M:
    """Validate an already-parsed YAML document into ``model``; on failure raise ``error``
    with one line per problem naming ``source``, the dotted key path, what was expected
    and the key's line (from ``lines``, the loader's map); ``what`` names the kind of
    file, ``docs`` where its keys are listed."""
    if not isinstance(data, dict):
        raise error(f"{source}: expected a mapping of keys at the top level")
    lines = lines or {}
    if "source" in data:  # the model's record of the file, not a key a file sets
        raise error(
            f"{source}: 1 error(s) in {what}\n  source: unknown key (the keys are listed in "
            f"{docs}){_line_note(('source',), lines, False)}"
        )
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise error(_format_errors(exc, data, source, lines, model, what, docs)) from None


def parse_profile(
    data: object, source: str | Path = "<profile>", lines: dict[Path_, int | str] | None = None
) -> Profile:
    """Validate an already-parsed YAML document into a Profile; ``lines`` (from the
    loader) gives each key path's line for the messages."""
    prof = validate_document(Profile, data, source, lines)
    return prof.model_copy(update={"source": Path(source)}) if source else prof


def _format_errors(
    exc: ValidationError,
    data: object,
    source: str | Path,
    lines: dict[Path_, int | str],
    root: type[BaseModel] | None = None,
    what: str = "profile",
    docs: str = DOCS,
) -> str:
    """One line per error: key path, what was expected, the value given, the line."""
    errors = exc.errors(include_url=False, include_context=False)
    locs = [tuple(e["loc"]) for e in errors]
    # A list whose items failed also reports "too short"; that one only confuses.
    errors = [
        e
        for e in errors
        if not (
            e["type"] == "too_short"
            and any(len(o) > len(e["loc"]) and o[: len(e["loc"])] == tuple(e["loc"]) for o in locs)
        )
    ]
    # One entry per key: a union's members each report their own error for the same key.
    by_key: dict[str, list[str]] = {}
    for err in errors:
        loc = tuple(err["loc"])
        missing = err["type"] == "missing"
        if missing and loc and isinstance(loc[-1], int):
            loc = loc[:-1]  # a tuple too short: reported at the list, not its absent item
            missing = False
        where, path = _format_loc(loc, data, root)
        got = err.get("input")
        # An unknown key's value is never shown: the key is wrong, whatever it holds (and a
        # file that is no profile at all must not be echoed back: reload over the socket).
        quiet = missing or err["type"] == "extra_forbidden" or isinstance(got, dict | list)
        shown = "" if quiet else f" (got {_shown(got)})"
        text = f"{_explain(err, root, docs)}{shown}{_line_note(path, lines, missing)}"
        msgs = by_key.setdefault(where, [])
        if text not in msgs:
            msgs.append(text)
    out = [f"{source}: {len(by_key)} error(s) in {what}"]
    for where, msgs in list(by_key.items())[:MAX_ERRORS_SHOWN]:
        out.append(f"  {where}: {'; or '.join(msgs)}")
    if len(by_key) > MAX_ERRORS_SHOWN:
        out.append(f"  ... and {len(by_key) - MAX_ERRORS_SHOWN} more")
    return "\n".join(out)


def read_document(
    path: str | Path, *, what: str = "profile", error: type[ValueError] = ProfileError
) -> tuple[object, dict[Path_, int]]:
    """The YAML document at ``path`` and the line of each key path: a regular file of at
    most ``MAX_BYTES``, read without blocking, without aliases or duplicate keys (``error``
    naming the file, and the line where it can)."""
    p = Path(path)
    try:
        # Non-blocking: a FIFO or device named as a file must not hang a reload.
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise error(f"{p}: cannot read {what}: not a regular file")
            raw = f.read(MAX_BYTES + 1)  # a larger file is refused unread
    except OSError as exc:
        raise error(f"{p}: cannot read {what}: {exc.strerror or exc}") from None
    except error:
        raise
    except ValueError as exc:  # e.g. a NUL byte in the path
        raise error(f"{p!r}: cannot read {what}: {exc}") from None
    return _read_yaml(raw, p, what, error)


_KEY_PATH = re.compile(r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*|\[[^\[\]]+\])*")
_KEY_PART = re.compile(r"([A-Za-z_]\w*)|\[([^\[\]]+)\]")


def parse_override(text: str) -> tuple[str, Path_, object]:
    """``KEY=VALUE`` (``hapticd run --set``) as (the key as written, its key path, the
    value). KEY is a dotted key path whose list items are picked in brackets by index or
    by their ``name`` (``fingers[0].device.max_force_n``, ``fingers[thumb].radius_m``; an
    error message's ``fingers[0:thumb]`` works too); VALUE is a YAML scalar or list, read
    by the profile's loader. ProfileError says what is wrong."""
    key, eq, value = text.partition("=")
    key = key.strip()
    if not eq or not key:
        raise ProfileError(f"--set {text!r}: expected KEY=VALUE, e.g. scene.object.mass_kg=0.1")
    if not _KEY_PATH.fullmatch(key):
        raise ProfileError(
            f"--set {key}: not a key path (dotted keys, list items as [0] or [name]: "
            "fingers[0].device.max_force_n)"
        )
    path: list[int | str] = []
    for m in _KEY_PART.finditer(key):
        if m.group(1) is not None:
            path.append(m.group(1))
        else:
            item = m.group(2).strip()
            index = item.split(":", 1)[0]
            path.append(int(index) if index.isdigit() else item)
    data, _ = _read_yaml(value.encode(), Path(f"--set {key}"))
    if isinstance(data, dict):
        raise ProfileError(f"--set {key}: give one value (a scalar or a list), not a mapping")
    return key, tuple(path), data


def _named(items: list, name: str) -> int:
    """The index of the first mapping in ``items`` whose ``name`` is ``name``, else -1."""
    return next(
        (i for i, v in enumerate(items) if isinstance(v, dict) and v.get("name") == name), -1
    )


def _override_paths(data: object, overrides: Sequence[str]) -> list[Path_]:
    """The key paths (list items by index) the ``overrides`` set in ``data``."""
    out: list[Path_] = []
    for text in overrides:
        _, over, _ = parse_override(text)
        resolved: list[int | str] = []
        node: Any = data
        for part in over:
            if isinstance(part, str) and isinstance(node, list):
                part = _named(node, part)
            resolved.append(part)
            try:
                node = node[part]
            except (KeyError, IndexError, TypeError):
                break
        out.append(tuple(resolved))
    return out


def apply_overrides(data: object, overrides: Sequence[str], source: str | Path) -> object:
    """``data`` (a profile document) with each ``KEY=VALUE`` of ``overrides`` set, in order
    (missing mappings on the way are made); ProfileError naming ``source`` and the key
    for a path the document cannot hold. The result is validated like any profile."""
    if not overrides:
        return data
    if not isinstance(data, dict):
        raise ProfileError(f"{source}: expected a mapping of keys at the top level")
    for text in overrides:
        key, path, value = parse_override(text)
        node: Any = data
        for n, part in enumerate(path):
            last = n == len(path) - 1
            here = "".join(f"[{p}]" if not isinstance(p, str) else f".{p}" for p in path[:n])
            where = f"{source}: --set {key}: {here.lstrip('.') or 'the profile'}"
            if isinstance(part, str) and isinstance(node, list):
                name, part = part, _named(node, part)
                if part < 0:
                    names = [v.get("name") for v in node if isinstance(v, dict)]
                    raise ProfileError(f"{where} has no item named {name!r}; names: {names}")
            if isinstance(part, int):
                if not isinstance(node, list):
                    raise ProfileError(f"{where} is not a list")
                if not 0 <= part < len(node):
                    raise ProfileError(f"{where} has {len(node)} item(s), no [{part}]")
            elif not isinstance(node, dict):
                raise ProfileError(f"{where} is not a mapping of keys")
            if last:
                node[part] = value
            else:
                if isinstance(node, dict) and not isinstance(node.get(part), dict | list):
                    node[part] = {}
                node = node[part]
    return data


def load_profile(path: str | Path, overrides: Sequence[str] = ()) -> Profile:
    """Read and validate the YAML profile at ``path`` (ProfileError naming the file, the
    key, its line and what was expected), with ``overrides`` (``KEY=VALUE``, as ``hapticd
    run --set`` gives them: ``parse_override``) set before it is validated."""
    p = Path(path)
    data, file_lines = read_document(p)
    lines: dict[Path_, int | str] = dict(file_lines)
    if overrides:
        data = apply_overrides(data, overrides, p)
        # A value from --set has no line in the file: its messages say "from --set".
        for over in _override_paths(data, overrides):
            lines = {k: v for k, v in lines.items() if k[: len(over)] != over}
            lines[over] = "from --set"
    try:
        return parse_profile(data, p.resolve(), lines)
    except ProfileError as exc:
        if not overrides:
            raise
        raise ProfileError(f"{exc}\n  (with --set {' --set '.join(overrides)})") from None


JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"


def json_schema() -> dict[str, Any]:
    """The profile's JSON Schema (pydantic's, of ``Profile``) for editors and other tools:
    the keys, their types, bounds, defaults and descriptions; unknown keys are refused
    (``additionalProperties: false``). Fields that are not profile keys (the loaded file's
    ``source``) are left out. A profile that passes it can still fail the checks the schema
    cannot say (a finger's name unique, a free object's mass); ``hapticd check`` is the
    authority."""
    schema = Profile.model_json_schema()
    for name, field in Profile.model_fields.items():
        if field.exclude:
            schema["properties"].pop(name, None)
            if name in schema.get("required", []):
                schema["required"].remove(name)
    return {"$schema": JSON_SCHEMA_DIALECT, **schema, "title": "hapticd profile"}
