"""Delta devices speaking the report protocol (docs/protocol.md), over any transport.

``ReportDelta`` holds everything but the transport: it decodes and checks
every input report (length, ID, CRC, sequence), turns encoder counts into
position and velocity, and maps a force to motor currents through the Jacobian
(tau = J^T f), scaling all three down together at the motors' limit so the
force keeps its direction. Every problem is a DeviceError, which the servo loop
turns into zero force and a latched fault. ``HidDelta`` is its cython-hidapi
transport; the ``hid`` module is passed in and defaults to cython-hidapi's,
imported only when this backend is selected, so tests hand in an emulator
behind the same API.
"""

from __future__ import annotations

import importlib
import math
from typing import Any

import numpy as np
from hapticd_drivers.base import Device, DeviceError, DeviceInfo, DeviceState, check_force
from hapticd_drivers.delta import Delta, load_description
from hapticd_drivers.reports import ReportError, ReportSet, sequence_gap

STATUS_WATCHDOG = 2


class ReportDelta(Device):
    """A delta device speaking the report protocol; subclasses provide the transport."""

    transport = "protocol"

    def __init__(
        self,
        description: str = "delta-omega-class",
        serial_number: str | None = None,
        index: int = 0,
        read_timeout_s: float = 0.005,
        max_lost_reports: int = 2,
        device_watchdog_s: float = 0.05,
        serial: str | None = None,
        **_: Any,
    ) -> None:
        self.desc = load_description(description)
        if self.desc.reports is None or self.desc.usb is None:
            raise DeviceError(f"{self.desc.model}: the description lacks 'reports' or 'usb'")
        self.delta = Delta(self.desc)
        self.protocol = ReportSet(self.desc.reports, self.desc.model)
        self.serial_number = serial_number
        self.index = index
        self.read_timeout_ms = max(1, round(read_timeout_s * 1e3))
        self.max_lost = max_lost_reports
        self.device_watchdog_s = device_watchdog_s
        name = serial or serial_number or f"{self.desc.model}#{index}"
        self.info = DeviceInfo(
            self.desc.model, name, self.desc.max_force, self.desc.workspace_radius
        )
        self._open = False
        self._enabled = False
        self._seq_in: int | None = None
        self._seq_out = 0
        self._theta = np.full(3, self.desc.home_angle)
        self._prev: tuple[float, np.ndarray] | None = None
        self.lost_reports = 0

    # -- transport hooks ----------------------------------------------------------------

    def _connect(self) -> None:
        """Find and open the device (by serial number or index); raise DeviceError if absent."""
        raise NotImplementedError

    def _disconnect(self) -> None:
        raise NotImplementedError

    def _read_report(self, size: int, timeout_ms: int) -> bytes | None:
        """One input report, or None on a timeout. OSError or ValueError mean the device is gone."""
        raise NotImplementedError

    def _write_report(self, data: bytes) -> int:
        raise NotImplementedError

    def _get_feature(self, report_id: int, size: int) -> bytes:
        raise NotImplementedError

    def _set_feature(self, data: bytes) -> None:
        raise NotImplementedError

    # -- the device --------------------------------------------------------------------------

    def _fail(self, what: str, exc: BaseException | None = None) -> DeviceError:
        detail = f": {exc}" if exc is not None else ""
        return DeviceError(f"{self.transport} {self.info.serial}: {what}{detail}")

    def _not_found(self, present: int) -> DeviceError:
        usb = self.desc.usb or {}
        want = self.serial_number or f"index {self.index}"
        return self._fail(
            f"no device {int(usb['vendor_id']):04x}:{int(usb['product_id']):04x} ({want}) found; "
            f"{present} present. Is it plugged in, and may this user open it?"
        )

    def open(self) -> None:
        self._connect()
        ident_codec = self.protocol["identity"]
        try:
            ident = ident_codec.decode(self._get_feature(ident_codec.report_id, ident_codec.size))
            self._set_feature(
                self.protocol["limits"].encode(
                    {
                        "max_current": self.desc.max_current,
                        "watchdog": self.device_watchdog_s,
                        "counts_per_rev": self.desc.counts_per_rev,
                    }
                )
            )
        except (OSError, ValueError, ReportError) as exc:
            self._disconnect()
            raise self._fail("cannot read its identity or set its limits", exc) from exc
        self.info = DeviceInfo(
            ident["model"], ident["serial"], self.desc.max_force, self.desc.workspace_radius
        )
        self._seq_in = None
        self._prev = None
        self._open = True

    def close(self) -> None:
        if not self._open:
            return
        try:
            self._send(np.zeros(3), enable=False)
        finally:
            self._open = False
            self._disconnect()

    def read_state(self, state: DeviceState) -> None:
        if not self._open:
            raise self._fail("read from a closed device")
        codec = self.protocol["input"]
        for _ in range(self.max_lost + 1):
            try:
                raw = self._read_report(codec.size, self.read_timeout_ms)
            except (OSError, ValueError) as exc:
                raise self._fail("read failed (unplugged?)", exc) from exc
            if raw:
                break
            self.lost_reports += 1
        else:
            raise self._fail(f"no input report for {self.max_lost + 1} reads (timeout)")
        try:
            values = codec.decode(bytes(raw))
        except ReportError as exc:
            raise self._fail("corrupt input report", exc) from exc
        seq = values["sequence"]
        if self._seq_in is not None:
            gap = sequence_gap(self._seq_in, seq)
            if gap == 0 or gap > 1 + self.max_lost:
                raise self._fail(f"input report out of sequence ({self._seq_in} then {seq})")
        self._seq_in = seq
        if values["status"] & STATUS_WATCHDOG and self._enabled:
            raise self._fail("the device's watchdog cut the forces")
        theta = self.delta.angles_from_counts(np.array(values["encoder"]))
        self._theta = theta
        pos = self.delta.forward(theta)
        t = values["time_us"] * 1e-6
        state.position[:] = pos
        if self._prev is not None and t > self._prev[0]:
            state.velocity[:] = (pos - self._prev[1]) / (t - self._prev[0])
        else:
            state.velocity[:] = 0.0
        self._prev = (t, pos.copy())
        state.buttons = int(values["buttons"])
        state.timestamp = t

    def currents_for(self, force: np.ndarray) -> np.ndarray:
        """Motor currents (3,) A for ``force`` (3,) N at the last read pose, saturated together."""
        current = self.delta.currents(self.delta.torques(self._theta, force))
        peak = float(np.abs(current).max())
        if peak > self.desc.max_current:
            current *= self.desc.max_current / peak  # keeps the force's direction
        return current

    def _send(self, current: np.ndarray, enable: bool) -> None:
        self._seq_out = (self._seq_out + 1) & 0xFFFF
        report = self.protocol["output"].encode(
            {"flags": 1 if enable else 0, "sequence": self._seq_out, "current": tuple(current)}
        )
        try:
            n = self._write_report(report)
        except (OSError, ValueError) as exc:
            raise self._fail("write failed (unplugged?)", exc) from exc
        if n != len(report):
            raise self._fail(f"short write: {n} of {len(report)} bytes")

    def write_force(self, force: np.ndarray) -> None:
        if not self._open:
            raise self._fail("write to a closed device")
        check_force(force, self.info.max_force_n, f"{self.transport} {self.info.serial}")
        current = (
            self.currents_for(np.asarray(force, dtype=float)) if self._enabled else np.zeros(3)
        )
        if not all(math.isfinite(c) for c in current):
            raise self._fail("non-finite motor currents")
        self._send(current, self._enabled)

    def enable_forces(self, enabled: bool) -> None:
        self._enabled = bool(enabled)


