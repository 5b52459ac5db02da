"""The ``dhd`` backend: Force Dimension devices through their SDK (libdhd, libdrd) by ctypes.

Loads the SDK when this backend is selected: the path in ``library`` or the
environment variable HAPTICD_LIBDHD, else the system's ``drd`` library, else
its ``dhd``. libdrd holds every DHD call too, and only it can tell whether a
device is initialised (calibrated) and initialise it (drdIsInitialized,
drdAutoInit), so it is the library to use. Opening a device (dhdOpenSerial or
dhdOpenID) first turns its forces off and writes a zero force, checks the
controller's memory, sets the device watchdog (125 us units), the SDK's own
force limit (dhdSetMaxForce: a second limit, independent of hapticd's safety
chain), the end effector's mass and the SDK's gravity compensation. Forces are
enabled only on an initialised device. Every DHD error is a DeviceError
carrying dhdErrorGetLastStr().
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import math
import os
from typing import Any

import numpy as np
from hapticd_drivers.base import Device, DeviceError, DeviceInfo, DeviceState, check_force

WATCHDOG_UNIT_S = 125e-6
WORKSPACE_RADIUS_M = 0.075  # an omega.3's: a sphere of 75 mm about the home position
_D = ctypes.c_double
_PD = ctypes.POINTER(ctypes.c_double)
_C = ctypes.c_byte  # the SDK's 'char ID'
_ON = 1

# name: (restype, argtypes)
_API: dict[str, tuple[Any, list[Any]]] = {
    "dhdGetDeviceCount": (ctypes.c_int, []),
    "dhdErrorGetLastStr": (ctypes.c_char_p, []),
    "dhdOpenID": (ctypes.c_int, [_C]),
    "dhdOpenSerial": (ctypes.c_int, [ctypes.c_int]),
    "dhdClose": (ctypes.c_int, [_C]),
    "dhdGetSerialNumber": (ctypes.c_int, [ctypes.POINTER(ctypes.c_ushort), _C]),
    "dhdGetSystemName": (ctypes.c_char_p, [_C]),
    "dhdGetSystemType": (ctypes.c_int, [_C]),
    "dhdCheckControllerMemory": (ctypes.c_int, [_C]),
    "dhdEnableExpertMode": (ctypes.c_int, []),
    "dhdDisableExpertMode": (ctypes.c_int, []),
    "dhdEnableForce": (ctypes.c_int, [ctypes.c_ubyte, _C]),
    "dhdSetWatchdog": (ctypes.c_int, [ctypes.c_ubyte, _C]),
    "dhdSetMaxForce": (ctypes.c_int, [_D, _C]),
    "dhdGetMaxForce": (_D, [_C]),
    "dhdSetEffectorMass": (ctypes.c_int, [_D, _C]),
    "dhdSetGravityCompensation": (ctypes.c_int, [ctypes.c_int, _C]),
    "dhdGetButtonMask": (ctypes.c_uint, [_C]),
    "dhdGetPosition": (ctypes.c_int, [_PD, _PD, _PD, _C]),
    "dhdGetLinearVelocity": (ctypes.c_int, [_PD, _PD, _PD, _C]),
    "dhdSetForce": (ctypes.c_int, [_D, _D, _D, _C]),
    # libdrd only: the initialisation (calibration) state and automatic initialisation.
    "drdOpenID": (ctypes.c_int, [_C]),
    "drdClose": (ctypes.c_int, [_C]),
    "drdIsInitialized": (ctypes.c_bool, [_C]),
    "drdAutoInit": (ctypes.c_int, [_C]),
    "drdStop": (ctypes.c_int, [ctypes.c_bool, _C]),
}
# Calls older SDKs or a bare libdhd lack; hapticd works without them (and says what it
# cannot do: check or run the calibration without libdrd).
_OPTIONAL = {
    "dhdOpenSerial",
    "dhdGetSystemName",
    "dhdGetSystemType",
    "dhdCheckControllerMemory",
    "dhdGetMaxForce",
    "drdOpenID",
    "drdClose",
    "drdIsInitialized",
    "drdAutoInit",
    "drdStop",
}
_DRD = ("drdOpenID", "drdClose", "drdIsInitialized", "drdAutoInit", "drdStop")


def load_libdhd(library: str | None = None) -> ctypes.CDLL:
    """The SDK library with its argument and return types declared; DeviceError if missing."""
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
    for name, (restype, argtypes) in _API.items():
        fn = getattr(lib, name, None)
        if fn is None:
            if name in _OPTIONAL:
                continue
            raise DeviceError(f"{path} lacks {name}: an SDK too old or not libdhd")
        fn.restype, fn.argtypes = restype, argtypes
    return lib


def has_drd(lib: ctypes.CDLL) -> bool:
    """True when ``lib`` holds the DRD calls hapticd uses (libdrd)."""
    return all(hasattr(lib, name) for name in _DRD)


def _last_error(lib: ctypes.CDLL) -> str:
    return (lib.dhdErrorGetLastStr() or b"").decode(errors="replace")


def _identity(lib: ctypes.CDLL, dev_id: int) -> tuple[str, str]:
    """(model, serial number) of an open device."""
    sn = ctypes.c_ushort()
    if lib.dhdGetSerialNumber(ctypes.byref(sn), dev_id) < 0:
        raise DeviceError(f"dhd: cannot read the serial number: {_last_error(lib)}")
    name = lib.dhdGetSystemName(dev_id) if hasattr(lib, "dhdGetSystemName") else None
    return (name or b"Force Dimension device").decode(errors="replace"), str(sn.value)


def preflight(library: str | None = None, **_: Any) -> None:
    """Check that the SDK library loads (DeviceError saying how to point at it if not)."""
    load_libdhd(library)


def discover() -> list[dict[str, Any]]:
    """The SDK's devices, per model: serial number, index and initialisation state; or why
    it cannot look. A device another program holds open is listed as in use."""
    try:
        lib = load_libdhd()
    except DeviceError as exc:
        return [{"backend": "dhd", "problem": str(exc)}]
    drd = has_drd(lib)
    by_model: dict[str, list[str]] = {}
    devices: list[dict[str, Any]] = []
    for i in range(lib.dhdGetDeviceCount()):
        dev_id = lib.dhdOpenID(i)
        if dev_id < 0:
            entry = {"index": i, "problem": f"cannot open: {_last_error(lib)} (in use?)"}
            devices.append(entry)
            by_model.setdefault("Force Dimension", []).append(f"index {i}: {entry['problem']}")
            continue
        try:
            model, serial = _identity(lib, dev_id)
            calibrated = bool(lib.drdIsInitialized(dev_id)) if drd else None
        finally:
            lib.dhdClose(dev_id)
        state = {True: "calibrated", False: "NOT calibrated", None: "calibration unknown"}
        devices.append({"index": i, "model": model, "serial": serial, "calibrated": calibrated})
        by_model.setdefault(model, []).append(f"{serial} (index {i}, {state[calibrated]})")
    if not by_model:
        return [{"backend": "dhd", "model": "Force Dimension", "found": [], "devices": []}]
    return [
        {
            "backend": "dhd",
            "model": model,
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
    Returns model, serial and whether it was initialised before; DeviceError on failure."""
    lib = load_libdhd(library)
    if not has_drd(lib):
        raise DeviceError(
            f"{lib._name} has no drdAutoInit: calibrating needs libdrd (it holds "
            "libdhd's calls too); give its path in the device key 'library'"
        )
    count = lib.dhdGetDeviceCount()
    dev_id = -1
    if serial_number is None:
        if index >= count:
            raise DeviceError(f"dhd: no device at index {index}; {count} present")
        dev_id = lib.drdOpenID(index)
        if dev_id < 0:
            raise DeviceError(f"dhd: cannot open device {index}: {_last_error(lib)}")
    else:
        # libdrd opens by index only: look for the serial number among the devices.
        for i in range(count):
            candidate = lib.drdOpenID(i)
            if candidate < 0:
                continue
            if _identity(lib, candidate)[1] == str(serial_number):
                dev_id = candidate
                break
            lib.drdClose(candidate)
        if dev_id < 0:
            raise DeviceError(
                f"dhd: no device with serial number {serial_number} among {count} present"
            )
    try:
        model, serial = _identity(lib, dev_id)
        was = bool(lib.drdIsInitialized(dev_id))
        if lib.drdAutoInit(dev_id) < 0:
            raise DeviceError(
                f"dhd {serial} ({model}): automatic initialisation failed: {_last_error(lib)}"
            )
        # Stop the SDK's regulation with forces off: hapticd enables them when it runs.
        if lib.drdStop(False, dev_id) < 0:
            raise DeviceError(f"dhd {serial}: cannot stop the regulation: {_last_error(lib)}")
        if not lib.drdIsInitialized(dev_id):
            raise DeviceError(f"dhd {serial} ({model}): still not initialised after drdAutoInit")
    finally:
        with contextlib.suppress(Exception):
            lib.dhdEnableForce(0, dev_id)
        lib.drdClose(dev_id)
    return {"model": model, "serial": serial, "was_calibrated": was}


