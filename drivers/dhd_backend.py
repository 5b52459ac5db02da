"""The ``dhd`` backend: Force Dimension devices through their SDK (libdhd, libdrd) by ctypes.

Loads the SDK when this backend is selected: the path in ``library`` or the
environment variable HAPTICD_LIBDHD, else the system's ``drd`` library, else
its ``dhd``, and refuses a library that is not the SDK or is older than
``MIN_SDK_VERSION`` (dhdGetSDKVersion). libdrd holds every DHD call too, and
only it can tell whether a device is initialised (calibrated) and initialise
it, so it is the library to use: with it, devices are opened through
drdOpenID (as CHAI3D opens them), so that the DRD state hapticd asks for is the
state of a device DRD opened. With a bare libdhd, devices open through
dhdOpenID and their calibration cannot be checked, so their forces stay off.

Opening a device first turns its forces off and writes a zero force, then
identifies it (dhdGetSystemType: a model of hapticd_drivers.models, else the
device is refused; the serial number where the device has one, else it is
known by its index), checks the controller's memory, sets the device watchdog
(125 us units), the SDK's own force limit (dhdSetMaxForce: a second limit,
independent of hapticd's safety chain), the end effector's mass and the SDK's
gravity compensation, and primes the SDK's velocity estimator with position
reads. Forces are enabled only on an initialised device, with its brakes
released first; the velocity threshold (dhdSetVelocityThreshold) is left at the
factory setting (docs/devices.md says why). A model with a wrist or a gripper
is commanded through dhdSetForceAndTorqueAndGripperForce, with zero torques and
gripper force (hapticd renders translational forces only); the others through
dhdSetForce. Closing writes a zero force, stops the device (dhdStop: forces off,
brakes on) and closes it.

While forces are on, the SDK's status (dhdGetStatus) is read at least every
``status_period_s``: forces the SDK turned off itself (its force button, velocity
threshold, watchdog, ...) end in a DeviceError naming the cause
(DHD_STATUS_FORCE_OFF_CAUSE), so the loop latches a fault instead of rendering to a
device that no longer pushes. The set-force call's positive return codes (a
saturated motor, a command the TimeGuard skipped) are counted (``counts``).

Errors are read by code (dhdErrorGetLast), with the SDK's message
(dhdErrorGetLastStr): a communication error or a device no longer found is a
lost device (DeviceLostError); a velocity estimator timeout keeps the last
velocity for at most ``MAX_VELOCITY_TIMEOUTS`` reads in a row, then fails;
anything else is a DeviceError naming the code.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import math
import os
import time
from typing import Any

import numpy as np
from hapticd_drivers import models
from hapticd_drivers.base import (
    Device,
    DeviceError,
    DeviceInfo,
    DeviceLostError,
    DeviceState,
    check_force,
)

WATCHDOG_UNIT_S = 125e-6
# forcedimension-core's runtime requires this version; hapticd's declarations are checked
# against the prototypes of 3.17.5 (tests/data/fd_sdk_prototypes.json).
MIN_SDK_VERSION = (3, 16, 0)
# Velocity reads in a row that may time out (the last velocity is kept) before the
# device fails: at 1 kHz, 50 ms without an estimate.
MAX_VELOCITY_TIMEOUTS = 50
PRIME_READS = 2  # the estimator needs two position updates within its window
# The longest time between two reads of the SDK's status while forces are on, s (the
# device key status_period_s): well within the device watchdog's period.
STATUS_PERIOD_S = 0.005
# The clock the status period is timed on, s (a test's own to step it).
_clock = time.monotonic

# The SDK's error codes (enum dhd_errors, in order from 0).
DHD_ERRORS = (
    "DHD_NO_ERROR",
    "DHD_ERROR",
    "DHD_ERROR_COM",
    "DHD_ERROR_DHC_BUSY",
    "DHD_ERROR_NO_DRIVER_FOUND",
    "DHD_ERROR_NO_DEVICE_FOUND",
    "DHD_ERROR_NOT_AVAILABLE",
    "DHD_ERROR_TIMEOUT",
    "DHD_ERROR_GEOMETRY",
    "DHD_ERROR_EXPERT_MODE_DISABLED",
    "DHD_ERROR_NOT_IMPLEMENTED",
    "DHD_ERROR_OUT_OF_MEMORY",
    "DHD_ERROR_DEVICE_NOT_READY",
    "DHD_ERROR_FILE_NOT_FOUND",
    "DHD_ERROR_CONFIGURATION",
    "DHD_ERROR_INVALID_INDEX",
    "DHD_ERROR_DEPRECATED",
    "DHD_ERROR_NULL_ARGUMENT",
    "DHD_ERROR_REDUNDANT_FAIL",
    "DHD_ERROR_NOT_ENABLED",
    "DHD_ERROR_DEVICE_IN_USE",
    "DHD_ERROR_INVALID",
    "DHD_ERROR_NO_REGULATION",
)
DHD_ERROR_COM = 2
DHD_ERROR_NO_DEVICE_FOUND = 5
DHD_ERROR_NOT_AVAILABLE = 6
DHD_ERROR_TIMEOUT = 7
DHD_ERROR_NOT_IMPLEMENTED = 10
DHD_ERROR_CONFIGURATION = 14
# The set-force calls' positive return codes: no error, counted (``DhdDevice.counts``).
DHD_TIMEGUARD = 1  # the TimeGuard skipped a command that came too soon after the last
DHD_MOTOR_SATURATED = 2  # a motor could not deliver it: the force was scaled down
# The status array (dhdGetStatus): DHD_MAX_STATUS entries, 17 in SDK 3.17.5; room for more.
STATUS_SIZE = 32
DHD_STATUS_POWER = 0
DHD_STATUS_CONNECTED = 1
DHD_STATUS_FORCE = 5
DHD_STATUS_BRAKE = 6
DHD_STATUS_ERROR = 9
DHD_STATUS_FORCE_OFF_CAUSE = 14
# Why the SDK turned forces off (DHD_FORCE_OFF_*, the value of DHD_STATUS_FORCE_OFF_CAUSE).
DHD_FORCE_OFF_USBDISCN = 5
FORCE_OFF_CAUSES = {
    0: ("DHD_FORCE_OFF_NONE", "the SDK gave no cause"),
    1: ("DHD_FORCE_OFF_BUTTON", "the device's force button was pressed"),
    2: (
        "DHD_FORCE_OFF_VELOCITY",
        "the handle moved faster than the device's velocity threshold; it brakes",
    ),
    3: (
        "DHD_FORCE_OFF_WATCHDOG",
        "no force command came within the device watchdog's period (device_watchdog_s): "
        "the loop stalled; it brakes",
    ),
    4: ("DHD_FORCE_OFF_SOFTWARE", "a program turned them off"),
    5: ("DHD_FORCE_OFF_USBDISCN", "the USB connection was lost"),
    6: ("DHD_FORCE_OFF_DEADMAN", "the deadman switch was released"),
}
# What the SDK documents as a device that is gone: a communication error between the
# host and the device, or no device found.
LOST = frozenset({DHD_ERROR_COM, DHD_ERROR_NO_DEVICE_FOUND})

_D = ctypes.c_double
_PD = ctypes.POINTER(ctypes.c_double)
_PI = ctypes.POINTER(ctypes.c_int)
_C = ctypes.c_byte  # the SDK's 'char ID'
_ON, _OFF = 1, 0

# name: (restype, argtypes); tests/test_dhd_sdk.py compares them with the recorded prototypes.
_API: dict[str, tuple[Any, list[Any]]] = {
    "dhdGetDeviceCount": (ctypes.c_int, []),
    "dhdErrorGetLast": (ctypes.c_int, []),
    "dhdErrorGetLastStr": (ctypes.c_char_p, []),
    "dhdGetSDKVersion": (None, [_PI, _PI, _PI, _PI]),
    "dhdOpenID": (ctypes.c_int, [_C]),
    "dhdClose": (ctypes.c_int, [_C]),
    "dhdGetSerialNumber": (ctypes.c_int, [ctypes.POINTER(ctypes.c_ushort), _C]),
    "dhdGetSystemName": (ctypes.c_char_p, [_C]),
    "dhdGetSystemType": (ctypes.c_int, [_C]),
    "dhdCheckControllerMemory": (ctypes.c_int, [_C]),
    "dhdEnableExpertMode": (ctypes.c_int, []),
    "dhdDisableExpertMode": (ctypes.c_int, []),
    "dhdEnableForce": (ctypes.c_int, [ctypes.c_ubyte, _C]),
    "dhdSetBrakes": (ctypes.c_int, [ctypes.c_int, _C]),
    "dhdSetWatchdog": (ctypes.c_int, [ctypes.c_ubyte, _C]),
    "dhdSetMaxForce": (ctypes.c_int, [_D, _C]),
    "dhdGetMaxForce": (_D, [_C]),
    "dhdSetEffectorMass": (ctypes.c_int, [_D, _C]),
    "dhdSetGravityCompensation": (ctypes.c_int, [ctypes.c_int, _C]),
    "dhdGetButtonMask": (ctypes.c_uint, [_C]),
    "dhdGetPosition": (ctypes.c_int, [_PD, _PD, _PD, _C]),
    "dhdGetLinearVelocity": (ctypes.c_int, [_PD, _PD, _PD, _C]),
    "dhdSetForce": (ctypes.c_int, [_D, _D, _D, _C]),
    "dhdSetForceAndTorqueAndGripperForce": (ctypes.c_int, [_D, _D, _D, _D, _D, _D, _D, _C]),
    "dhdGetStatus": (ctypes.c_int, [_PI, _C]),
    "dhdStop": (ctypes.c_int, [_C]),
    # libdrd only: opening, the initialisation (calibration) state, automatic initialisation.
    "drdOpenID": (ctypes.c_int, [_C]),
    "drdClose": (ctypes.c_int, [_C]),
    "drdIsInitialized": (ctypes.c_bool, [_C]),
    "drdAutoInit": (ctypes.c_int, [_C]),
    "drdStop": (ctypes.c_int, [ctypes.c_bool, _C]),
}
# Calls hapticd works without (and says what it then cannot do): the model's name, the
# memory check and the brakes on devices and SDKs without them, the calibration without
# libdrd.
_OPTIONAL = {
    "dhdGetSystemName",
    "dhdCheckControllerMemory",
    "dhdGetMaxForce",
    "dhdSetBrakes",
    "drdOpenID",
    "drdClose",
    "drdIsInitialized",
    "drdAutoInit",
    "drdStop",
}
_DRD = ("drdOpenID", "drdClose", "drdIsInitialized", "drdAutoInit", "drdStop")

# Devices this process holds open, per loaded library: (dlopen handle, device ID). The SDK
# answers dhdOpenID/drdOpenID on an open device with its ID, so only this tells discover()
# and the search by serial number not to close a device a loop is using.
_HELD: set[tuple[int, int]] = set()


def sdk_version(lib: ctypes.CDLL) -> tuple[int, int, int, int]:
    """(major, minor, release, revision) of a loaded SDK (dhdGetSDKVersion)."""
    v = [ctypes.c_int() for _ in range(4)]
    lib.dhdGetSDKVersion(*(ctypes.byref(x) for x in v))
    return (v[0].value, v[1].value, v[2].value, v[3].value)


def _version_text(v: tuple[int, ...]) -> str:
    return ".".join(str(x) for x in v[:3]) + (f"-{v[3]}" if len(v) > 3 else "")


def load_libdhd(library: str | None = None) -> ctypes.CDLL:
    """The SDK library with its argument and return types declared; DeviceError if it is
    missing, is not Force Dimension's SDK, or is older than MIN_SDK_VERSION."""
    path = (
        library
        or os.environ.get("HAPTICD_LIBDHD")
        or ctypes.util.find_library("drd")
        or ctypes.util.find_library("dhd")
    )
    if not path:
        raise DeviceError(
            "the dhd backend needs Force Dimension's SDK (libdrd or libdhd), which was not "
            "found: install it, or give its path in the profile's device key 'library' "
            "or in the environment variable HAPTICD_LIBDHD"
        )
    try:
        lib = ctypes.CDLL(path)
    except OSError as exc:
        raise DeviceError(f"cannot load libdhd from {path}: {exc}") from exc
    if not hasattr(lib, "dhdGetDeviceCount"):
        raise DeviceError(
            f"{path} is not Force Dimension's SDK (it has no dhdGetDeviceCount): point the "
            "device key 'library' or HAPTICD_LIBDHD at libdrd (or libdhd)"
        )
    minimum = _version_text(MIN_SDK_VERSION)
    for name, (restype, argtypes) in _API.items():
        fn = getattr(lib, name, None)
        if fn is None:
            if name in _OPTIONAL:
                continue
            raise DeviceError(
                f"{path} lacks {name}: a Force Dimension SDK older than {minimum}, the "
                "minimum hapticd needs, or not the SDK"
            )
        fn.restype, fn.argtypes = restype, argtypes
    version = sdk_version(lib)
    if version[:3] < MIN_SDK_VERSION:
        raise DeviceError(
            f"{path} is Force Dimension SDK {_version_text(version)}, older than {minimum}, "
            f"the minimum hapticd needs: install SDK {minimum} or newer"
        )
    return lib


