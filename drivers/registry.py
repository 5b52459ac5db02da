"""The backend registry: every device backend declared once.

Each ``Backend`` names its module and class (imported only when selected), the
pip extra that provides its optional dependency, the keys a profile may give
it (with their SI units, defaults and bounds) and how it is used: whether it
plays a finger's trajectory (replay, sim), whether the device emulator can run
under it (``--emulate``), how to find attached devices and what to check
before a run. The profile's device schema, ``--device`` choices, the session's
device construction, ``hapticd devices`` and the docs' backend table all
derive from ``BACKENDS``.

A lab's own package adds backends through the ``hapticd.backends`` entry-point group:
each entry point names a ``Backend`` (its module's registry entry), checked and merged
into ``BACKENDS`` when this module is imported (``load_plugins``; hapticd_drivers.plugins
says what is refused). docs/devices.md, "Writing a backend".
"""

from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass, field
from typing import Any

from hapticd_drivers import models
from hapticd_drivers.base import BackendUnavailableError, Device, DeviceError
from hapticd_drivers.plugins import Plugin, Problem
from hapticd_drivers.plugins import discover as discover_plugins

GROUP = "hapticd.backends"

REQUIRED: Any = object()  # a key without a default: the profile must give it


@dataclass(frozen=True)
class Key:
    """One profile key of a backend: ``type`` is float, int, bool, str, or that or None
    (``optional``); ``gt``/``ge``/``le`` bound a number; ``doc`` names the unit."""

    name: str
    type: type
    default: Any
    doc: str
    optional: bool = False
    gt: float | None = None
    ge: float | None = None
    le: float | None = None


@dataclass(frozen=True)
class Backend:
    """One device backend.

    ``plays_trajectory``: the device follows the finger's trajectory (it gets
    ``times``, ``positions`` and ``clock``, and ``buttons`` when the trajectory
    carries them). ``emulated``: a device emulator can run under it (``--emulate``:
    the delta emulator, or the Falcon's under falcon). ``discover`` and ``preflight`` are
    "module:function" paths: the first lists attached devices, the second checks
    what a run needs (a library, a driver) and raises DeviceError saying how to fix it.
    ``calibrate`` ("module:function") runs the device's own calibration (it moves the
    device) and returns what it did; backends without one need none from hapticd.
    ``takes_clock``: the device gets ``clock``, the loop's nominal time (s), without
    playing a trajectory (the virtual device moves at its speed per tick, not per
    wall-clock second, so a late tick is no jump).
    ``calibrate_by_hand``: what the user does while a calibration the device does not
    move for itself runs (empty: the device moves on its own).
    ``hardware``: it drives a real device (unless ``--emulate`` puts an emulator under
    it), so a run on it needs the loop's wall-clock watchdog.
    """

    name: str
    module: str
    cls: str
    doc: str
    keys: tuple[Key, ...]
    extra: str | None = None
    plays_trajectory: bool = False
    emulated: bool = False
    discover: str | None = None
    preflight: str | None = None
    calibrate: str | None = None
    takes_clock: bool = False
    calibrate_by_hand: str = ""
    hardware: bool = False
    status: str = ""
    defaults: dict[str, Any] = field(default_factory=dict, init=False, compare=False)

    def __post_init__(self) -> None:
        self.defaults.update({k.name: k.default for k in self.keys if k.default is not REQUIRED})

    def key(self, name: str) -> Key:
        return next(k for k in self.keys if k.name == name)


def _trajectory(required: bool, doc: str) -> Key:
    return Key("trajectory", str, REQUIRED if required else None, doc, optional=not required)


_FINGER = Key(
    "finger", str, None, "finger of the recording to play; defaults to this finger's name", True
)
_MAX_FORCE = Key("max_force_n", float, 12.0, "the device's rated force, N", gt=0.0, le=100.0)
_HOLD = Key(
    "hold_s", float, 0.0, "keep running this long after the trajectory ends, s", ge=0.0, le=86400.0
)
_INDEX = Key("index", int, 0, "pick the n-th matching device", ge=0, le=255)
_REPEAT = Key(
    "repeat",
    bool,
    False,
    "play the trajectory again from its start each time it ends, for as long as the run "
    "lasts (it must end where it starts; hold_s is then unused)",
)
_FALCON = models.by_name("Falcon")
assert _FALCON is not None

