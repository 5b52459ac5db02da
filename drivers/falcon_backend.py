"""The ``falcon`` backend: a Novint Falcon over its FTDI USB chip, through pyftdi on pyusb.

No vendor SDK: the host speaks the Falcon's firmware protocol (hapticd_drivers.
falcon_model) through pyftdi, which drives the FTDI chip's baud rate, line, modem
lines, latency timer and buffers and strips its modem status bytes. A Falcon that
has been powered up runs a bootloader: the backend loads the firmware from the file the
profile names (``firmware``; Novint's image is not ours to ship: docs/devices.md says
where to find it), echo-checked byte by byte. After power-on the encoders count from
wherever the arms were: ``hapticd calibrate`` (``calibrate`` here) homes them, and an
open refuses a Falcon that is not homed, so one that is never gets force. The LEDs
show the state (red: not homed, blue: ready, forces off, green: forces on); the grip's
four buttons are the device's buttons 0-3.

Each tick the backend reads the firmware's answer to its last command (encoders to
thigh angles to position by forward kinematics, velocity over a 20 ms window of ``clock``)
and sends the next command (force to thigh torques through the Jacobian, scaled
together to the motor limit). A broken frame, an impossible encoder jump, a lost
homing, a Falcon that stops answering or is unplugged: DeviceError naming the Falcon.
pyusb's backend is passed in (``usb_backend``; libusb from libusb-package by default),
so tests hand in the emulator (hapticd_drivers.falcon_emulator).
"""

from __future__ import annotations

import contextlib
import importlib
import os
import stat
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from hapticd_drivers import falcon_model as fm
from hapticd_drivers import models
from hapticd_drivers.base import (
    Device,
    DeviceError,
    DeviceInfo,
    DeviceLostError,
    DeviceState,
    check_force,
)
from hapticd_drivers.device_lock import (
    DeviceInUseError,
    UsbDeviceLock,
    lock_usb_device,
    pick_device,
)

MODEL = models.by_usb_id(fm.FALCON_VENDOR_ID, fm.FALCON_PRODUCT_ID)
assert MODEL is not None
# The known firmware images are 7-9 KB (libnifalcon's firmware/ directory): a file far
# from that is not a Falcon firmware.
FIRMWARE_MIN_BYTES, FIRMWARE_MAX_BYTES = 4096, 16384
# The bootloader takes at most 62 bytes per write (libnifalcon FalconFirmware.cpp: a
# 64-byte full-speed packet less the chip's two status bytes).
FIRMWARE_CHUNK = 62
# The serial rates libnifalcon sets (FalconCommLibUSB.cpp): the loader's handshake at
# 9600 baud, the firmware upload at 3 MHz / 21, and the running firmware at 3 MHz / 2.
LOADER_BAUD, BOOT_BAUD, NORMAL_BAUD = 9600, 142_857, 1_500_000
LOADER_HELLO, LOADER_REPLY = b"\n\x43\r", b"\n\x44,\r"
# As libnifalcon: up to 100 hellos before the bootloader counts as silent
# (FalconCommLibUSB.cpp, setFirmwareMode), and the whole load tried up to 10 times
# (FalconCLIBase.cpp and its examples loop 10 times over loadFirmware), since a load
# can fail once and succeed after the next reset.
LOADER_HELLO_TRIES, FIRMWARE_ATTEMPTS = 100, 10
# After the upload: the line is left quiet this long (s), then the firmware is asked up to
# FIRMWARE_PROBES times whether it runs.
FIRMWARE_QUIET_S, FIRMWARE_PROBES = 0.05, 10
# Velocity is the position's change over this window, s: as Force Dimension's SDK
# estimates it (its default window is 20 ms, dhdConfigLinearVelocity), for the same
# reason: encoder counts differenced over one tick are mostly quantisation noise.
VELOCITY_WINDOW_S = 0.02
# USB transfer timeouts, ms. Running, every transfer is given a few ms: the chip answers
# an IN request within its 1 ms latency timer, and a transfer that waits longer is a
# stalled Falcon, lost well within the loop's watchdog (pyftdi's default, 5 s, would hold
# the loop with the last motor command applied). Opening and loading the firmware (latency
# timer 16 ms, 9600 baud) are given longer.
TRANSFER_TIMEOUT_MS, SETUP_TIMEOUT_MS = 5, 500
# An arm cannot turn this far (about 36 degrees) between two packets 1 ms apart.
MAX_ENCODER_STEP = 1000
LED_NOT_HOMED, LED_READY, LED_FORCES = fm.LED_RED, fm.LED_BLUE, fm.LED_GREEN