def has_drd(lib: ctypes.CDLL) -> bool:
    """True when ``lib`` holds the DRD calls hapticd uses (libdrd)."""
    return all(hasattr(lib, name) for name in _DRD)


def error_name(code: int) -> str:
    """The SDK's name for an error code (DHD_ERROR_TIMEOUT, ...)."""
    return DHD_ERRORS[code] if 0 <= code < len(DHD_ERRORS) else f"error code {code}"


def last_error(lib: ctypes.CDLL) -> tuple[int, str]:
    """The SDK's last error in this thread: (code, its name and message)."""
    code = int(lib.dhdErrorGetLast())
    text = (lib.dhdErrorGetLastStr() or b"").decode(errors="replace")
    return code, f"{error_name(code)}: {text}" if text else error_name(code)


def sdk_error(lib: ctypes.CDLL, who: str, what: str) -> DeviceError:
    """The error of the SDK call that just failed, by its code: DeviceLostError when the SDK
    says the device is gone, else DeviceError."""
    code, text = last_error(lib)
    if code in LOST:
        return DeviceLostError(f"{who}: lost ({what}): {text}")
    return DeviceError(f"{who}: {what}: {text}")


def force_off_cause(code: int) -> str:
    """The SDK's name for a force-off cause (DHD_STATUS_FORCE_OFF_CAUSE) and what it means."""
    name, meaning = FORCE_OFF_CAUSES.get(
        code, (f"force-off cause {code}", "a cause this version of hapticd does not know")
    )
    return f"{name}: {meaning}"