# The protocol devices (hid, usb) share their keys: the same device on two transports.
_REPORT_KEYS = (
    Key(
        "description",
        str,
        "delta-omega-class",
        "device description: a bundled name or a YAML path (docs/protocol.md)",
    ),
    Key("serial_number", str, None, "pick the device by its USB serial number", True),
    _INDEX,
    Key(
        "device_watchdog_s",
        float,
        0.05,
        "the device cuts its forces after this long without a command, s",
        gt=0.0,
        le=8.0,
    ),
    _trajectory(False, "path for the emulator (--emulate) to move the device along"),
    _FINGER,
)

BACKENDS: dict[str, Backend] = {
    b.name: b
    for b in (
        Backend(
            "replay",
            "hapticd_drivers.replay",
            "ReplayDevice",
            "plays a recorded trajectory, open loop (the tests' device)",
            (
                _trajectory(True, "recording path (relative to the profile) or 'builtin:NAME'"),
                _FINGER,
                _MAX_FORCE,
                _HOLD,
                _REPEAT,
            ),
            plays_trajectory=True,
            status="done",
        ),
        Backend(
            "sim",
            "hapticd_drivers.sim",
            "SimulatedFinger",
            "a simulated finger that follows a trajectory and feels the rendered force",
            (
                _trajectory(True, "path for the hand: recording path or 'builtin:NAME'"),
                _FINGER,
                _MAX_FORCE,
                _HOLD,
                _REPEAT,
                Key("mass_kg", float, 0.05, "fingertip and device mass, kg", gt=0.0, le=5.0),
                Key(
                    "hand_stiffness_n_per_m",
                    float,
                    300.0,
                    "grip of the hand on the path, N/m",
                    ge=0.0,
                    le=1e4,
                ),
                Key(
                    "hand_damping_n_s_per_m",
                    float,
                    3.0,
                    "damping of finger and device, N s/m",
                    ge=0.0,
                    le=100.0,
                ),
            ),
            plays_trajectory=True,
            status="done",
        ),
        Backend(
            "virtual",
            "hapticd_drivers.virtual",
            "VirtualDevice",
            "a handle with no hardware, moved from the view page (mouse and keys) over the "
            "control protocol",
            (
                Key("serial", str, "virtual", "its name in the status and recordings"),
                _MAX_FORCE,
                Key(
                    "max_speed_m_per_s",
                    float,
                    0.25,
                    "how fast the handle follows the mouse, m/s",
                    gt=0.0,
                    le=2.0,
                ),
                Key(
                    "workspace_radius_m",
                    float,
                    0.075,
                    "the handle stays this close to the device's origin, m",
                    gt=0.0,
                    le=1.0,
                ),
            ),
            takes_clock=True,
            status="done, tested in headless Chromium",
        ),
        Backend(
            "hid",
            "hapticd_drivers.hid_backend",
            "HidDelta",
            "an Omega-class delta device speaking hapticd's report protocol, through cython-hidapi",
            _REPORT_KEYS,
            extra="hid",
            emulated=True,
            discover="hapticd_drivers.udev:discover_hid",
            hardware=True,
            status="done, tested through the emulator",
        ),
        Backend(
            "usb",
            "hapticd_drivers.usb_backend",
            "UsbDelta",
            "the same protocol on a vendor-class interface, through pyusb and libusb",
            _REPORT_KEYS,
            extra="usb",
            emulated=True,
            discover="hapticd_drivers.udev:discover_usb",
            hardware=True,
            status="done, tested through an emulated pyusb backend",
        ),
        Backend(
            "dhd",
            "hapticd_drivers.dhd_backend",
            "DhdDevice",
            "a Force Dimension device (omega.3, ...) through its SDK, libdhd",
            (
                Key(
                    "model",
                    str,
                    None,
                    "the model the profile expects, a row of the model table (omega.3, "
                    "...): its workspace is known before the device opens (hapticd check), "
                    "and a device of another model is refused; none: read from the device",
                    True,
                ),
                Key(
                    "library",
                    str,
                    None,
                    "path to the SDK: libdrd (it holds libdhd's calls too, and only it can "
                    "check and run the calibration) or libdhd; else $HAPTICD_LIBDHD, else "
                    "the system's drd, then dhd library",
                    True,
                ),
                Key(
                    "serial_number",
                    int,
                    None,
                    "pick the device by its serial number",
                    True,
                    ge=0,
                    le=2**31 - 1,
                ),
                _INDEX,
                Key(
                    "device_watchdog_s",
                    float,
                    0.03,
                    "the SDK cuts forces after this long without a command, s "
                    "(its watchdog counts 125 us units up to 255: at most 0.031875 s)",
                    gt=0.0,
                    le=0.031875,
                ),
                Key(
                    "max_force_n",
                    float,
                    12.0,
                    "the device's rated force, and the SDK's own force limit (dhdSetMaxForce, "
                    "independent of the safety chain), at most its model's, N",
                    gt=0.0,
                    le=100.0,
                ),
                Key(
                    "effector_mass_kg",
                    float,
                    None,
                    "mass of the end effector with its thimble, for the SDK's gravity "
                    "compensation (always on), kg; none: the SDK's default for the model",
                    True,
                    ge=0.0,
                    le=1.0,
                ),
                Key(
                    "status_period_s",
                    float,
                    0.005,
                    "the longest time between two reads of the SDK's status while forces "
                    "are on (dhdGetStatus: forces the SDK turned off itself, by its force "
                    "button, velocity threshold or watchdog, latch a fault naming the cause), "
                    "s; 0: on every read",
                    ge=0.0,
                    le=0.03,
                ),
                _FINGER,
            ),
            discover="hapticd_drivers.dhd_backend:discover",
            hardware=True,
            preflight="hapticd_drivers.dhd_backend:preflight",
            calibrate="hapticd_drivers.dhd_backend:calibrate",
            status="done, tested through a fake SDK compiled by the tests, as the SDK's "
            "documentation describes it and with its older behaviours",
        ),
        Backend(
            "falcon",
            "hapticd_drivers.falcon_backend",
            "FalconDevice",
            "a Novint Falcon, no vendor SDK: its FTDI chip through pyftdi on pyusb",
            (
                Key(
                    "firmware",
                    str,
                    None,
                    "path of the Falcon firmware image to load after power-on (not shipped: "
                    "docs/devices.md says where to find it); none: the Falcon must run it already",
                    True,
                ),
                Key("serial_number", str, None, "pick the Falcon by its USB serial number", True),
                _INDEX,
                Key(
                    "max_force_n",
                    float,
                    _FALCON.max_force_n,
                    "the device's rated force, at most the Falcon's (the model table), N",
                    gt=0.0,
                    le=_FALCON.max_force_n,
                ),
                _trajectory(False, "path for the emulator (--emulate) to move the Falcon along"),
                _FINGER,
            ),
            emulated=True,
            discover="hapticd_drivers.falcon_backend:discover",
            hardware=True,
            preflight="hapticd_drivers.falcon_backend:preflight",
            calibrate="hapticd_drivers.falcon_backend:calibrate",
            calibrate_by_hand="move its grip all the way out, then push it straight in "
            "(the LED turns from red to blue)",
            status="protocol, kinematics and firmware load from libnifalcon; tested through "
            "an emulated FTDI chip under pyusb, not yet on a real Falcon",
        ),
    )
}