class DhdDevice(Device):
    """A Force Dimension device (e.g. omega.3) through its SDK.

    ``max_force_n`` (N) is the device's rated force in hapticd and the SDK's own force
    limit; ``effector_mass_kg`` (kg) the end effector's mass for the SDK's gravity
    compensation (None: the SDK's default for the model).
    """

    def __init__(
        self,
        serial_number: int | None = None,
        index: int = 0,
        library: str | None = None,
        device_watchdog_s: float = 0.03,
        max_force_n: float = 12.0,
        effector_mass_kg: float | None = None,
        serial: str | None = None,
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
        name = serial or (str(serial_number) if serial_number is not None else f"dhd#{index}")
        self.info = DeviceInfo("dhd", name, float(max_force_n), WORKSPACE_RADIUS_M)
        self._lib: ctypes.CDLL | None = None
        self._id = -1
        self._enabled = False
        self._xyz = [_D(), _D(), _D()]
        self._refs = [ctypes.byref(v) for v in self._xyz]

    def _err(self, what: str) -> DeviceError:
        detail = _last_error(self._lib) if self._lib is not None else ""
        return DeviceError(f"dhd {self.info.serial}: {what}: {detail}")

    def _check(self, rc: int, what: str) -> int:
        if rc < 0:
            raise self._err(what)
        return rc

    def open(self) -> None:
        lib = self._lib = load_libdhd(self.library)
        count = lib.dhdGetDeviceCount()
        if self.serial_number is not None and hasattr(lib, "dhdOpenSerial"):
            dev_id = lib.dhdOpenSerial(int(self.serial_number))
        elif self.serial_number is not None:
            raise DeviceError(f"dhd: {lib._name} cannot open by serial number; use 'index'")
        elif self.index < count:
            dev_id = lib.dhdOpenID(self.index)
        else:
            raise DeviceError(f"dhd: no device at index {self.index}; {count} present")
        if dev_id < 0:
            raise self._err(f"cannot open ({count} device(s) present)")
        self._id = dev_id
        try:
            self._set_up(lib, dev_id)
        except BaseException:
            self._id = -1
            with contextlib.suppress(Exception):
                lib.dhdEnableForce(0, dev_id)
            lib.dhdClose(dev_id)
            raise

    def _set_up(self, lib: ctypes.CDLL, dev_id: int) -> None:
        """Everything between opening and enabling forces, in the order it is safe."""
        # Whatever the last program left: forces off, and a zero force is the first command.
        self._enabled = False
        self._check(lib.dhdEnableForce(0, dev_id), "cannot disable forces")
        self._check(lib.dhdSetForce(0.0, 0.0, 0.0, dev_id), "cannot write a zero force")
        model, serial = _identity(lib, dev_id)
        self.info = DeviceInfo(model, serial, self.info.max_force_n, WORKSPACE_RADIUS_M)
        if hasattr(lib, "dhdCheckControllerMemory") and lib.dhdCheckControllerMemory(dev_id):
            raise self._err(
                "the controller's memory check failed (firmware or configuration); do not "
                "use the device, contact Force Dimension"
            )
        # The watchdog is an expert setting: expert mode only for as long as it takes.
        self._check(lib.dhdEnableExpertMode(), "cannot enter expert mode")
        try:
            self._check(lib.dhdSetWatchdog(self.watchdog, dev_id), "cannot set the watchdog")
        finally:
            lib.dhdDisableExpertMode()
        limit = self.info.max_force_n
        self._check(lib.dhdSetMaxForce(limit, dev_id), "cannot set the SDK's force limit")
        if hasattr(lib, "dhdGetMaxForce"):
            got = lib.dhdGetMaxForce(dev_id)
            if not abs(got - limit) <= 1e-9 * limit:
                raise self._err(f"the SDK's force limit reads {got:g} N, not {limit:g} N")
        if self.effector_mass_kg is not None:
            self._check(
                lib.dhdSetEffectorMass(self.effector_mass_kg, dev_id),
                "cannot set the effector mass",
            )
        self._check(lib.dhdSetGravityCompensation(_ON, dev_id), "cannot turn on gravity comp.")

    def calibrated(self) -> bool | None:
        """Whether the SDK reports the device initialised (calibrated); None when the library
        cannot tell (libdhd without libdrd's calls)."""
        if self._lib is None or self._id < 0:
            raise DeviceError(f"dhd {self.info.serial}: not open")
        if not has_drd(self._lib):
            return None
        return bool(self._lib.drdIsInitialized(self._id))

    def close(self) -> None:
        if self._lib is None or self._id < 0:
            return
        lib, dev_id = self._lib, self._id
        self._id = -1
        self._enabled = False
        lib.dhdSetForce(0.0, 0.0, 0.0, dev_id)
        lib.dhdEnableForce(0, dev_id)
        lib.dhdClose(dev_id)

    def read_state(self, state: DeviceState) -> None:
        if self._id < 0:
            raise DeviceError(f"dhd {self.info.serial}: read from a closed device")
        lib, refs, xyz = self._lib, self._refs, self._xyz
        assert lib is not None
        self._check(lib.dhdGetPosition(*refs, self._id), "cannot read the position")
        state.position[:] = (xyz[0].value, xyz[1].value, xyz[2].value)
        self._check(lib.dhdGetLinearVelocity(*refs, self._id), "cannot read the velocity")
        state.velocity[:] = (xyz[0].value, xyz[1].value, xyz[2].value)
        state.buttons = int(lib.dhdGetButtonMask(self._id))

    def write_force(self, force: np.ndarray) -> None:
        if self._id < 0:
            raise DeviceError(f"dhd {self.info.serial}: write to a closed device")
        check_force(force, self.info.max_force_n, f"dhd {self.info.serial}")
        f = (
            (float(force[0]), float(force[1]), float(force[2]))
            if self._enabled
            else (0.0, 0.0, 0.0)
        )
        if not all(math.isfinite(v) for v in f):
            raise DeviceError(f"dhd {self.info.serial}: refused a non-finite force")
        assert self._lib is not None
        self._check(self._lib.dhdSetForce(*f, self._id), "cannot set the force")

    def enable_forces(self, enabled: bool) -> None:
        if not enabled:
            self._enabled = False
            if self._lib is not None and self._id >= 0:
                self._check(self._lib.dhdEnableForce(0, self._id), "cannot disable forces")
            return
        if self._lib is None or self._id < 0:
            raise DeviceError(f"dhd {self.info.serial}: cannot enable forces on a closed device")
        state = self.calibrated()
        if state is None:
            raise DeviceError(
                f"dhd {self.info.serial}: forces stay off: {self._lib._name} cannot tell whether "
                "the device is calibrated (libdhd without libdrd's calls); point the device "
                "key 'library' at libdrd, which holds libdhd's calls too"
            )
        if not state:
            raise DeviceError(
                f"dhd {self.info.serial} ({self.info.model}): not calibrated, so its forces "
                "stay off; empty its workspace and run: hapticd calibrate PROFILE"
            )
        self._check(self._lib.dhdEnableForce(_ON, self._id), "cannot enable forces")
        self._enabled = True