def _unsupported(lib: ctypes.CDLL) -> bool:
    """Whether the call that just failed is one the device does not have (not an error)."""
    return int(lib.dhdErrorGetLast()) in (DHD_ERROR_NOT_AVAILABLE, DHD_ERROR_NOT_IMPLEMENTED)


def _held(lib: ctypes.CDLL, dev_id: int) -> bool:
    return (lib._handle, dev_id) in _HELD


def _read_serial(lib: ctypes.CDLL, dev_id: int) -> int | None:
    """The serial number of an open device; None for a device without a readable one
    (dhdGetSerialNumber is available on recent models only)."""
    sn = ctypes.c_ushort()
    if lib.dhdGetSerialNumber(ctypes.byref(sn), dev_id) < 0:
        return None
    return int(sn.value)


def _identify(lib: ctypes.CDLL, dev_id: int) -> tuple[models.DeviceModel | None, str, int | None]:
    """An open device's row of the model table (None: its type is not in it), its model
    as hapticd names it (the row's name, else its type and the SDK's name) and its serial
    number (None when it has no readable one)."""
    t = int(lib.dhdGetSystemType(dev_id))
    row = models.by_dhd_type(t)
    if row is not None:
        label = row.name
    else:
        name = lib.dhdGetSystemName(dev_id) if hasattr(lib, "dhdGetSystemName") else None
        label = f"type {t} {(name or b'').decode(errors='replace')}".strip()
    return row, label, _read_serial(lib, dev_id)


