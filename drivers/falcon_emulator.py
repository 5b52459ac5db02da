"""Emulated Novint Falcons under pyusb: an FTDI chip with a simulated Falcon behind it.

``EmulatedFalconBackend`` is a ``usb.backend.IBackend``: it presents each emulator as
the Falcon's FTDI USB device (0403:cb48, one interface, bulk IN 0x81 and OUT 0x02),
answers the FTDI vendor requests pyftdi sends (reset and purge, modem control, flow
control, baud rate, line properties, latency timer, bit mode) and carries the serial
stream both ways, with the two modem status bytes the chip puts before every IN
packet. So ``usb.core.find``, pyftdi and the ``falcon`` backend run unmodified.

``FalconEmulator`` is the device behind the chip: at power-on its bootloader waits
for the loader handshake (DTR pulsed; ``\\n C \\r`` answered with ``\\n D , \\r`` at
9600 baud; ``A`` echoed at 140 kbaud), echoes the firmware bytes it is sent, and
starts the firmware when the upload is over. How a real bootloader knows that is not
public (libnifalcon sends the image, checks each echo and switches the chip to the
normal baud rate, nothing more), so ``firmware_start`` picks one of three readings a
microcontroller could act on: ``"framing"`` (the first byte it cannot frame, one sent
at another baud rate, ends the upload and is lost), ``"length"`` (it knows its image is
``image_size`` bytes) and ``"quiet"`` (the line stays quiet for ``quiet_s`` s). The
chip's own baud setting is invisible to the microcontroller. The firmware
answers each 16-byte command packet with one state packet: encoder counts from a
simulated mechanism following a path (or a ``hand``, hapticd_drivers.sim.Hand, that
feels the motors' force), homed bits, grip buttons. Homing: while the host asks for
it, the simulated user pulls the grip all the way out and pushes it in, and each
encoder is homed when its arm passes the index mark. Fault injection: drop, corrupt
or jump an answer, corrupt the firmware echo, stop answering, answer each command more
than once, stall the IN endpoint (a transfer that waits out its timeout), unplug.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np
import usb.core
from hapticd_drivers import falcon_model as fm
from hapticd_drivers.trajectory import Trajectory
from hapticd_drivers.usb_emulator import (
    ENODEV,
    GET_DESCRIPTOR,
    EmulatedBus,
    fill,
    string_descriptor,
)

# FTDI vendor requests (bRequest) and what the emulated chip does with them.
SIO_RESET, SIO_MODEM_CTRL, SIO_SET_FLOW_CTRL, SIO_SET_BAUDRATE, SIO_SET_DATA = 0, 1, 2, 3, 4
SIO_POLL_MODEM_STATUS, SIO_SET_LATENCY, SIO_GET_LATENCY, SIO_SET_BITMODE = 5, 9, 10, 11
FTDI_CLOCK_HZ = 3_000_000
# Sub-integer divisor codes: bits 14-15 of the value, bit 0 of the index.
_FRAC = (0.0, 0.5, 0.25, 0.125, 0.375, 0.625, 0.75, 0.875)
MODEM_STATUS = bytes([0x01, 0x60])  # CTS/DSR clear, transmitter empty

LOADER_BAUD, BOOT_BAUD, NORMAL_BAUD = 9600, 142_857, 1_500_000
FIRMWARE_STARTS = ("framing", "length", "quiet")
LOADER_HELLO, LOADER_REPLY = b"\n\x43\r", b"\n\x44,\r"
# A stalled IN transfer waits out the timeout it is given, but at most this long (s), so
# that a test of a host that gives a long timeout ends.
STALL_CAP_S = 0.25


def ftdi_baud(value: int, index: int) -> float:
    """Baud rate of an FTDI (FT232R/BM) divisor as SIO_SET_BAUDRATE carries it."""
    div = value & 0x3FFF
    if div == 0 and not value >> 14:
        return FTDI_CLOCK_HZ
    if div == 1 and not value >> 14:
        return FTDI_CLOCK_HZ / 1.5
    frac = _FRAC[((value >> 14) & 3) | ((index & 1) << 2)]
    return FTDI_CLOCK_HZ / (div + frac)


def _near(baud: float, want: float) -> bool:
    return abs(baud - want) <= 0.03 * want


class FalconEmulator:
    """A simulated Falcon (bootloader, firmware, mechanism) behind an FTDI chip."""

    def __init__(
        self,
        path: Trajectory,
        clock: Callable[[], float],
        serial: str = "EMU-FALCON",
        firmware_loaded: bool = False,
        homed: bool = False,
        hand: Any = None,
        firmware_sizes: tuple[int, int] = (4096, 16384),
        homed_bits_outside_homing: bool = False,
        hello_failures: int = 0,
        firmware_failures: int = 0,
        motor_limit: int = fm.MOTOR_LIMIT,
        firmware_start: str = "framing",
        image_size: int | None = None,
        quiet_s: float = 0.02,
    ) -> None:
        self.path, self.clock, self.serial, self.hand = path, clock, serial, hand
        self.firmware_sizes = firmware_sizes
        if firmware_start not in FIRMWARE_STARTS:
            raise ValueError(
                f"firmware_start {firmware_start!r}: expected one of {FIRMWARE_STARTS}"
            )
        if firmware_start == "length" and (image_size is None or image_size < 1):
            raise ValueError("firmware_start 'length' needs image_size, the image's bytes")
        # How the bootloader knows the upload is over (module docstring); the quiet reading
        # times the line on the microcontroller's own clock, real time, as the host waits.
        self.firmware_start, self.image_size, self.quiet_s = firmware_start, image_size, quiet_s
        self._last_load_byte = 0.0
        self.framing_errors = 0  # bytes the bootloader received at another baud rate
        # libnifalcon's FalconFirmware.h: the homed bits are reported only in homing mode
        # (the default here); True: reported whatever the mode. Only a real Falcon says.
        self.homed_bits_outside_homing = homed_bits_outside_homing
        # A bootloader that needs several tries: the first ``hello_failures`` hellos go
        # unanswered, and the first ``firmware_failures`` uploads echo one byte wrong.
        self.hello_failures = hello_failures
        self.firmware_failures = firmware_failures
        self.loads = 0  # uploads begun (the 'A' synchronised)
        # The largest motor value the amplifiers take: libnifalcon's header says 4096
        # (its code's torque cap, 30 x 10000 units, does not fit the packet's 16 bits, so
        # it is no cap a device could take). Commands beyond it are counted, then clipped.
        self.motor_limit = motor_limit
        self.motor_over_limit = 0
        self.hellos = 0  # hellos received
        self.plugged = True
        # The chip.
        self.baud = float(FTDI_CLOCK_HZ)
        self.dtr = False
        self.to_host = bytearray()
        self._from_host = bytearray()
        # The microcontroller: "boot" (waiting for the hello), "sync" (waiting for 'A'),
        # "load" (echoing firmware), "run".
        self.state = "run" if firmware_loaded else "boot"
        self.image = bytearray()
        self.homed = fm.ALL_HOMED if homed else 0
        # Before homing the counts start wherever the arms were at power-on.
        self._offset = np.zeros(3, dtype=int) if homed else np.array([311, -127, 205])
        self.motor = np.zeros(3, dtype=int)
        self.leds = 0
        self.homing = False
        self._homing_t0: float | None = None
        self._theta_prev: np.ndarray | None = None
        self._last_reached = np.zeros(3)
        self.grip = 0
        self.commands = 0
        self.rejected = 0
        self._force = np.zeros(3)
        # Fault injection: counts of upcoming answers to drop, break or jump; firmware
        # bytes to echo wrong; answer nothing from now on.
        self.drop_next = 0
        self.corrupt_next = 0
        self.jump_next = 0
        self.corrupt_echo = 0
        self.silent = False
        # Answers per command (2: a Falcon that answers twice, so its answers pile up).
        self.answers_per_command = 1
        # An IN transfer waits out its timeout and brings nothing (libusb's timeout).
        self.stall_in = False
        # Control transfers (standard and vendor) and bulk OUT transfers the host made.
        self.control_transfers = 0
        self.out_transfers = 0
        # IN transfers made, and the longest timeout (ms) the host gave one.
        self.in_transfers = 0
        self.in_timeout_max_ms = 0
        # The chip holds the firmware's answer until its latency timer runs out: the first
        # IN poll after a command brings only the status bytes, the next the answer.
        self.latency_polls = 1
        self._held: list[list[Any]] = []  # [polls still to wait, answer bytes]

    # -- the mechanism ----------------------------------------------------------------------

    HOMING_SWEEP = ((0.0, 0.0), (1.0, 0.055), (2.5, -0.045), (3.0, 0.0))  # (s, z m)

    def position(self) -> np.ndarray:
        """End-effector position now (3,) m, device frame."""
        now = self.clock()
        if self._homing_t0 is not None:
            # The user follows the homing instructions: grip all the way out, then in.
            t = now - self._homing_t0
            ts, zs = zip(*self.HOMING_SWEEP, strict=True)
            if t < ts[-1]:
                return np.array([0.0, 0.0, float(np.interp(t, ts, zs))])
            self._homing_t0 = None
        if self.hand is None:
            pos, _ = self.path.at(now)
            return np.array(pos)
        self.hand.advance(now, tuple(self._force))
        return np.array(self.hand.x)

    def reachable_position(self) -> np.ndarray:
        """Where the end effector is now (3,) m: the path's point, or, beyond the
        mechanism's reach, the last pose it reached (the arms are at their stops)."""
        p = self.position()
        try:
            fm.inverse(p)
        except fm.FalconKinematicsError:
            return self._last_reached.copy()
        self._last_reached = p
        return p

    def end_effector_force(self) -> np.ndarray:
        """Force (3,) N the motors exert on the end effector now."""
        return fm.force_from_motor(self.reachable_position(), self.motor)

    def _home(self, theta: np.ndarray) -> None:
        if self._theta_prev is not None:
            crossed = (self._theta_prev - fm.ANGLE_AT_ZERO) * (theta - fm.ANGLE_AT_ZERO) <= 0
            for i in range(3):
                if crossed[i] and not self.homed >> i & 1:
                    self.homed |= 1 << i
                    self._offset[i] = 0
        self._theta_prev = theta

    def _answer(self) -> bytes:
        theta = fm.inverse(self.reachable_position())
        if self.homing:
            self._home(theta)
        counts = fm.counts_from_angles(theta) + self._offset
        if self.jump_next:
            self.jump_next -= 1
            counts = counts + np.array([9000, 0, 0])
        homed = self.homed if self.homing or self.homed_bits_outside_homing else 0
        raw = fm.encode_state(tuple(int(c) for c in counts), homed, self.grip)
        if self.corrupt_next:
            self.corrupt_next -= 1
            raw = raw[:5] + b"\x00" + raw[6:]
        return raw

    # -- the firmware -----------------------------------------------------------------------

    def _command(self, packet: bytes) -> None:
        try:
            motor, leds, homing = fm.decode_command(packet)
        except fm.FalconPacketError:
            self.rejected += 1
            return
        self.commands += 1
        # The amplifiers clip at their limit whatever they are sent; a host that sends
        # beyond it is counted (a host that relies on the clip would render a wrong force).
        if max(abs(int(m)) for m in motor) > self.motor_limit:
            self.motor_over_limit += 1
        self.motor = np.clip(np.array(motor), -self.motor_limit, self.motor_limit)
        self.leds = leds
        if homing and not self.homing and self.homed != fm.ALL_HOMED:
            self._homing_t0 = self.clock()
            self._theta_prev = None
        self.homing = homing
        if self.hand is not None:
            self._force = fm.force_from_motor(np.array(self.hand.x), self.motor)
        if self.drop_next:
            self.drop_next -= 1
            return
        for _ in range(self.answers_per_command):
            self._held.append([self.latency_polls, self._answer()])

    def _firmware_bytes(self) -> None:
        buf = self._from_host
        while buf:
            start = buf.find(b"<")
            if start < 0:
                self.rejected += 1
                buf.clear()
                return
            if start > 0:
                self.rejected += 1
                del buf[:start]
            if len(buf) < fm.PACKET_SIZE:
                return
            packet = bytes(buf[: fm.PACKET_SIZE])
            del buf[: fm.PACKET_SIZE]
            self._command(packet)

    def _end_upload(self) -> None:
        """The bootloader ends the upload: it starts an image of a size it takes, else it
        waits for the hello again."""
        lo, hi = self.firmware_sizes
        self.state = "run" if lo <= len(self.image) <= hi else "boot"
        self._from_host.clear()

    def _quiet_over(self) -> None:
        if (
            self.state == "load"
            and self.firmware_start == "quiet"
            and self.image
            and time.monotonic() - self._last_load_byte >= self.quiet_s
        ):
            self._end_upload()

    def _bootloader_bytes(self, data: bytes) -> None:
        if self.state == "load" and not _near(self.baud, BOOT_BAUD):
            # Bytes at another baud rate reach the microcontroller as framing errors.
            self.framing_errors += len(data)
            self._last_load_byte = time.monotonic()
            if self.firmware_start == "framing" and self.image:
                self._end_upload()
            return
        if self.state == "boot" and _near(self.baud, LOADER_BAUD):
            self._from_host += data
            if self._from_host.endswith(LOADER_HELLO):
                self._from_host.clear()
                self.hellos += 1
                if self.hellos > self.hello_failures:
                    self.to_host += LOADER_REPLY
                    self.state = "sync"
        elif self.state == "sync" and _near(self.baud, BOOT_BAUD) and data == b"A":
            self.to_host += b"A"
            self.state = "load"
            self.loads += 1
            if self.loads <= self.firmware_failures:
                self.corrupt_echo = max(self.corrupt_echo, 1)
        elif self.state == "load":
            if self.firmware_start == "length":
                data = data[: self.image_size - len(self.image)]  # type: ignore[operator]
            self.image += data
            self._last_load_byte = time.monotonic()
            echo = bytearray(data)
            if self.corrupt_echo and echo:
                self.corrupt_echo -= 1
                echo[0] ^= 0xFF
            self.to_host += echo
            if self.firmware_start == "length" and len(self.image) == self.image_size:
                self._end_upload()

    def _set_dtr(self, high: bool) -> None:
        # A DTR pulse (low, then high) resets the microcontroller into its bootloader.
        if high and not self.dtr:
            self.state, self.image = "boot", bytearray()
            self._from_host.clear()
            self.to_host.clear()
            self._held.clear()
            self.motor[:] = 0
        self.dtr = high

    # -- the chip ---------------------------------------------------------------------------

    def write(self, data: bytes) -> None:
        self._require()
        if self.silent:
            return
        self._quiet_over()
        if self.state == "run":
            if _near(self.baud, NORMAL_BAUD):
                self._from_host += data
                self._firmware_bytes()
        else:
            self._bootloader_bytes(bytes(data))

    def read(self, size: int) -> bytes:
        self._require()
        self._quiet_over()
        for held in self._held:
            held[0] -= 1
        while self._held and self._held[0][0] < 0:
            self.to_host += self._held.pop(0)[1]
        n = max(0, min(size - 2, 62, len(self.to_host)))
        out = MODEM_STATUS + bytes(self.to_host[:n])
        del self.to_host[:n]
        return out

    def control(self, request: int, value: int, index: int) -> bytes | None:
        """Apply an FTDI vendor request; the bytes an IN request returns."""
        self._require()
        if request == SIO_RESET and value == 1:  # purge what the chip holds for the host
            self.to_host.clear()
            self._held.clear()
        elif request == SIO_RESET and value == 2:
            self._from_host.clear()
        elif request == SIO_MODEM_CTRL and value & 0x100:
            self._set_dtr(bool(value & 1))
        elif request == SIO_SET_BAUDRATE:
            self.baud = ftdi_baud(value, index)
        elif request == SIO_GET_LATENCY:
            return bytes([1])
        elif request == SIO_POLL_MODEM_STATUS:
            return MODEM_STATUS
        return None

    def _require(self) -> None:
        if not self.plugged:
            raise usb.core.USBError("No such device (it may have been disconnected)", -4, ENODEV)

    def unplug(self) -> None:
        self.plugged = False
        self.motor[:] = 0  # no power, no force
        self._force = np.zeros(3)

    def replug(self) -> None:
        """Power comes back: the firmware and the homing are gone, as on the real device."""
        self.plugged = True
        self.state, self.image, self.homed = "boot", bytearray(), 0
        self.to_host.clear()
        self._held.clear()


