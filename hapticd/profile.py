"""Profiles: YAML files to a frozen, typed configuration that rejects unknown keys.

Every quantity is SI and its unit is in the key name (``_m``, ``_n``,
``_n_per_m``, ``_hz``, ``_s``). ``load_profile`` raises ``ProfileError`` naming
the file, the dotted key path and what was expected. See docs/profiles.md.
"""

from __future__ import annotations

import difflib
import math
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar, Union

import yaml
from hapticd_drivers.registry import BACKENDS, REQUIRED, Backend
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    create_model,
    field_validator,
    model_validator,
)

from hapticd import params

PROFILE_VERSION = 1
UNIT_TOL = 1e-3

Vec3 = tuple[float, float, float]
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
AllocatorName = Literal[tuple(params.ALLOCATORS)]  # type: ignore[valid-type]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _device_model(b: Backend) -> type[_Strict]:
    """The profile model of one backend's ``device`` section, built from its registry keys."""
    fields: dict[str, Any] = {"backend": (Literal[b.name], ...)}  # type: ignore[valid-type]
    for k in b.keys:
        kind: Any = k.type | None if k.optional else k.type
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
    n = math.sqrt(sum(c * c for c in v))
    if not math.isfinite(n) or abs(n - 1.0) > UNIT_TOL:
        raise ValueError(
            f"{what} must be a unit vector (norm 1 within {UNIT_TOL}), got norm {n:.6g}"
        )
    return (v[0] / n, v[1] / n, v[2] / n)


class FingerConfig(_Strict):
    """One fingertip: its thimble sphere, its device and its actuated force directions."""

    name: str = Field(min_length=1)
    radius_m: float = Field(default=0.008, gt=0, le=0.05, description="fingertip sphere radius, m")
    device: DeviceConfig
    actuated_directions: tuple[Vec3, ...] = param_field(
        "actuated_directions",
        min_length=0,
        description="unit force directions the device renders for this finger (0-3)",
    )

    @field_validator("actuated_directions")
    @classmethod
    def _units(cls, v: tuple[Vec3, ...]) -> tuple[Vec3, ...]:
        return tuple(_unit(d, f"direction {i}") for i, d in enumerate(v))