def _pyusb() -> Any:
    try:
        return importlib.import_module("usb.core")
    except ImportError as exc:
        raise DeviceError("the falcon backend needs pyusb: pip install pyusb") from exc


def _libusb(backend: Any) -> Any:
    if backend is not None:
        return backend
    try:
        libusb_package = importlib.import_module("libusb_package")
    except ImportError as exc:
        raise DeviceError("the falcon backend needs libusb: pip install libusb-package") from exc
    found = libusb_package.get_libusb1_backend()
    if found is None:
        raise DeviceError("libusb could not be loaded (libusb-package)")
    return found


def find_falcons(usb_backend: Any = None) -> list[Any]:
    """The attached Falcons (pyusb devices), in bus order."""
    core = _pyusb()
    try:
        return list(
            core.find(
                find_all=True,
                idVendor=fm.FALCON_VENDOR_ID,
                idProduct=fm.FALCON_PRODUCT_ID,
                backend=_libusb(usb_backend),
            )
        )
    except (core.USBError, ValueError) as exc:
        raise DeviceError(
            f"cannot list USB devices (permissions? see the udev rules): {exc}"
        ) from exc


def read_firmware(path: str | Path) -> bytes:
    """The firmware image in ``path`` (the device key ``firmware``); DeviceError if it is
    missing, not a regular file, or of a size no Falcon firmware has.

    Opened without blocking and checked before a byte is read: a FIFO would wait for a
    writer and ``/dev/zero`` never ends."""
    p = Path(path).expanduser()
    where = f"falcon firmware {p} (device key 'firmware')"
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise DeviceError(
            f"{where}: cannot read it ({exc.strerror}); docs/devices.md says where to find the file"
        ) from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise DeviceError(
                f"{where}: not a regular file (mode {stat.filemode(info.st_mode)}); name the "
                "firmware image file itself, e.g. Novint's test_firmware.bin"
            )
        if not FIRMWARE_MIN_BYTES <= info.st_size <= FIRMWARE_MAX_BYTES:
            raise DeviceError(
                f"{where}: {info.st_size} bytes, expected {FIRMWARE_MIN_BYTES}-"
                f"{FIRMWARE_MAX_BYTES} (a Falcon firmware image, e.g. Novint's "
                "test_firmware.bin)"
            )
        # At most one byte past the bound: a file that grows while read is refused too.
        image = bytearray()
        while len(image) <= FIRMWARE_MAX_BYTES:
            part = os.read(fd, FIRMWARE_MAX_BYTES + 1 - len(image))
            if not part:
                break
            image += part
    except OSError as exc:
        raise DeviceError(f"{where}: cannot read it ({exc.strerror})") from None
    finally:
        os.close(fd)
    if len(image) != info.st_size:
        raise DeviceError(f"{where}: changed while read ({info.st_size} bytes, then {len(image)})")
    return bytes(image)


