"""A software Omega-class delta device that speaks the report protocol (docs/protocol.md).

It is the device side: firmware and mechanism. The end-effector follows a
path (the profile's trajectory) on the clock it is given; each input report
carries quantised encoder counts (inverse kinematics), a sequence number and
the device time. Output reports set motor currents, saturated at the motors'
limit; a device-side watchdog zeroes them when no valid output report came for
the watchdog time. Fault injection: drop, corrupt, repeat (reorder) or delay
input reports, and unplug or replug the device. The host-side backends reach
it through the libraries' own seams (a fake ``hid`` module here), so the code
above the seam is exactly what runs on hardware.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from hapticd_drivers.delta import Delta, DeltaDescription
from hapticd_drivers.reports import ReportError, ReportSet
from hapticd_drivers.trajectory import Trajectory


class UnpluggedError(OSError):
    """The emulated device was unplugged (what hidapi and libusb report as an I/O error)."""


class DeltaEmulator:
    """Device side of one emulated delta device moved along ``path``."""

    def __init__(
        self,
        desc: DeltaDescription,
        path: Trajectory,
        clock: Callable[[], float],
        serial: str = "EMU-0001",
        firmware: int = 0x0100,
        hand: Any = None,
    ) -> None:
        if desc.reports is None:
            raise ReportError(f"{desc.model}: the description has no report layouts")
        self.desc = desc
        self.delta = Delta(desc)
        self.protocol = ReportSet(desc.reports, desc.model)
        self.path = path
        self.clock = clock
        # With a hand (hapticd_drivers.sim.Hand) the end-effector is a fingertip that feels
        # the motors' force; without one it follows the path rigidly.
        self.hand = hand
        self.serial = serial
        self.firmware = firmware
        self.watchdog_s = 0.05
        self.currents = np.zeros(3)
        self.forces_enabled = False
        self.watchdog_tripped = False
        self.plugged = True
        self._seq = 0
        self._ack = 0
        self._last_output_t: float | None = None
        self._last_report: bytes | None = None
        self.rejected_outputs = 0
        self._force = np.zeros(3)
        # Fault injection: counts of upcoming input reports to drop, corrupt or repeat.
        self.drop_next = 0
        self.corrupt_next = 0
        self.repeat_next = 0
        self.delay_next = 0

    # -- the mechanism --------------------------------------------------------------------

    def position(self) -> np.ndarray:
        """End-effector position now, m (device frame)."""
        if self.hand is None:
            pos, _ = self.path.at(self.clock())
            return np.array(pos)
        self.hand.advance(self.clock(), tuple(self._force))
        return np.array(self.hand.x)

    def theta(self) -> np.ndarray:
        return self.delta.inverse(self.position())

    def _motor_force(self, theta: np.ndarray) -> np.ndarray:
        tau = self.currents * self.desc.torque_constant * self.desc.gear_ratio
        return np.linalg.solve(self.delta.jacobian(theta).T, tau)

    def end_effector_force(self) -> np.ndarray:
        """Force (3,) N the motors exert on the end-effector now: tau = J^T f."""
        return self._motor_force(self.theta())

    def _check_watchdog(self) -> None:
        now = self.clock()
        if self._last_output_t is not None and now - self._last_output_t > self.watchdog_s:
            self.currents[:] = 0.0
            self._force = np.zeros(3)
            self.watchdog_tripped = True

    # -- reports ----------------------------------------------------------------------------

    def _require_plugged(self) -> None:
        if not self.plugged:
            raise UnpluggedError(5, "emulated device unplugged")

    def input_report(self) -> bytes | None:
        """The next input report, or None when it is lost (a read then times out)."""
        self._require_plugged()
        self._check_watchdog()
        if self.drop_next:
            self.drop_next -= 1
            self._seq = (self._seq + 1) & 0xFFFF
            return None
        if self.repeat_next and self._last_report is not None:
            self.repeat_next -= 1
            return self._last_report
        if self.delay_next:
            self.delay_next -= 1
            return None  # late: this read times out, the report comes with the next one
        counts = self.delta.counts_from_angles(self.theta())
        status = (1 if self.forces_enabled else 0) | (2 if self.watchdog_tripped else 0)
        raw = self.protocol["input"].encode(
            {
                "status": status,
                "sequence": self._seq,
                "time_us": int(self.clock() * 1e6) & 0xFFFFFFFF,
                "encoder": tuple(int(c) for c in counts),
                "buttons": 0,
                "ack_sequence": self._ack,
            }
        )
        self._seq = (self._seq + 1) & 0xFFFF
        self._last_report = raw
        if self.corrupt_next:
            self.corrupt_next -= 1
            bad = bytearray(raw)
            bad[9] ^= 0x40
            return bytes(bad)
        return raw

    def output_report(self, data: bytes) -> None:
        """Apply an output report; a malformed one is rejected and changes nothing."""
        self._require_plugged()
        try:
            values = self.protocol["output"].decode(bytes(data))
        except ReportError:
            self.rejected_outputs += 1
            return
        self._ack = values["sequence"]
        self.forces_enabled = bool(values["flags"] & 1)
        current = np.array(values["current"], dtype=float)
        limit = self.desc.max_current
        self.currents = np.clip(current, -limit, limit) if self.forces_enabled else np.zeros(3)
        if self.hand is not None:
            self._force = self._motor_force(self.theta())
        self._last_output_t = self.clock()
        self.watchdog_tripped = False

    def feature_report(self, report_id: int) -> bytes:
        self._require_plugged()
        if report_id == self.protocol["identity"].report_id:
            return self.protocol["identity"].encode(
                {"model": self.desc.model, "serial": self.serial, "firmware": self.firmware}
            )
        if report_id == self.protocol["limits"].report_id:
            return self.limits_report()
        raise OSError(32, f"no feature report {report_id}")

    def limits_report(self) -> bytes:
        return self.protocol["limits"].encode(
            {
                "max_current": self.desc.max_current,
                "watchdog": self.watchdog_s,
                "counts_per_rev": self.desc.counts_per_rev,
            }
        )

    def set_feature_report(self, data: bytes) -> None:
        self._require_plugged()
        values = self.protocol["limits"].decode(bytes(data))
        self.watchdog_s = float(values["watchdog"])

    def unplug(self) -> None:
        self.plugged = False
        self.currents[:] = 0.0  # no power, no force
        self._force = np.zeros(3)
        self.forces_enabled = False

    def replug(self) -> None:
        self.plugged = True
        self._last_output_t = None


class FakeHidModule:
    """An object with cython-hidapi's module API (``enumerate``, ``device``) in front of
    emulators, so the ``hid`` backend runs unmodified without hardware."""

    def __init__(self, emulators: list[DeltaEmulator]) -> None:
        self.emulators = emulators

    def enumerate(self, vendor_id: int = 0, product_id: int = 0) -> list[dict]:
        out = []
        for i, emu in enumerate(self.emulators):
            usb = emu.desc.usb or {}
            vid, pid = usb.get("vendor_id", 0), usb.get("product_id", 0)
            if (
                not emu.plugged
                or (vendor_id and vid != vendor_id)
                or (product_id and pid != product_id)
            ):
                continue
            out.append(
                {
                    "path": f"emulated/{i}".encode(),
                    "vendor_id": vid,
                    "product_id": pid,
                    "serial_number": emu.serial,
                    "release_number": emu.firmware,
                    "manufacturer_string": "hapticd emulator",
                    "product_string": emu.desc.model,
                    "usage_page": 0xFF00,
                    "usage": 1,
                    "interface_number": usb.get("interface", 0),
                }
            )
        return out

    def device(self) -> FakeHidDevice:
        return FakeHidDevice(self)


class FakeHidDevice:
    """cython-hidapi's ``hid.device`` API over an emulator: open, read, write, feature reports."""

    def __init__(self, module: FakeHidModule) -> None:
        self._module = module
        self._emu: DeltaEmulator | None = None

    def open(
        self, vendor_id: int = 0, product_id: int = 0, serial_number: str | None = None
    ) -> None:
        for emu in self._module.emulators:
            usb = emu.desc.usb or {}
            if (
                emu.plugged
                and usb.get("vendor_id") == vendor_id
                and usb.get("product_id") == product_id
                and (serial_number is None or emu.serial == serial_number)
            ):
                self._emu = emu
                return
        raise OSError("open failed")

    def _dev(self) -> DeltaEmulator:
        if self._emu is None:
            raise ValueError("not open")
        return self._emu

    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]:
        raw = self._dev().input_report()
        return [] if raw is None else list(raw[:max_length])

    def write(self, buff: bytes | list[int]) -> int:
        data = bytes(buff)
        self._dev().output_report(data)
        return len(data)

    def get_feature_report(self, report_num: int, max_length: int) -> list[int]:
        return list(self._dev().feature_report(report_num)[:max_length])

    def send_feature_report(self, data: bytes | list[int]) -> int:
        self._dev().set_feature_report(bytes(data))
        return len(bytes(data))

    def set_nonblocking(self, v: int) -> int:
        return 0

    def error(self) -> str:
        return ""

    def close(self) -> None:
        self._emu = None
