"""The ``dhd`` backend: Force Dimension devices through their SDK (libdhd) by ctypes.

Loads libdhd when this backend is selected: the path in ``library`` or the
environment variable HAPTICD_LIBDHD, else the system's ``dhd`` library. Opens
a device by serial number (dhdOpenSerial) or index (dhdOpenID), sets the
device watchdog (125 us units) and the SDK's own force limit, and maps
position, velocity, buttons and force onto the device interface. Every DHD
error is a DeviceError carrying dhdErrorGetLastStr().
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import os
from typing import Any

import numpy as np
from hapticd_drivers.base import Device, DeviceError, DeviceInfo, DeviceState, check_force

WATCHDOG_UNIT_S = 125e-6
_D = ctypes.c_double
_PD = ctypes.POINTER(ctypes.c_double)
_C = ctypes.c_byte  # the SDK's 'char ID'

# name: (restype, argtypes)
_API: dict[str, tuple[Any, list[Any]]] = {
    "dhdGetDeviceCount": (ctypes.c_int, []),
    "dhdErrorGetLastStr": (ctypes.c_char_p, []),
    "dhdOpenID": (ctypes.c_int, [_C]),
    "dhdOpenSerial": (ctypes.c_int, [ctypes.c_int]),
    "dhdClose": (ctypes.c_int, [_C]),
    "dhdGetSerialNumber": (ctypes.c_int, [ctypes.POINTER(ctypes.c_ushort), _C]),
    "dhdGetSystemName": (ctypes.c_char_p, [_C]),
    "dhdEnableForce": (ctypes.c_int, [ctypes.c_ubyte, _C]),
    "dhdSetWatchdog": (ctypes.c_int, [ctypes.c_ubyte, _C]),
    "dhdSetMaxForce": (ctypes.c_int, [_D, _C]),
    "dhdGetButtonMask": (ctypes.c_uint, [_C]),
    "dhdGetPosition": (ctypes.c_int, [_PD, _PD, _PD, _C]),
    "dhdGetLinearVelocity": (ctypes.c_int, [_PD, _PD, _PD, _C]),
    "dhdSetForce": (ctypes.c_int, [_D, _D, _D, _C]),
}
_OPTIONAL = {"dhdOpenSerial", "dhdSetMaxForce", "dhdGetSystemName"}


def load_libdhd(library: str | None = None) -> ctypes.CDLL:
    """libdhd with its argument and return types declared; DeviceError if it is missing."""
    path = library or os.environ.get("HAPTICD_LIBDHD") or ctypes.util.find_library("dhd")
    if not path:
        raise DeviceError(
            "the dhd backend needs Force Dimension's SDK (libdhd), which was not found: "
            "install it, or give its path in the profile's device key 'library' "
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


def preflight(library: str | None = None, **_: Any) -> None:
    """Check that libdhd loads (DeviceError saying how to point at it if not)."""
    load_libdhd(library)


def discover() -> list[dict[str, Any]]:
    """The SDK's devices (indices), or why it cannot look."""
    try:
        lib = load_libdhd()
    except DeviceError as exc:
        return [{"backend": "dhd", "problem": str(exc)}]
    return [
        {
            "backend": "dhd",
            "model": "Force Dimension",
            "found": list(range(lib.dhdGetDeviceCount())),
        }
    ]


class DhdDevice(Device):
    """A Force Dimension device (e.g. omega.3) through libdhd."""

    def __init__(
        self,
        serial_number: int | None = None,
        index: int = 0,
        library: str | None = None,
        device_watchdog_s: float = 0.05,
        max_force_n: float = 12.0,
        serial: str | None = None,
        **_: Any,
    ) -> None:
        self.serial_number = serial_number
        self.index = index
        self.library = library
        self.watchdog = max(1, min(255, round(device_watchdog_s / WATCHDOG_UNIT_S)))
        name = serial or (str(serial_number) if serial_number is not None else f"dhd#{index}")
        self.info = DeviceInfo("dhd", name, float(max_force_n), 0.075)
        self._lib: ctypes.CDLL | None = None
        self._id = -1
        self._enabled = False
        self._xyz = [_D(), _D(), _D()]
        self._refs = [ctypes.byref(v) for v in self._xyz]

    def _err(self, what: str) -> DeviceError:
        detail = self._lib.dhdErrorGetLastStr() if self._lib is not None else b""
        return DeviceError(
            f"dhd {self.info.serial}: {what}: {(detail or b'').decode(errors='replace')}"
        )

    def _check(self, rc: int, what: str) -> int:
        if rc < 0:
            raise self._err(what)
        return rc

    def open(self) -> None:
        lib = self._lib = load_libdhd(self.library)
        count = lib.dhdGetDeviceCount()
        if self.serial_number is not None and hasattr(lib, "dhdOpenSerial"):
            dev_id = lib.dhdOpenSerial(int(self.serial_number))
        elif self.index < count:
            dev_id = lib.dhdOpenID(self.index)
        else:
            raise DeviceError(f"dhd: no device at index {self.index}; {count} present")
        if dev_id < 0:
            raise self._err(f"cannot open ({count} device(s) present)")
        self._id = dev_id
        sn = ctypes.c_ushort()
        self._check(
            lib.dhdGetSerialNumber(ctypes.byref(sn), dev_id), "cannot read the serial number"
        )
        model = lib.dhdGetSystemName(dev_id) if hasattr(lib, "dhdGetSystemName") else None
        self.info = DeviceInfo(
            (model or b"dhd").decode(errors="replace"), str(sn.value), self.info.max_force_n, 0.075
        )
        self._check(lib.dhdSetWatchdog(self.watchdog, dev_id), "cannot set the watchdog")
        if hasattr(lib, "dhdSetMaxForce"):
            self._check(
                lib.dhdSetMaxForce(self.info.max_force_n, dev_id), "cannot set the force limit"
            )

    def close(self) -> None:
        if self._lib is None or self._id < 0:
            return
        lib, dev_id = self._lib, self._id
        self._id = -1
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
        self._enabled = bool(enabled)
        if self._lib is not None and self._id >= 0:
            self._check(
                self._lib.dhdEnableForce(1 if enabled else 0, self._id), "cannot enable forces"
            )