def _opener(lib: ctypes.CDLL) -> tuple[Any, Any]:
    """(open, close) calls: DRD's when the library has them (so DRD knows the device)."""
    if has_drd(lib):
        return lib.drdOpenID, lib.drdClose
    return lib.dhdOpenID, lib.dhdClose


def open_index(lib: ctypes.CDLL, index: int, who: str) -> int:
    """Open the device at ``index``; its ID, or DeviceError naming the SDK's error."""
    count = lib.dhdGetDeviceCount()
    if not 0 <= index < count:
        raise DeviceError(f"{who}: no device at index {index}; {count} present")
    open_, _ = _opener(lib)
    dev_id = int(open_(index))
    if dev_id < 0:
        raise sdk_error(lib, who, f"cannot open ({count} device(s) present)")
    return dev_id


def find_serial(lib: ctypes.CDLL, serial_number: int, who: str) -> tuple[int, int]:
    """Open the device whose serial number is ``serial_number``: (its ID, its index).
    Every other device it opened to ask is closed again, except those this process holds;
    DeviceError naming what it saw when none matches."""
    open_, close = _opener(lib)
    count = lib.dhdGetDeviceCount()
    unreadable: list[str] = []
    unopened: list[str] = []
    for i in range(count):
        dev_id = int(open_(i))
        if dev_id < 0:
            unopened.append(f"index {i} ({last_error(lib)[1]})")
            continue
        held = _held(lib, dev_id)
        sn = _read_serial(lib, dev_id)
        if sn == serial_number and not held:
            return dev_id, i
        if sn is None:
            unreadable.append(str(i))
        if not held:
            close(dev_id)
        elif sn == serial_number:
            raise DeviceError(f"{who}: already open in this process (index {i})")
    notes = ""
    if unreadable:
        notes += "; without a readable serial number, to be picked by 'index': index "
        notes += ", ".join(unreadable)
    if unopened:
        notes += "; could not be opened to ask: " + ", ".join(unopened)
    raise DeviceError(f"{who}: no device with serial number {serial_number} among {count}{notes}")


def _describe(model: str, index: int, serial: int | None) -> str:
    return f"dhd {model} index {index}" + (
        f", serial {serial}" if serial is not None else " (no serial number)"
    )


def preflight(library: str | None = None, **_: Any) -> None:
    """Check that the SDK library loads and is recent enough (DeviceError saying how to
    point at it if not)."""
    load_libdhd(library)