# The built-ins' names: a plugin cannot take one.
BUILTIN: frozenset[str] = frozenset(BACKENDS)
# Installed backends, by name, with the package each comes from; and the entry points
# refused (a broken import, the wrong shape, a name registered twice or a built-in's).
PLUGINS: dict[str, Plugin] = {}
PROBLEMS: list[Problem] = []


def check_plugin(name: str, obj: Any) -> str | None:
    """Why the entry point ``name``'s object is no backend (None: it is one): a ``Backend``
    of that name whose class is a concrete ``Device``."""
    if not isinstance(obj, Backend):
        return f"expected a hapticd_drivers.registry.Backend, got {type(obj).__name__}"
    if obj.name != name:
        return f"its Backend is named {obj.name!r}, the entry point {name!r}: they must agree"
    try:
        cls = getattr(importlib.import_module(obj.module), obj.cls)
    except (ImportError, AttributeError) as exc:
        return f"its device class {obj.module}:{obj.cls} cannot be imported ({exc})"
    if not (isinstance(cls, type) and issubclass(cls, Device)):
        return f"{obj.module}:{obj.cls} is not a subclass of hapticd_drivers.base.Device"
    if inspect.isabstract(cls):
        missing = ", ".join(sorted(cls.__abstractmethods__))
        return f"{obj.module}:{obj.cls} does not implement {missing}"
    for k in obj.keys:
        if not isinstance(k, Key):
            return f"its keys must be hapticd_drivers.registry.Key, got {type(k).__name__}"
        if k.name in ("backend", "mount"):
            return f"key {k.name!r} is every device's own; a backend cannot declare it"
    return None


def load_plugins() -> None:
    """Find the installed backends (entry points of ``hapticd.backends``) and merge those
    that pass ``check_plugin`` into ``BACKENDS``; the others into ``PROBLEMS``."""
    for name in list(PLUGINS):
        BACKENDS.pop(name, None)
    found, problems = discover_plugins(GROUP, BUILTIN, check_plugin)
    PLUGINS.clear()
    PLUGINS.update(found)
    PROBLEMS[:] = problems
    for name, plugin in found.items():
        BACKENDS[name] = plugin.obj


