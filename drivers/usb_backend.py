"""The ``usb`` backend: a protocol delta device over libusb through pyusb.

The device exposes one vendor-class interface with an interrupt IN endpoint
(input reports) and an interrupt OUT endpoint (output reports), so no kernel
driver has to be detached; feature reports travel as vendor control requests
(docs/protocol.md). The pyusb backend is passed in (``usb_backend``) and
defaults to libusb from the libusb-package wheel, so pip alone installs it;
tests hand in an emulated backend (``usb.backend.IBackend``). pyusb is
imported only when this backend is selected.
"""

from __future__ import annotations

import contextlib
import importlib
from typing import Any

from hapticd_drivers.base import DeviceError
from hapticd_drivers.device_lock import UsbDeviceLock, pick_device
from hapticd_drivers.report_device import ReportDelta

# Vendor control requests for feature reports (bmRequestType: vendor, interface).
REQ_GET_FEATURE = 0x01
REQ_SET_FEATURE = 0x09
RT_VENDOR_IN = 0xC1
RT_VENDOR_OUT = 0x41
CTRL_TIMEOUT_MS = 100


class UsbDelta(ReportDelta):
    """A protocol delta device on a vendor-class USB interface."""

    transport = "usb"

    def __init__(self, *args: Any, usb_backend: Any = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._backend = usb_backend
        self._dev: Any = None
        self._lock: UsbDeviceLock | None = None
        usb = self.desc.usb or {}
        self.interface = int(usb.get("interface", 0))
        self.in_ep = int(usb.get("in_endpoint", 0x81))
        self.out_ep = int(usb.get("out_endpoint", 0x01))

    def _pyusb(self) -> tuple[Any, Any]:
        try:
            return importlib.import_module("usb.core"), importlib.import_module("usb.util")
        except ImportError as exc:
            raise DeviceError("the usb backend needs pyusb: pip install 'hapticd[usb]'") from exc

    def _libusb(self) -> Any:
        if self._backend is None:
            try:
                libusb_package = importlib.import_module("libusb_package")
            except ImportError as exc:
                raise DeviceError(
                    "the usb backend needs libusb: pip install 'hapticd[usb]'"
                ) from exc
            self._backend = libusb_package.get_libusb1_backend()
            if self._backend is None:
                raise DeviceError("libusb could not be loaded (libusb-package)")
        return self._backend

    def _connect(self) -> None:
        core, util = self._pyusb()
        usb = self.desc.usb or {}
        vid, pid = int(usb["vendor_id"]), int(usb["product_id"])
        try:
            present = list(
                core.find(find_all=True, idVendor=vid, idProduct=pid, backend=self._libusb())
            )
            # Locked before anything is sent: a device another process holds is asked nothing.
            picked = pick_device(
                present,
                self.index,
                self.serial_number,
                lambda d: d.serial_number,
                f"{self.desc.model} {self.serial_number or f'#{self.index}'}",
            )
        except (core.USBError, ValueError) as exc:
            raise self._fail("cannot list devices (permissions? see the udev rules)", exc) from exc
        if picked is None:
            raise self._not_found(len(present))
        dev, self._lock = picked
        try:
            dev.set_configuration()
            util.claim_interface(dev, self.interface)
        except core.USBError as exc:
            self._lock.release()
            self._lock = None
            raise self._fail("cannot open", exc) from exc
        self._dev = dev

    def _disconnect(self) -> None:
        if self._dev is None:
            return
        _, util = self._pyusb()
        # The device may be gone already; its resources go regardless.
        with contextlib.suppress(Exception):
            util.release_interface(self._dev, self.interface)
        util.dispose_resources(self._dev)
        self._dev = None
        if self._lock is not None:
            self._lock.release()  # the device closed first: then another process may have it
            self._lock = None

    def _read_report(self, size: int, timeout_ms: int) -> bytes | None:
        core, _ = self._pyusb()
        try:
            return bytes(self._dev.read(self.in_ep, size, timeout_ms))
        except core.USBTimeoutError:
            return None
        except core.USBError as exc:
            raise OSError(exc.errno or 5, str(exc)) from exc

    def _write_report(self, data: bytes) -> int:
        core, _ = self._pyusb()
        try:
            return int(self._dev.write(self.out_ep, data, CTRL_TIMEOUT_MS))
        except core.USBError as exc:
            raise OSError(exc.errno or 5, str(exc)) from exc

    def _get_feature(self, report_id: int, size: int) -> bytes:
        core, _ = self._pyusb()
        try:
            raw = self._dev.ctrl_transfer(
                RT_VENDOR_IN, REQ_GET_FEATURE, report_id, self.interface, size, CTRL_TIMEOUT_MS
            )
        except core.USBError as exc:
            raise OSError(exc.errno or 5, str(exc)) from exc
        return bytes(raw)

    def _set_feature(self, data: bytes) -> None:
        core, _ = self._pyusb()
        try:
            self._dev.ctrl_transfer(
                RT_VENDOR_OUT, REQ_SET_FEATURE, data[0], self.interface, data, CTRL_TIMEOUT_MS
            )
        except core.USBError as exc:
            raise OSError(exc.errno or 5, str(exc)) from exc