class FrictionConfig(_Strict):
    """Coulomb friction coefficients (dimensionless); 0 and 0 turn friction off."""

    static: float = param_field("friction", default=0.0, description="static coefficient")
    dynamic: float = param_field("friction", default=0.0, description="dynamic coefficient")
    torsion_m: float = Field(
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
    mesh: str | None = Field(
        default=None,
        description="STL/OBJ/PLY file (relative to the profile); its convex hull is used",
    )
    mesh_scale: float = Field(default=1.0, gt=0, description="factor from mesh units to m")
    position_m: Vec3 = (0.0, 0.0, 0.0)
    orientation_rpy_rad: Vec3 = Field(
        default=(0.0, 0.0, 0.0), description="roll, pitch, yaw (x, y, z fixed axes), rad"
    )
    fixed: bool = True
    mass_kg: float | None = param_field("mass_kg", default=None, description="needed when free, kg")
    stiffness_n_per_m: float = param_field("stiffness_n_per_m")
    damping_n_s_per_m: float = param_field("damping_n_s_per_m", default=0.0)
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

    stiffness_n_per_m: float = Field(default=2000.0, gt=0, le=1e5)
    damping_n_s_per_m: float = Field(default=5.0, ge=0, le=1e3)
    friction: FrictionConfig = FrictionConfig(static=0.6, dynamic=0.5)


class GroundConfig(SurfaceConfig):
    """A horizontal ground plane: nothing goes below height_m."""

    height_m: float = Field(ge=-1, le=1, description="height of the ground plane (world z), m")


class WallsConfig(SurfaceConfig):
    """Workspace walls: vertical planes bounding |x| and |y| around the origin."""

    half_width_m: tuple[float, float] = Field(
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
    gravity_m_s2: Vec3 | None = Field(
        default=None, description="gravity acceleration, m/s^2 (e.g. [0, 0, -9.81]); none: off"
    )
    ground: GroundConfig | None = None
    walls: WallsConfig | None = None
    substeps: int | Literal["auto"] = Field(
        default="auto",
        description="dynamics integration steps per tick (1-64), or auto: enough for the "
        "object's mass, the contact stiffness and damping",
    )

    @field_validator("substeps")
    @classmethod
    def _substeps(cls, v: int | str) -> int | str:
        if v != "auto" and not (1 <= int(v) <= 64):
            raise ValueError(f"substeps must be 1-64 or auto, got {v}")
        return v


BoxConfig = ObjectConfig  # the name used before meshes and free objects


class RealtimeConfig(_Strict):
    """Real-time settings for the servo thread (docs/daemon.md); each falls back with a
    message when not permitted, unless ``required``."""

    enabled: bool = Field(default=True, description="try SCHED_FIFO, mlockall and timer slack")
    priority: int = Field(default=80, ge=1, le=99, description="SCHED_FIFO priority")
    cpu: int | None = Field(default=None, ge=0, description="pin the servo thread to this CPU")
    lock_memory: bool = Field(default=True, description="mlockall: no page faults in the loop")
    timer_slack_ns: int = Field(default=1, ge=1, le=50_000_000, description="timer slack, ns")
    required: bool = Field(
        default=False, description="refuse to run when a setting cannot be applied"
    )


class LoopConfig(_Strict):
    rate_hz: float = Field(default=1000.0, ge=100.0, le=8000.0, description="servo rate, Hz")
    max_consecutive_overruns: int = Field(
        default=200,
        ge=0,
        description="this many periods in a row longer than 1.1x nominal latch a fault; 0: off",
    )
    realtime: RealtimeConfig = RealtimeConfig()
    gil_switch_interval_s: float = Field(
        default=5e-4,
        ge=1e-6,
        le=0.1,
        description="Python's GIL switch interval while the loop runs, s: the longest the "
        "loop waits for the GIL held by the control thread (Python's default is 0.005)",
    )


class RobustnessConfig(_Strict):
    """Singularity-robust allocation (docs/allocation.md)."""

    eps: float = Field(
        default=0.2, gt=0, lt=1, description="singular-value threshold below which gains are damped"
    )
    min_separation_m: float = Field(
        default=0.005,
        gt=0,
        lt=1,
        description="contacts closer than this blend internal subspaces, m",
    )
    contact_onset_n: float = Field(
        default=0.05, ge=0, lt=10, description="a contact weaker than this joins gradually, N"
    )


class AdaptiveConfig(_Strict):
    """The task-adaptive allocator's switch from internal to external forces."""

    ratio_low: float = Field(default=0.2, ge=0, lt=1, description="external ratio where it starts")
    ratio_high: float = Field(default=0.6, gt=0, le=1, description="external ratio where it ends")
    time_constant_s: float = Field(default=0.1, ge=0, le=10, description="lag of the switch, s")

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


class RecordingConfig(_Strict):
    directory: str | None = Field(
        default=None,
        min_length=1,
        description="where record_start over the control socket may write (relative to the "
        "profile's folder); none: the service's state directory",
    )


class SafetyConfig(_Strict):
    max_force_n: float = param_field(
        "force_limit_n",
        description="force limit per finger, N (the device's own limit also applies)",
    )
    ramp_s: float = Field(default=0.5, ge=0, le=10, description="force ramp after enabling, s")
    stop_ramp_s: float = Field(
        default=0.05, ge=0, le=2, description="forces ramp to zero over this time on a stop, s"
    )
    max_force_rate_n_per_s: float | None = Field(
        default=5000.0, gt=0, description="largest change of a finger's force, N/s; none: off"
    )
    workspace_center_m: Vec3 = (0.0, 0.0, 0.0)
    workspace_radius_m: float | None = Field(
        default=None, gt=0, le=2, description="fingers beyond this sphere latch a fault, m"
    )
    watchdog_s: float | None = Field(
        default=0.1, gt=0, le=10, description="longest wall time between ticks, s; none: off"
    )
    reconnect: bool = Field(
        default=False,
        description="on a device error keep running (forces off) and reopen the device when "
        "it returns; false: end the run",
    )


class Profile(_Strict):
    """A complete hapticd profile (see docs/profiles.md)."""

    version: Literal[1] = 1
    name: str = Field(min_length=1)
    description: str = ""
    loop: LoopConfig = LoopConfig()
    fingers: tuple[FingerConfig, ...] = Field(min_length=1, max_length=5)
    rendering: RenderingConfig = RenderingConfig()
    scene: SceneConfig
    safety: SafetyConfig
    recording: RecordingConfig = RecordingConfig()

    source: Path | None = Field(default=None, exclude=True, description="file it was loaded from")

    @model_validator(mode="after")
    def _consistent(self) -> Profile:
        names = [f.name for f in self.fingers]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"finger names must be unique, repeated: {sorted(dup)}")
        if self.rendering.actuation_frame == "grasp" and len(self.fingers) < 2:
            raise ValueError("actuation_frame 'grasp' needs at least two fingers")
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


def _format_loc(loc: tuple[int | str, ...], data: object) -> str:
    """Dotted key path; list indices become the item's name where it has one."""
    parts: list[str] = []
    node = data
    for item in loc:
        if isinstance(item, int):
            name = node[item].get("name") if isinstance(node, list) and item < len(node) else None
            parts.append(f"[{item}]" if name is None else f"[{item}:{name}]")
            node = node[item] if isinstance(node, list) and item < len(node) else None
        else:
            if item in BACKENDS and isinstance(node, dict) and node.get("backend") == item:
                continue  # pydantic's discriminator tag, not a key the user wrote
            parts.append(("." if parts else "") + str(item))
            node = node.get(item) if isinstance(node, dict) else None
    return "".join(parts) or "(top level)"


def _all_keys(root: type[BaseModel]) -> set[str]:
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
    return keys


def _models_in(annotation: object) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    out: list[type[BaseModel]] = []
    for arg in getattr(annotation, "__args__", ()) or ():
        out.extend(_models_in(arg))
    return out


def _explain(err: dict, root: type[BaseModel], docs: str) -> str:
    kind = err["type"]
    if kind == "extra_forbidden":
        key = str(err["loc"][-1])
        keys = sorted(_all_keys(root))
        # Keys carry their unit ("mass_kg"): a key written without it is the likeliest slip.
        close = [k for k in keys if k.startswith(key + "_")][:1]
        close = close or difflib.get_close_matches(key, keys, n=1, cutoff=0.75)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        return f"unknown key{hint} (the keys are listed in {docs})"
    if kind == "missing":
        return "required key is missing"
    msg = str(err["msg"])
    return msg.removeprefix("Value error, ")


def validate_document(
    model: type[M],
    data: object,
    source: str | Path,
    *,
    what: str = "profile",
    docs: str = "docs/profiles.md",
    error: type[ValueError] = ProfileError,
) -> M:
    """Validate an already-parsed YAML document into ``model``; on failure raise ``error``
    with one line per problem naming ``source``, the dotted key path and what was expected
    (``what`` names the kind of file, ``docs`` where its keys are listed)."""
    if not isinstance(data, dict):
        raise error(f"{source}: expected a mapping of keys at the top level")
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        errors = exc.errors()
        locs = [tuple(e["loc"]) for e in errors]
        # A list whose items failed also reports "too short"; that one only confuses.
        errors = [
            e
            for e in errors
            if not (
                e["type"] == "too_short"
                and any(
                    len(o) > len(e["loc"]) and o[: len(e["loc"])] == tuple(e["loc"]) for o in locs
                )
            )
        ]
        lines = [f"{source}: {len(errors)} error(s) in {what}"]
        for err in errors:
            where = _format_loc(tuple(err["loc"]), data)
            got = err.get("input")
            shown = ""
            if err["type"] != "missing" and not isinstance(got, dict | list):
                shown = f" (got {got!r})"
            lines.append(f"  {where}: {_explain(err, model, docs)}{shown}")
        raise error("\n".join(lines)) from None


def read_yaml(
    path: str | Path, *, what: str = "profile", error: type[ValueError] = ProfileError
) -> object:
    """The parsed YAML document at ``path``; ``error`` naming the file (and the line and
    column of a syntax error) if it cannot be read or parsed."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(f"{p}: cannot read {what}: {exc.strerror or exc}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise error(f"{p}: not valid YAML{where}: {problem}") from None


def parse_profile(data: object, source: str | Path = "<profile>") -> Profile:
    """Validate an already-parsed YAML document into a Profile."""
    prof = validate_document(Profile, data, source)
    return prof.model_copy(update={"source": Path(source)}) if source else prof


def load_profile(path: str | Path) -> Profile:
    """Read and validate the YAML profile at ``path``."""
    p = Path(path)
    return parse_profile(read_yaml(p), p.resolve())