class FalconDevice(Device):
    """One Novint Falcon. ``firmware``: path of the firmware image to load when the
    Falcon runs none yet; ``max_force_n`` (N): rated force, at most the model's."""

    # Lost (DeviceLostError): the chip gone from the bus, or a Falcon that answers nothing
    # (its firmware gone with its power). A Falcon that answers wrongly is a fault.
    reports_lost = True

    def __init__(
        self,
        firmware: str | None = None,
        serial_number: str | None = None,
        index: int = 0,
        max_force_n: float = MODEL.max_force_n,
        usb_backend: Any = None,
        clock: Callable[[], float] | None = None,
        read_attempts: int = 3,
        serial: str | None = None,
        **_: Any,
    ) -> None:
        if not 0.0 < max_force_n <= MODEL.max_force_n:
            raise DeviceError(
                f"falcon: max_force_n {max_force_n} N, expected > 0 and at most the "
                f"Falcon's {MODEL.max_force_n:g} N"
            )
        self.firmware = firmware
        self.serial_number = serial_number
        self.index = index
        self._backend = usb_backend
        self._clock = clock or time.monotonic
        self.read_attempts = read_attempts
        self.info = self._info(serial or serial_number or f"falcon#{index}", max_force_n)
        self._lock: UsbDeviceLock | None = None
        self._ftdi: Any = None
        self._enabled = False
        self._rx = bytearray()
        self._pending = 0
        self._counts: tuple[int, int, int] | None = None
        self._p = np.zeros(3)
        # (time s, position m) of the reads within the velocity window, oldest first.
        self._recent: deque[tuple[float, np.ndarray]] = deque()
        self._motor = np.zeros(3, dtype=int)
        self.homed = 0
        self.grip = 0

    @staticmethod
    def _info(serial: str, max_force_n: float) -> DeviceInfo:
        assert MODEL is not None
        return DeviceInfo.of_model(MODEL, serial, max_force_n)

    def _fail(self, what: str, exc: BaseException | None = None, lost: bool = False) -> DeviceError:
        detail = f": {exc}" if exc is not None else ""
        cls = DeviceLostError if lost else DeviceError
        return cls(f"falcon {self.info.serial}: {what}{detail}")

    # -- the FTDI chip ------------------------------------------------------------------------

    def _connect(self) -> None:
        try:
            ftdi_mod = importlib.import_module("pyftdi.ftdi")
        except ImportError as exc:
            raise self._fail("the falcon backend needs pyftdi: pip install pyftdi", exc) from exc
        present = find_falcons(self._backend)
        # Locked before anything is sent: a Falcon another process holds is asked nothing.
        picked = pick_device(
            present, self.index, self.serial_number, _serial, f"falcon {self.info.serial}"
        )
        if picked is None:
            want = self.serial_number or f"index {self.index}"
            raise self._fail(
                f"no Falcon ({want}) found; {len(present)} present (one another process "
                "holds is not asked its serial number). Is it plugged in and powered, and "
                "may this user open it (hapticd udev-rules)?"
            )
        dev, self._lock = picked
        ftdi = ftdi_mod.Ftdi()
        ftdi.timeouts = (SETUP_TIMEOUT_MS, SETUP_TIMEOUT_MS)
        try:
            ftdi.open_from_device(dev)
        except (ftdi_mod.FtdiError, OSError, ValueError) as exc:
            self._release()
            raise self._fail("cannot open its FTDI chip", exc) from exc
        self._ftdi = ftdi
        if self.serial_number is None:
            with contextlib.suppress(Exception):
                self.info = self._info(_serial(dev) or self.info.serial, self.info.max_force_n)

    def _chip(self, what: str, call: Callable[[], Any]) -> Any:
        try:
            return call()
        except Exception as exc:  # pyftdi's FtdiError, pyusb's USBError, OSError
            # pyftdi raises its FtdiError from pyusb's error, which stays its context.
            cause = exc.__cause__ or exc.__context__
            if type(cause).__name__ == "USBTimeoutError":
                ms = self._ftdi.timeouts[0] if self._ftdi is not None else "?"
                raise self._fail(f"{what} stalled (no transfer within {ms} ms)", lost=True) from exc
            raise self._fail(f"{what} failed (unplugged?)", exc, lost=True) from exc

    def _normal_mode(self) -> None:
        f = self._ftdi
        f.timeouts = (SETUP_TIMEOUT_MS, SETUP_TIMEOUT_MS)
        self._chip("setting the latency timer", lambda: f.set_latency_timer(1))
        self._chip("setting the baud rate", lambda: f.set_baudrate(NORMAL_BAUD))
        self._chip("purging", f.purge_buffers)
        f.timeouts = (TRANSFER_TIMEOUT_MS, TRANSFER_TIMEOUT_MS)
        self._rx.clear()
        self._pending = 0

    def _write(self, data: bytes) -> None:
        n = self._chip("write", lambda: self._ftdi.write_data(data))
        if n != len(data):
            raise self._fail(f"short write: {n} of {len(data)} bytes")

    def _read(self, size: int) -> bytes:
        return bytes(self._chip("read", lambda: self._ftdi.read_data(size)))

    def _read_exact(self, size: int, attempts: int) -> bytes:
        out = bytearray()
        for _ in range(attempts):
            out += self._read(size - len(out))
            if len(out) >= size:
                break
        return bytes(out)

    # -- firmware ------------------------------------------------------------------------------

    def _send(self) -> None:
        leds = (
            LED_NOT_HOMED
            if self.homed != fm.ALL_HOMED
            else (LED_FORCES if self._enabled else LED_READY)
        )
        # Homing mode always on, as libnifalcon keeps it: its header says the homed bits
        # are reported only in homing mode, so turning it off could hide them.
        self._write(fm.encode_command(tuple(int(m) for m in self._motor), leds, True))
        self._pending += 1

    def _packet(self) -> bytes | None:
        """The next 16-byte packet from the firmware, or None after ``read_attempts`` reads
        brought none. DeviceError if more answers wait than commands went unanswered."""
        for _ in range(self.read_attempts):
            if len(self._rx) >= fm.PACKET_SIZE:
                break
            # Only what a packet lacks: pyftdi reads one USB transfer for it and returns,
            # where a larger request would wait for a second, empty one.
            self._rx += self._read(fm.PACKET_SIZE - len(self._rx))
        if len(self._rx) < fm.PACKET_SIZE:
            return None
        raw = bytes(self._rx[: fm.PACKET_SIZE])
        del self._rx[: fm.PACKET_SIZE]
        self._pending -= 1
        if self._pending <= 0:
            # Every command answered: anything more waiting would be read a tick late,
            # then ever later (a Falcon answering twice). A fault, never a lagging state.
            waiting = len(self._rx) + _read_cache(self._ftdi)
            if waiting:
                raise self._fail(
                    f"answers more often than it is asked ({waiting} bytes wait with every "
                    "command answered): its state would lag behind"
                )
            self._pending = 0
        return raw

    def _firmware_running(self, tries: int = 3) -> bool:
        """Whether the Falcon runs its firmware: it answers one of ``tries`` commands
        (forces zero). A command left unanswered is forgotten (the chip purged), so a
        firmware that starts after it answers the next one in step."""
        self._normal_mode()
        self._motor[:] = 0
        for _ in range(tries):
            self._send()
            raw = self._packet()
            if raw is not None:
                try:
                    fm.decode_state(raw)
                    return True
                except fm.FalconPacketError:
                    pass
            self._normal_mode()
        return False

    def _load_firmware(self, image: bytes) -> None:
        """Load ``image``, as libnifalcon does, in up to FIRMWARE_ATTEMPTS attempts: each
        resets the microcontroller into its bootloader and starts over. A chip gone from
        the bus (DeviceLostError) is not tried again."""
        failures = []
        for _ in range(FIRMWARE_ATTEMPTS):
            try:
                self._load_firmware_once(image)
                return
            except DeviceLostError:
                raise
            except DeviceError as exc:
                failures.append(str(exc).removeprefix(f"falcon {self.info.serial}: "))
        raise self._fail(
            f"firmware load failed {FIRMWARE_ATTEMPTS} times; the last: {failures[-1]}"
        )

    def _load_firmware_once(self, image: bytes) -> None:
        """The bootloader's handshake and the upload, each chunk's echo checked."""
        f = self._ftdi
        f.timeouts = (SETUP_TIMEOUT_MS, SETUP_TIMEOUT_MS)
        self._chip("purging", f.purge_buffers)
        self._chip("setting the latency timer", lambda: f.set_latency_timer(16))
        self._chip("setting the baud rate", lambda: f.set_baudrate(LOADER_BAUD))
        self._chip("setting the line", lambda: f.set_line_property(8, 1, "N"))
        self._chip("setting flow control", lambda: f.set_flowctrl(""))
        self._chip("setting RTS", lambda: f.set_rts(False))
        # A DTR pulse resets the Falcon's microcontroller into its bootloader.
        self._chip("setting DTR", lambda: f.set_dtr(False))
        self._chip("setting DTR", lambda: f.set_dtr(True))
        for _ in range(LOADER_HELLO_TRIES):
            self._write(LOADER_HELLO)
            if self._read_exact(len(LOADER_REPLY) + 1, 3).lstrip(b"\x00") == LOADER_REPLY:
                break
        else:
            raise self._fail("firmware load failed: its bootloader does not answer")
        self._chip("setting DTR", lambda: f.set_dtr(False))
        self._chip("setting the baud rate", lambda: f.set_baudrate(BOOT_BAUD))
        self._write(b"A")
        if self._read_exact(1, 3) != b"A":
            raise self._fail("firmware load failed: its bootloader did not synchronise")
        for at in range(0, len(image), FIRMWARE_CHUNK):
            chunk = image[at : at + FIRMWARE_CHUNK]
            self._write(chunk)
            echo = self._read_exact(len(chunk), 5)
            if echo != chunk:
                raise self._fail(
                    f"firmware load failed: byte {at + _first_difference(echo, chunk)} of "
                    f"{len(image)} came back wrong or not at all"
                )
        # How the bootloader knows the upload is over is not public (the emulator's module
        # docstring has three readings): the line stays quiet a while, then the firmware is
        # asked until it answers, the first command perhaps lost to it (libnifalcon asks its
        # I/O loop up to 10 times after a load).
        time.sleep(FIRMWARE_QUIET_S)
        if not self._firmware_running(FIRMWARE_PROBES):
            raise self._fail("firmware load failed: the firmware does not answer after loading")

    # -- the device -------------------------------------------------------------------------------

    def open(self, require_homed: bool = True) -> None:
        """Connect (loading the firmware if it runs none) and read it once. A Falcon not
        homed since power-up is refused unless ``require_homed`` is False (to home it:
        ``home``); until homed it gets zero force whatever it is sent."""
        image = read_firmware(self.firmware) if self.firmware is not None else None
        self._connect()
        try:
            if not self._firmware_running():
                if image is None:
                    raise self._fail(
                        "its firmware is not loaded (it was powered up since): name the "
                        "firmware file in the profile's device key 'firmware'"
                    )
                self._load_firmware(image)
            self._enabled = False
            self._counts = None
            self._recent.clear()
            self._p = np.zeros(3)
            st = DeviceState()
            self._read_state(st, check_homed=False)
            if require_homed and self.homed != fm.ALL_HOMED:
                raise self._fail(
                    "not homed since it was powered up: run hapticd calibrate (move the grip "
                    "all the way out, then push it straight in)"
                )
            self._send()
        except BaseException:
            self._disconnect()
            raise

    def _release(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def _disconnect(self) -> None:
        if self._ftdi is None:
            self._release()
            return
        with contextlib.suppress(Exception):
            self._motor[:] = 0
            self._enabled = False
            self._write(fm.encode_command((0, 0, 0), 0, False))
        with contextlib.suppress(Exception):
            self._ftdi.close()
        self._ftdi = None
        self._release()  # the chip closed first: then another process may have it

    def close(self) -> None:
        self._disconnect()

    def read_state(self, state: DeviceState) -> None:
        self._read_state(state, check_homed=True)

    def _read_state(self, state: DeviceState, check_homed: bool) -> None:
        if self._ftdi is None:
            raise self._fail("read from a closed device")
        if self._pending == 0:
            self._send()  # the firmware answers commands: ask with the last one again
        raw = self._packet()
        if raw is None:
            raise self._fail(
                f"stopped answering ({self.read_attempts} reads brought nothing): its power "
                "cut, or reset?",
                lost=True,
            )
        try:
            counts, homed, grip = fm.decode_state(raw)
        except fm.FalconPacketError as exc:
            raise self._fail("broken packet", exc) from exc
        c = counts  # plain ints: this runs every tick
        if self._counts is not None and homed == self.homed:
            step = max(abs(a - b) for a, b in zip(c, self._counts, strict=True))
            if step > MAX_ENCODER_STEP:
                raise self._fail(
                    f"impossible encoder jump of {step} counts between two packets "
                    f"({list(self._counts)} then {list(c)})"
                )
        if check_homed and homed != fm.ALL_HOMED and self.homed == fm.ALL_HOMED:
            raise self._fail(f"lost its homing (homed bits {homed:03b}): power cut?")
        self._counts, self.homed, self.grip = c, homed, grip
        t = self._clock()
        state.buttons = grip
        state.timestamp = t
        if homed != fm.ALL_HOMED:
            # The counts start wherever the arms were at power-on: no position yet.
            state.position[:] = 0.0
            state.velocity[:] = 0.0
            self._recent.clear()
            return
        try:
            p = fm.forward(fm.angles_from_counts(c), self._p)
        except fm.FalconKinematicsError as exc:
            raise self._fail(f"encoder counts {list(c)} are not a pose", exc) from exc
        state.position[:] = p
        # Velocity over the window, not the last tick: one encoder count (~40 um) in 1 ms
        # would be 0.04 m/s of noise; over 20 ms it is 2 mm/s.
        recent = self._recent
        while len(recent) > 1 and t - recent[1][0] >= VELOCITY_WINDOW_S:
            recent.popleft()
        if recent and t > recent[0][0]:
            state.velocity[:] = (p - recent[0][1]) / (t - recent[0][0])
        else:
            state.velocity[:] = 0.0
        recent.append((t, p))
        self._p = p

    def write_force(self, force: np.ndarray) -> None:
        if self._ftdi is None:
            raise self._fail("write to a closed device")
        check_force(force, self.info.max_force_n, f"falcon {self.info.serial}")
        if self._enabled and self.homed == fm.ALL_HOMED:
            try:
                motor = fm.motor_values(self._p, np.asarray(force, dtype=float))
            except fm.FalconKinematicsError as exc:
                raise self._fail("no motor values for this pose", exc) from exc
            self._motor[:] = motor
        else:
            self._motor[:] = 0
        self._send()

    def calibrated(self) -> bool:
        """Whether all three encoders are homed (an open Falcon always is)."""
        if self._ftdi is None:
            raise self._fail("not open")
        return self.homed == fm.ALL_HOMED

    def enable_forces(self, enabled: bool) -> None:
        self._enabled = bool(enabled)
        if not enabled:
            self._motor[:] = 0

    def home(self, timeout_s: float = 30.0, sleep: Callable[[float], None] = time.sleep) -> int:
        """Ask the firmware to home the encoders while the user moves the grip all the way
        out and straight back in; the homed bits (all three: 0b111) once done. DeviceError
        after ``timeout_s`` s of the device's clock."""
        start = self._clock()
        st = DeviceState()
        while self.homed != fm.ALL_HOMED:
            if self._clock() - start > timeout_s:
                raise self._fail(
                    f"not homed after {timeout_s:g} s (homed bits {self.homed:03b}): move "
                    "the grip all the way out, then push it straight in"
                )
            self._counts = None  # homing moves the counts' origin
            self._read_state(st, check_homed=False)
            self._motor[:] = 0
            self._send()
            sleep(0.001)
        return self.homed


def _serial(dev: Any) -> str | None:
    """The USB serial number of pyusb device ``dev``, or None when it cannot be read (no
    permission to open it: pyusb's USBError or ValueError)."""
    try:
        return dev.serial_number
    except Exception:
        return None


def _read_cache(ftdi: Any) -> int:
    """Bytes pyftdi has taken off the chip and not yet handed over: one USB transfer can
    bring more than the packet asked for, and pyftdi keeps the rest (in its read cache,
    which it has no public accessor for; 0 if a pyftdi has none)."""
    buf = getattr(ftdi, "_readbuffer", b"")
    return max(0, len(buf) - int(getattr(ftdi, "_readoffset", 0)))


def _first_difference(a: bytes, b: bytes) -> int:
    return next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), len(a))