class EmulatedFalconBackend(EmulatedBus):
    """pyusb backend whose devices are ``FalconEmulator`` instances behind FTDI chips."""

    emulators: list[FalconEmulator]

    def get_device_descriptor(self, dev: int) -> SimpleNamespace:
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=8, idVendor=fm.FALCON_VENDOR_ID,
            idProduct=fm.FALCON_PRODUCT_ID, bcdDevice=0x0600, iManufacturer=1, iProduct=2,
            iSerialNumber=3, bNumConfigurations=1, address=dev + 1, bus=1,
            port_number=dev + 1, port_numbers=(dev + 1,), speed=2,
        )  # fmt: skip

    def get_interface_descriptor(
        self, dev: int, intf: int, alt: int, config: int
    ) -> SimpleNamespace:
        return SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0,
            bNumEndpoints=2, bInterfaceClass=0xFF, bInterfaceSubClass=0xFF,
            bInterfaceProtocol=0xFF, iInterface=2, extra_descriptors=[],
        )  # fmt: skip

    def get_endpoint_descriptor(
        self, dev: int, ep: int, intf: int, alt: int, config: int
    ) -> SimpleNamespace:
        return SimpleNamespace(
            bLength=7, bDescriptorType=5, bEndpointAddress=0x81 if ep == 0 else 0x02,
            bmAttributes=0x02, wMaxPacketSize=64, bInterval=0, bRefresh=0, bSynchAddress=0,
            extra_descriptors=[],
        )  # fmt: skip

    def bulk_write(self, dev_handle: int, ep: int, intf: int, data: Any, timeout: int) -> int:
        emu = self._emu(dev_handle)
        emu.out_transfers += 1
        emu.write(bytes(data))
        return len(data)

    def bulk_read(self, dev_handle: int, ep: int, intf: int, buff: Any, timeout: int) -> int:
        emu = self._emu(dev_handle)
        emu.in_transfers += 1
        emu.in_timeout_max_ms = max(emu.in_timeout_max_ms, timeout)
        if emu.stall_in:
            time.sleep(min(timeout / 1000.0, STALL_CAP_S))
            raise usb.core.USBTimeoutError("Operation timed out", -7, 110)
        return fill(buff, emu.read(len(buff)))

    def ctrl_transfer(
        self, dev_handle: int, bmRequestType: int, bRequest: int, wValue: int, wIndex: int,
        data: Any, timeout: int,
    ) -> int:  # fmt: skip
        emu = self._emu(dev_handle)
        emu.control_transfers += 1
        raw: bytes | None = None
        if bmRequestType == 0x80 and bRequest == GET_DESCRIPTOR:
            texts = {1: "NOVINT (emulated)", 2: "FALCON HAPTIC", 3: emu.serial}
            raw = string_descriptor(wValue, texts)
        elif bmRequestType & 0x60 == 0x40:  # vendor: the FTDI requests
            raw = emu.control(bRequest, wValue, wIndex) or b""
            if not bmRequestType & 0x80:
                return 0
        if raw is None:
            raise usb.core.USBError("Pipe error (request not supported)", -9, 32)
        return fill(data, raw)