class HidDelta(ReportDelta):
    """A protocol delta device over HID (hidraw) through cython-hidapi."""

    transport = "hid"

    def __init__(self, *args: Any, hid_module: Any = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._hid = hid_module
        self._dev: Any = None

    def _module(self) -> Any:
        if self._hid is None:
            try:
                self._hid = importlib.import_module("hid")
            except ImportError as exc:
                raise DeviceError(
                    "the hid backend needs cython-hidapi: pip install 'hapticd[hid]'"
                ) from exc
        return self._hid

    def _connect(self) -> None:
        hid = self._module()
        usb = self.desc.usb or {}
        vid, pid = int(usb["vendor_id"]), int(usb["product_id"])
        present = hid.enumerate(vid, pid)
        found = present
        if self.serial_number is not None:
            found = [d for d in found if d.get("serial_number") == self.serial_number]
        if len(found) <= self.index:
            raise self._not_found(len(present))
        dev = hid.device()
        try:
            dev.open(vid, pid, found[self.index].get("serial_number"))
        except (OSError, ValueError) as exc:
            raise self._fail("cannot open", exc) from exc
        self._dev = dev

    def _disconnect(self) -> None:
        if self._dev is not None:
            self._dev.close()
            self._dev = None

    def _read_report(self, size: int, timeout_ms: int) -> bytes | None:
        raw = self._dev.read(size, timeout_ms)
        return bytes(raw) if raw else None

    def _write_report(self, data: bytes) -> int:
        return int(self._dev.write(data))

    def _get_feature(self, report_id: int, size: int) -> bytes:
        return bytes(self._dev.get_feature_report(report_id, size))

    def _set_feature(self, data: bytes) -> None:
        self._dev.send_feature_report(data)