def _status(index: int, usb_backend: Any) -> str:
    """What the Falcon at ``index`` runs: its firmware and homing, or why it cannot tell.
    It is opened, asked with zero force, and closed; nothing is loaded."""
    dev = FalconDevice(index=index, usb_backend=usb_backend)
    try:
        dev._connect()
        if not dev._firmware_running():
            return "firmware not loaded: hapticd loads the profile's 'firmware' file"
        dev._read_state(DeviceState(), check_homed=False)
        if dev.homed != fm.ALL_HOMED:
            return "firmware running, NOT homed: hapticd calibrate PROFILE"
        return "firmware running, homed"
    except DeviceInUseError as exc:
        return _in_use(exc)
    except DeviceError as exc:
        return f"cannot open it (in use? the udev rules?): {exc}"
    finally:
        dev._disconnect()


def _in_use(exc: DeviceInUseError) -> str:
    return f"in use (by pid {exc.pid})" if exc.pid is not None else "in use by another process"


def discover(usb_backend: Any = None) -> list[dict[str, Any]]:
    """The attached Falcons (serial number, index, firmware and homing), or why pyusb and
    libusb cannot look. A Falcon another process holds is asked nothing, not even its
    serial number: it is listed as in use, with the holder's pid."""
    try:
        found = find_falcons(usb_backend)
    except DeviceError as exc:
        return [{"backend": "falcon", "problem": str(exc)}]
    listed = []
    for i, dev in enumerate(found):
        try:
            lock = lock_usb_device(dev, f"falcon at index {i}")
        except DeviceInUseError as exc:
            listed.append(f"index {i}: {_in_use(exc)}, not asked")
            continue
        try:
            serial = _serial(dev) or "no readable serial"
        finally:
            lock.release()  # _status takes it again, as every open does
        listed.append(f"{serial} (index {i}, {_status(i, usb_backend)})")
    return [{"backend": "falcon", "model": "Novint Falcon", "found": listed}]


def preflight(firmware: str | None = None, **_: Any) -> None:
    """Before a run: pyftdi is importable and the named firmware file is one (DeviceError
    saying which and why)."""
    try:
        importlib.import_module("pyftdi.ftdi")
    except ImportError as exc:
        raise DeviceError("the falcon backend needs pyftdi: pip install pyftdi") from exc
    if firmware is not None:
        read_firmware(firmware)


def calibrate(
    firmware: str | None = None,
    serial_number: str | None = None,
    index: int = 0,
    usb_backend: Any = None,
    clock: Callable[[], float] | None = None,
    timeout_s: float = 30.0,
    **_: Any,
) -> dict[str, Any]:
    """Home one Falcon (loading its firmware first if it runs none): the user moves the
    grip all the way out, then straight in. Returns model, serial and whether it was
    homed before; DeviceError on failure."""
    dev = FalconDevice(
        firmware=firmware,
        serial_number=serial_number,
        index=index,
        usb_backend=usb_backend,
        clock=clock,
    )
    dev.open(require_homed=False)
    try:
        was = dev.homed == fm.ALL_HOMED
        if not was:
            dev.home(timeout_s)
    finally:
        dev.close()
    return {"model": dev.info.model, "serial": dev.info.serial, "was_calibrated": was}