def discover() -> list[dict[str, Any]]:
    """The SDK's devices, per model: serial number (or that there is none), index and
    initialisation state; or why it cannot look. A device another program holds open is
    listed as in use; one this process holds is listed, and left open."""
    try:
        lib = load_libdhd()
    except DeviceError as exc:
        return [{"backend": "dhd", "problem": str(exc)}]
    drd = has_drd(lib)
    open_, close = _opener(lib)
    by_model: dict[str, list[str]] = {}
    devices: list[dict[str, Any]] = []
    for i in range(lib.dhdGetDeviceCount()):
        dev_id = int(open_(i))
        if dev_id < 0:
            _, text = last_error(lib)
            entry = {"index": i, "problem": f"cannot open: {text} (in use?)"}
            devices.append(entry)
            by_model.setdefault("Force Dimension", []).append(f"index {i}: {entry['problem']}")
            continue
        held = _held(lib, dev_id)
        try:
            row, model, serial = _identify(lib, dev_id)
            calibrated = bool(lib.drdIsInitialized(dev_id)) if drd else None
        finally:
            if not held:
                close(dev_id)
        state = {True: "calibrated", False: "NOT calibrated", None: "calibration unknown"}
        notes = [state[calibrated]]
        if row is None:
            notes.append("NOT in hapticd's model table: refused")
        if held:
            notes.append("open in this process")
        devices.append(
            {
                "index": i,
                "model": model,
                "serial": None if serial is None else str(serial),
                "calibrated": calibrated,
                "known_model": row is not None,
            }
        )
        where = f"{serial} (index {i}, " if serial is not None else f"index {i} (no serial, "
        by_model.setdefault(model, []).append(where + ", ".join(notes) + ")")
    version = _version_text(sdk_version(lib))
    if not by_model:
        return [{"backend": "dhd", "model": "Force Dimension", "found": [], "devices": []}]
    return [
        {
            "backend": "dhd",
            "model": model,
            "sdk": version,
            "found": found,
            "devices": [d for d in devices if d.get("model", "Force Dimension") == model],
        }
        for model, found in by_model.items()
    ]


def calibrate(
    library: str | None = None, serial_number: int | None = None, index: int = 0, **_: Any
) -> dict[str, Any]:
    """Run the SDK's automatic initialisation (drdAutoInit) on one device: it moves on its
    own to find its end stops, so its workspace must be empty. Forces are off afterwards.
    Returns model, serial (or index) and whether it was initialised before; DeviceError
    on failure."""
    lib = load_libdhd(library)
    if not has_drd(lib):
        raise DeviceError(
            f"{lib._name} has no drdAutoInit: calibrating needs libdrd (it holds "
            "libdhd's calls too); give its path in the device key 'library'"
        )
    if serial_number is None:
        dev_id = open_index(lib, index, f"dhd index {index}")
    else:
        dev_id, index = find_serial(lib, serial_number, f"dhd serial {serial_number}")
    try:
        _, model, serial = _identify(lib, dev_id)
        who = _describe(model, index, serial)
        was = bool(lib.drdIsInitialized(dev_id))
        if lib.drdAutoInit(dev_id) < 0:
            raise DeviceError(f"{who}: automatic initialisation failed: {last_error(lib)[1]}")
        # Stop the SDK's regulation with forces off (it leaves the brakes on): hapticd
        # releases them and enables forces when it runs.
        if lib.drdStop(False, dev_id) < 0:
            raise DeviceError(f"{who}: cannot stop the regulation: {last_error(lib)[1]}")
        if not lib.drdIsInitialized(dev_id):
            raise DeviceError(f"{who}: still not initialised after drdAutoInit")
    finally:
        with contextlib.suppress(Exception):
            lib.dhdEnableForce(_OFF, dev_id)
        lib.drdClose(dev_id)
    return {
        "model": model,
        "serial": str(serial) if serial is not None else f"index {index}",
        "was_calibrated": was,
    }