def package_of(name: str) -> str:
    """The package a backend comes from: hapticd for a built-in."""
    return PLUGINS[name].package if name in PLUGINS else "hapticd"


def problem(name: str) -> Problem | None:
    """The refused entry point named ``name``, if there is one."""
    return next((p for p in PROBLEMS if p.name == name), None)


def backend_names() -> list[str]:
    return sorted(BACKENDS)


def backend(name: str) -> Backend:
    """The registry entry of ``name``; BackendUnavailableError naming the known ones (or,
    for a refused plugin of that name, its package, entry point and why)."""
    try:
        return BACKENDS[name]
    except KeyError:
        refused = problem(name)
        if refused is not None:
            raise BackendUnavailableError(
                f"device backend {name!r} is refused: {refused.message()}"
            ) from None
        raise BackendUnavailableError(
            f"unknown device backend {name!r}; known backends: {', '.join(backend_names())}"
        ) from None


def _import(name: str, dotted: str) -> Any:
    b = backend(name)
    module_name, _, attr = dotted.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        hint = f" (install it with: pip install 'hapticd[{b.extra}]')" if b.extra else ""
        raise BackendUnavailableError(
            f"device backend {name!r} needs a package that is missing: {exc.name}{hint}"
        ) from exc
    return getattr(module, attr) if attr else module


def open_device(name: str, **kwargs: Any) -> Device:
    """Create (not yet open) a device of backend ``name`` with backend-specific ``kwargs``."""
    b = backend(name)
    cls = _import(name, f"{b.module}:{b.cls}")
    return cls(**kwargs)


def preflight(name: str, **kwargs: Any) -> None:
    """Check what a device of backend ``name`` needs before a run (DeviceError if missing)."""
    b = backend(name)
    if b.preflight is not None:
        _import(name, b.preflight)(**kwargs)


def calibrate(name: str, **kwargs: Any) -> dict[str, Any]:
    """Calibrate one device of backend ``name`` (it moves!); DeviceError if that fails or
    the backend has no calibration."""
    b = backend(name)
    if b.calibrate is None:
        raise DeviceError(f"backend {name!r} has no calibration to run")
    return _import(name, b.calibrate)(**kwargs)


def discover() -> list[dict[str, Any]]:
    """Per backend that can look for devices: what it found (``model``, ``found``) or why it
    cannot look (``problem``)."""
    report: list[dict[str, Any]] = []
    for b in BACKENDS.values():
        if b.discover is not None:
            report += _import(b.name, b.discover)()
    return report


def _builtins() -> list[Backend]:
    """The built-in backends, in the registry's order (the docs list these, whatever a
    machine has installed)."""
    return [b for b in BACKENDS.values() if b.name in BUILTIN]


def listing() -> list[dict[str, Any]]:
    """Every backend, built-in and installed, with the package it comes from; then the
    refused entry points with why (``problem``)."""
    rows: list[dict[str, Any]] = [
        {"name": b.name, "package": package_of(b.name), "doc": b.doc, "problem": None}
        for b in BACKENDS.values()
    ]
    rows += [
        {"name": p.name, "package": ", ".join(p.packages), "doc": "", "problem": p.message()}
        for p in PROBLEMS
    ]
    return rows


def markdown_table() -> str:
    """The backends as a Markdown table (docs/devices.md keeps a copy; a test compares)."""
    rows = ["| backend | what | pip extra | status |", "|---|---|---|---|"]
    for b in _builtins():
        extra = f"`hapticd[{b.extra}]`" if b.extra else "-"
        rows.append(f"| `{b.name}` | {b.doc} | {extra} | {b.status} |")
    return "\n".join(rows) + "\n"


def keys_table(name: str) -> str:
    """One backend's profile keys as a Markdown table."""
    rows = ["| key | default | meaning |", "|---|---|---|"]
    for k in backend(name).keys:
        default = "required" if k.default is REQUIRED else f"`{k.default!r}`"
        bounds = [
            f"{op} {v:g}" for op, v in ((">", k.gt), (">=", k.ge), ("<=", k.le)) if v is not None
        ]
        extra = f" ({', '.join(bounds)})" if bounds else ""
        rows.append(f"| `{k.name}` | {default} | {k.doc}{extra} |")
    return "\n".join(rows) + "\n"


def docs() -> str:
    """The generated part of docs/devices.md: the backend table and each backend's keys."""
    parts = [markdown_table(), "### Profile keys\n"]
    for name in (b.name for b in _builtins()):
        parts.append(f"`backend: {name}`\n\n{keys_table(name)}")
    return "\n".join(parts)


load_plugins()
