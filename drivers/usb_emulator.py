"""Emulated delta devices under pyusb: a custom ``usb.backend.IBackend``.

It presents each emulator as a USB device (descriptors, string descriptors,
one vendor-class interface with interrupt IN and OUT endpoints) and carries
reports to and from it, so ``usb.core.find`` and the ``usb`` backend run
unmodified. A lost input report is a libusb timeout; an unplugged device an
I/O error, as libusb reports them. Needs pyusb (``pip install 'hapticd[usb]'``).
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import usb.backend
import usb.core
from hapticd_drivers.emulator import DeltaEmulator
from hapticd_drivers.usb_backend import (
    REQ_GET_FEATURE,
    REQ_SET_FEATURE,
    RT_VENDOR_IN,
    RT_VENDOR_OUT,
)

GET_DESCRIPTOR = 0x06
DESC_STRING = 0x03
LANG_EN_US = 0x0409
ENODEV = 19


class EmulatedBus(usb.backend.IBackend):
    """What every emulated pyusb backend shares: its devices are emulators (each with a
    ``plugged`` flag), listed while plugged in; opening, configuring and claiming check
    that the device is still there, and one that is not is libusb's ENODEV."""

    def __init__(self, emulators: list[Any]) -> None:
        self.emulators = emulators

    def _emu(self, dev: int) -> Any:
        emu = self.emulators[dev]
        if not emu.plugged:
            raise usb.core.USBError("No such device (it may have been disconnected)", -4, ENODEV)
        return emu

    def enumerate_devices(self) -> Any:
        return iter([i for i, e in enumerate(self.emulators) if e.plugged])

    def get_configuration_descriptor(self, dev: int, config: int) -> SimpleNamespace:
        """One configuration with one interface, bus powered."""
        return SimpleNamespace(
            bLength=9, bDescriptorType=2, wTotalLength=32, bNumInterfaces=1,
            bConfigurationValue=1, iConfiguration=0, bmAttributes=0x80, bMaxPower=250,
            extra_descriptors=[],
        )  # fmt: skip

    def open_device(self, dev: int) -> int:
        self._emu(dev)
        return dev

    def close_device(self, dev_handle: int) -> None:
        pass

    def set_configuration(self, dev_handle: int, config_value: int) -> None:
        self._emu(dev_handle)

    def get_configuration(self, dev_handle: int) -> int:
        return 1

    def claim_interface(self, dev_handle: int, intf: int) -> None:
        self._emu(dev_handle)

    def release_interface(self, dev_handle: int, intf: int) -> None:
        pass

    def is_kernel_driver_active(self, dev_handle: int, intf: int) -> bool:
        return False


def string_descriptor(w_value: int, texts: dict[int, str]) -> bytes | None:
    """The GET_DESCRIPTOR(string) answer for ``w_value`` (index 0: the languages), or None
    when ``w_value`` asks for another descriptor type."""
    if w_value >> 8 != DESC_STRING:
        return None
    index = w_value & 0xFF
    if index == 0:
        return bytes([4, DESC_STRING]) + LANG_EN_US.to_bytes(2, "little")
    body = texts.get(index, "").encode("utf-16-le")
    return bytes([2 + len(body), DESC_STRING]) + body


def fill(buff: Any, raw: bytes) -> int:
    """Copy ``raw`` into pyusb's array ``buff`` as far as it fits; the bytes copied."""
    n = min(len(raw), len(buff))
    buff[:n] = type(buff)(buff.typecode, raw[:n])
    return n


class EmulatedUsbBackend(EmulatedBus):
    """pyusb backend whose devices are ``DeltaEmulator`` instances."""

    emulators: list[DeltaEmulator]

    def get_device_descriptor(self, dev: int) -> SimpleNamespace:
        emu = self.emulators[dev]
        ids = emu.desc.usb or {}
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=int(ids["vendor_id"]),
            idProduct=int(ids["product_id"]), bcdDevice=emu.firmware, iManufacturer=1,
            iProduct=2, iSerialNumber=3, bNumConfigurations=1, address=dev + 1, bus=1,
            port_number=dev + 1, port_numbers=(dev + 1,), speed=3,
        )  # fmt: skip

    def get_interface_descriptor(
        self, dev: int, intf: int, alt: int, config: int
    ) -> SimpleNamespace:
        ids = self.emulators[dev].desc.usb or {}
        return SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=int(ids.get("interface", 0)),
            bAlternateSetting=0, bNumEndpoints=2, bInterfaceClass=0xFF, bInterfaceSubClass=0,
            bInterfaceProtocol=0, iInterface=0, extra_descriptors=[],
        )  # fmt: skip

    def get_endpoint_descriptor(
        self, dev: int, ep: int, intf: int, alt: int, config: int
    ) -> SimpleNamespace:
        ids = self.emulators[dev].desc.usb or {}
        address = (
            int(ids.get("in_endpoint", 0x81)) if ep == 0 else int(ids.get("out_endpoint", 0x01))
        )
        return SimpleNamespace(
            bLength=7, bDescriptorType=5, bEndpointAddress=address, bmAttributes=0x03,
            wMaxPacketSize=64, bInterval=1, bRefresh=0, bSynchAddress=0, extra_descriptors=[],
        )  # fmt: skip

    def intr_read(self, dev_handle: int, ep: int, intf: int, buff: Any, timeout: int) -> int:
        raw = self._emu(dev_handle).input_report()
        if raw is None:
            raise usb.core.USBTimeoutError("Operation timed out", -7, 110)
        return fill(buff, raw)

    def intr_write(self, dev_handle: int, ep: int, intf: int, data: Any, timeout: int) -> int:
        self._emu(dev_handle).output_report(bytes(data))
        return len(data)

    def ctrl_transfer(
        self, dev_handle: int, bmRequestType: int, bRequest: int, wValue: int, wIndex: int,
        data: Any, timeout: int,
    ) -> int:  # fmt: skip
        emu = self._emu(dev_handle)
        texts = {1: "hapticd emulator", 2: emu.desc.model, 3: emu.serial}
        if bmRequestType == 0x80 and bRequest == GET_DESCRIPTOR:
            raw = string_descriptor(wValue, texts)
        elif bmRequestType == RT_VENDOR_IN and bRequest == REQ_GET_FEATURE:
            raw = emu.feature_report(wValue)
        elif bmRequestType == RT_VENDOR_OUT and bRequest == REQ_SET_FEATURE:
            emu.set_feature_report(bytes(data))
            return len(data)
        else:
            raw = None
        if raw is None:
            raise usb.core.USBError("Pipe error (request not supported)", -9, 32)
        return fill(data, raw)