class DhdDevice(Device):
    """A Force Dimension device (e.g. omega.3) through its SDK.

    ``max_force_n`` (N) is the device's rated force in hapticd and the SDK's own force
    limit, at most its model's; ``effector_mass_kg`` (kg) the end effector's mass for the
    SDK's gravity compensation (None: the SDK's default for the model); ``model`` the
    model the profile expects (a row of hapticd_drivers.models: its workspace is known
    before the device is opened, and a device of another model is refused);
    ``status_period_s`` (s) the longest time between two reads of the SDK's status while
    forces are on (0: on every read).
    """

    reports_lost = True  # DHD_ERROR_COM and DHD_ERROR_NO_DEVICE_FOUND only

    def __init__(
        self,
        serial_number: int | None = None,
        index: int = 0,
        library: str | None = None,
        device_watchdog_s: float = 0.03,
        max_force_n: float = 12.0,
        effector_mass_kg: float | None = None,
        model: str | None = None,
        serial: str | None = None,
        status_period_s: float = STATUS_PERIOD_S,
        **_: Any,
    ) -> None:
        self.serial_number = serial_number
        self.index = index
        self.library = library
        self.watchdog = max(1, min(255, round(device_watchdog_s / WATCHDOG_UNIT_S)))
        if not (math.isfinite(max_force_n) and max_force_n > 0):
            raise DeviceError(f"dhd: max_force_n must be positive, got {max_force_n}")
        if effector_mass_kg is not None and not (
            math.isfinite(effector_mass_kg) and effector_mass_kg >= 0
        ):
            raise DeviceError(f"dhd: effector_mass_kg must be >= 0 kg, got {effector_mass_kg}")
        self.effector_mass_kg = effector_mass_kg
        if not (math.isfinite(status_period_s) and status_period_s >= 0):
            raise DeviceError(f"dhd: status_period_s must be >= 0 s, got {status_period_s}")
        self.status_period_s = float(status_period_s)
        self.model = None
        if model is not None:
            self.model = models.by_name(model)
            if self.model is None:
                raise DeviceError(
                    f"dhd: unknown model {model!r}; hapticd knows {', '.join(models.model_names())}"
                )
            if max_force_n > self.model.max_force_n:
                raise DeviceError(
                    f"dhd: max_force_n {max_force_n:g} N is above the {self.model.name}'s force "
                    f"limit, {self.model.max_force_n:g} N: set it to at most that"
                )
        name = serial or (str(serial_number) if serial_number is not None else f"dhd#{index}")
        self._who = (
            f"dhd serial {serial_number}" if serial_number is not None else f"dhd index {index}"
        )
        self.info = self._info(self.model, name, float(max_force_n))
        self._lib: ctypes.CDLL | None = None
        self._id = -1
        self._drd = False
        self._enabled = False
        self._xyz = [_D(), _D(), _D()]
        self._refs = [ctypes.byref(v) for v in self._xyz]
        self._velocity = [0.0, 0.0, 0.0]
        self._velocity_timeouts = 0
        # Preallocated for the status read (no allocation per tick); when it is next due (s,
        # on _clock).
        self._status = (ctypes.c_int * STATUS_SIZE)()
        self._status_due = 0.0
        # The model takes its force with wrist torques and gripper force in one call.
        self._combined = False
        self._saturated = 0
        self._timeguard = 0

    @staticmethod
    def _info(row: models.DeviceModel | None, name: str, max_force_n: float) -> DeviceInfo:
        if row is None:  # not known until the device is opened and identified
            return DeviceInfo("dhd", name, max_force_n, math.nan)
        return DeviceInfo.of_model(row, name, max_force_n)

    def _check(self, rc: int, what: str) -> int:
        if rc < 0:
            assert self._lib is not None
            raise sdk_error(self._lib, self._who, what)
        return rc

    def open(self) -> None:
        lib = self._lib = load_libdhd(self.library)
        if self.serial_number is not None:
            dev_id, self.index = find_serial(lib, int(self.serial_number), self._who)
        else:
            dev_id = open_index(lib, self.index, self._who)
        self._id, self._drd = dev_id, has_drd(lib)
        _HELD.add((lib._handle, dev_id))
        try:
            self._set_up(lib, dev_id)
        except BaseException:
            self._release()
            raise

    def _release(self) -> None:
        """Forces off and the device closed (never raises)."""
        lib, dev_id = self._lib, self._id
        self._id = -1
        self._enabled = False
        if lib is None or dev_id < 0:
            return
        _HELD.discard((lib._handle, dev_id))
        with contextlib.suppress(Exception):
            self._send(lib, dev_id, 0.0, 0.0, 0.0)
        # dhdStop: forces off and the brakes on, the state to leave a device in (as
        # forcedimension_ros2 closes); forces off at least where it fails.
        stopped = False
        with contextlib.suppress(Exception):
            stopped = lib.dhdStop(dev_id) >= 0
        if not stopped:
            with contextlib.suppress(Exception):
                lib.dhdEnableForce(_OFF, dev_id)
        with contextlib.suppress(Exception):
            (lib.drdClose if self._drd else lib.dhdClose)(dev_id)

    def _set_up(self, lib: ctypes.CDLL, dev_id: int) -> None:
        """Everything between opening and enabling forces, in the order it is safe."""
        # Whatever the last program left: forces off, and a zero force is the first command.
        self._enabled = False
        self._check(lib.dhdEnableForce(_OFF, dev_id), "cannot disable forces")
        row, model, serial = _identify(lib, dev_id)
        self._who = _describe(model, self.index, serial)
        self._combined = row is not None and row.wrist_or_gripper
        self._check(self._send(lib, dev_id, 0.0, 0.0, 0.0), "cannot write a zero force")
        if row is None:
            raise DeviceError(
                f"{self._who}: its device type (dhdGetSystemType) is not in hapticd's model "
                f"table ({', '.join(models.model_names())}), so its workspace and force limit "
                "are unknown and hapticd refuses it; add its row to hapticd_drivers.models"
            )
        if self.model is not None and self.model is not row:
            raise DeviceError(
                f"{self._who}: the profile's device key 'model' says {self.model.name}, but "
                f"the device is a {row.name}"
            )
        limit = self.info.max_force_n
        if limit > row.max_force_n:
            raise DeviceError(
                f"{self._who}: max_force_n {limit:g} N is above the {row.name}'s force limit, "
                f"{row.max_force_n:g} N: set the device key max_force_n to at most that"
            )
        name = str(serial) if serial is not None else f"index {self.index}"
        self.info = self._info(row, name, limit)
        self._check_memory(lib, dev_id)
        # The watchdog is an expert setting: expert mode only for as long as it takes.
        self._check(lib.dhdEnableExpertMode(), "cannot enter expert mode")
        try:
            self._check(lib.dhdSetWatchdog(self.watchdog, dev_id), "cannot set the watchdog")
        finally:
            lib.dhdDisableExpertMode()
        self._check(lib.dhdSetMaxForce(limit, dev_id), "cannot set the SDK's force limit")
        if hasattr(lib, "dhdGetMaxForce"):
            got = lib.dhdGetMaxForce(dev_id)
            if not abs(got - limit) <= 1e-9 * limit:
                raise DeviceError(
                    f"{self._who}: the SDK's force limit reads {got:g} N, not {limit:g} N"
                )
        if self.effector_mass_kg is not None:
            self._check(
                lib.dhdSetEffectorMass(self.effector_mass_kg, dev_id),
                "cannot set the effector mass",
            )
        self._check(lib.dhdSetGravityCompensation(_ON, dev_id), "cannot turn on gravity comp.")
        self._prime()

    def _check_memory(self, lib: ctypes.CDLL, dev_id: int) -> None:
        """The controller's firmware and configuration check, on the devices that have it:
        0 passes, DHD_ERROR_CONFIGURATION fails it."""
        if not hasattr(lib, "dhdCheckControllerMemory"):
            return
        rc = int(lib.dhdCheckControllerMemory(dev_id))
        if rc == 0:
            return
        if rc < 0:
            if _unsupported(lib):
                return  # a device type without the check
            raise sdk_error(lib, self._who, "the controller's memory check failed")
        raise DeviceError(
            f"{self._who}: the controller's memory check failed ({error_name(rc)}: the "
            "firmware or internal configuration health check failed); do not use the "
            "device, contact Force Dimension"
        )

    def _prime(self) -> None:
        """Position reads for the SDK's velocity estimator, which needs two updates within
        its window before it answers; the last velocity starts at rest."""
        assert self._lib is not None
        for _ in range(PRIME_READS):
            self._check(self._lib.dhdGetPosition(*self._refs, self._id), "cannot read the position")
        self._velocity = [0.0, 0.0, 0.0]
        self._velocity_timeouts = 0

    def calibrated(self) -> bool | None:
        """Whether the SDK reports the device initialised (calibrated); None when it cannot
        tell (a bare libdhd: the device was not opened through DRD)."""
        if self._lib is None or self._id < 0:
            raise DeviceError(f"{self._who}: not open")
        if not self._drd:
            return None
        return bool(self._lib.drdIsInitialized(self._id))

    def close(self) -> None:
        self._release()

    def read_state(self, state: DeviceState) -> None:
        if self._id < 0:
            raise DeviceError(f"{self._who}: read from a closed device")
        lib, refs, xyz = self._lib, self._refs, self._xyz
        assert lib is not None
        if lib.dhdGetPosition(*refs, self._id) < 0:
            raise sdk_error(lib, self._who, "cannot read the position")
        state.position[:] = (xyz[0].value, xyz[1].value, xyz[2].value)
        v = self._velocity
        if lib.dhdGetLinearVelocity(*refs, self._id) < 0:
            if lib.dhdErrorGetLast() != DHD_ERROR_TIMEOUT:
                raise sdk_error(lib, self._who, "cannot read the velocity")
            # The estimator saw too few position updates in its window (a late tick): the
            # last velocity stands, for a bounded number of reads.
            self._velocity_timeouts += 1
            if self._velocity_timeouts > MAX_VELOCITY_TIMEOUTS:
                raise DeviceError(
                    f"{self._who}: the SDK's velocity estimator timed out on "
                    f"{self._velocity_timeouts} reads in a row (DHD_ERROR_TIMEOUT: fewer than "
                    "two position updates within its window); the device answers, but its "
                    "velocity is unknown, so its forces stop"
                )
        else:
            self._velocity_timeouts = 0
            v[0], v[1], v[2] = xyz[0].value, xyz[1].value, xyz[2].value
        state.velocity[:] = v
        state.buttons = int(lib.dhdGetButtonMask(self._id))
        if self._enabled:
            period = self.status_period_s
            if period > 0.0:
                now = _clock()
                if now < self._status_due:
                    return
                self._status_due = now + period
            self._read_status(lib)

    def _read_status(self, lib: ctypes.CDLL) -> None:
        """The SDK's status: DeviceError naming the cause when the SDK turned the forces off
        itself (DeviceLostError when for a lost USB connection)."""
        st = self._status
        if lib.dhdGetStatus(st, self._id) < 0:
            raise sdk_error(lib, self._who, "cannot read the status")
        if st[DHD_STATUS_FORCE]:
            return
        self._enabled = False  # what it is sent from now on: zero
        code = int(st[DHD_STATUS_FORCE_OFF_CAUSE])
        notes = [
            note
            for on, note in (
                (not st[DHD_STATUS_POWER], "no power"),
                (not st[DHD_STATUS_CONNECTED], "not connected"),
                (st[DHD_STATUS_BRAKE], "brakes on"),
                (st[DHD_STATUS_ERROR], "the device reports an error"),
            )
            if on
        ]
        lost = code == DHD_FORCE_OFF_USBDISCN or not st[DHD_STATUS_CONNECTED]
        raise (DeviceLostError if lost else DeviceError)(
            f"{self._who}: {'lost: ' if lost else ''}the SDK turned its forces off "
            f"({force_off_cause(code)}{'; ' + ', '.join(notes) if notes else ''}); hapticd "
            "zeroes and disables every device, and the fault stays latched"
        )

    def _send(self, lib: ctypes.CDLL, dev_id: int, x: float, y: float, z: float) -> int:
        """One force command (N, the device's frame) through the model's call: the SDK's
        return code. A model with a wrist or a gripper gets zero torques and gripper force:
        hapticd renders translations only."""
        if self._combined:
            return lib.dhdSetForceAndTorqueAndGripperForce(x, y, z, 0.0, 0.0, 0.0, 0.0, dev_id)
        return lib.dhdSetForce(x, y, z, dev_id)

    def counts(self) -> dict[str, int]:
        """The set-force calls that returned DHD_MOTOR_SATURATED (a motor could not deliver
        the force: the SDK scaled it down) and DHD_TIMEGUARD (the SDK skipped a command
        that came too soon after the last), since the device was made."""
        return {"motor_saturated": self._saturated, "timeguard": self._timeguard}

    def write_force(self, force: np.ndarray) -> None:
        if self._id < 0:
            raise DeviceError(f"{self._who}: write to a closed device")
        x, y, z = check_force(force, self.info.max_force_n, self._who)  # finite, in the limit
        if not self._enabled:
            x = y = z = 0.0
        lib = self._lib
        assert lib is not None
        rc = self._send(lib, self._id, x, y, z)
        if rc != 0:
            if rc < 0:
                raise sdk_error(lib, self._who, "cannot set the force")
            if rc == DHD_MOTOR_SATURATED:
                self._saturated += 1
            elif rc == DHD_TIMEGUARD:
                self._timeguard += 1

    def enable_forces(self, enabled: bool) -> None:
        if not enabled:
            self._enabled = False
            if self._lib is not None and self._id >= 0:
                self._check(self._lib.dhdEnableForce(_OFF, self._id), "cannot disable forces")
            return
        if self._lib is None or self._id < 0:
            raise DeviceError(f"{self._who}: cannot enable forces on a closed device")
        lib = self._lib
        state = self.calibrated()
        if state is None:
            raise DeviceError(
                f"{self._who}: forces stay off: {lib._name} cannot tell whether the device is "
                "calibrated (libdhd without libdrd's calls); point the device key 'library' "
                "at libdrd, which holds libdhd's calls too"
            )
        if not state:
            raise DeviceError(
                f"{self._who}: not calibrated, so its forces stay off; empty its workspace "
                "and run: hapticd calibrate PROFILE"
            )
        # The DRD leaves a device it stopped in brake mode (drdStop(false)); a device
        # without brakes has none to release.
        released = not hasattr(lib, "dhdSetBrakes") or lib.dhdSetBrakes(_OFF, self._id) >= 0
        if not released and not _unsupported(lib):
            raise sdk_error(lib, self._who, "cannot release the brakes")
        self._prime()  # the last calls before the loop's first read
        self._check(lib.dhdEnableForce(_ON, self._id), "cannot enable forces")
        # A zero force at once: the SDK's watchdog counts from the last command.
        self._check(self._send(lib, self._id, 0.0, 0.0, 0.0), "cannot write a zero force")
        self._enabled = True
        self._status_due = 0.0  # the first read with forces on reads the status
