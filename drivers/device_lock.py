"""Who holds a USB device: an advisory lock on its device node, taken before anything is sent.

Linux does not check interface claims for vendor control requests, so a second process
that opens a device a run holds (``hapticd devices``, a second run) can disturb it before
claiming the interface fails. Every hapticd process that opens a USB device first takes
an exclusive ``flock`` on its node, /dev/bus/usb/BBB/DDD, without blocking, and keeps it
while the device is open; one that finds it taken sends nothing to the device.

The node, not a file in a runtime directory: every user who may open the device can open
its node (the udev rules give both), so a lab user's probe sees the lock a service user's
run holds, and there is no directory to plant or check. The kernel drops the lock with
the process, so a killed run leaves no stale lock. Opening the node sends nothing to the
device. No node (not Linux, or an emulated bus): nothing to lock, and nothing is.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path
from typing import Any

from hapticd_drivers.base import DeviceError

# Where usbfs lists the devices (a seam for the tests).
USB_NODES = Path("/dev/bus/usb")
PROC_LOCKS = Path("/proc/locks")


class DeviceInUseError(DeviceError):
    """Another process holds the device; nothing was sent to it. ``pid``: the holder's, or
    None when the system does not say."""

    def __init__(self, message: str, pid: int | None) -> None:
        super().__init__(message)
        self.pid = pid


def usb_node(dev: Any, root: Path | None = None) -> Path:
    """The usbfs node of pyusb device ``dev`` (its ``bus`` and ``address``)."""
    return (root or USB_NODES) / f"{int(dev.bus):03d}" / f"{int(dev.address):03d}"


def holder_pid(node: Path) -> int | None:
    """The pid that holds a ``flock`` on ``node`` (from /proc/locks), or None."""
    try:
        st = os.stat(node)
        with open(PROC_LOCKS, encoding="ascii", errors="replace") as f:
            lines = f.read(1 << 20).splitlines()
    except OSError:
        return None
    want = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    for line in lines:
        # "1: FLOCK  ADVISORY  WRITE 1234 fe:00:2146324 0 EOF" ("->" marks a waiter)
        parts = line.split()
        if len(parts) >= 6 and "->" not in parts and parts[1] == "FLOCK" and parts[5] == want:
            with contextlib.suppress(ValueError):
                return int(parts[4])
    return None


class UsbDeviceLock:
    """The exclusive lock on one USB device's node, held until ``release``."""

    def __init__(self, node: Path, fd: int | None) -> None:
        self.node, self._fd = node, fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock
            self._fd = None


def lock_usb_device(dev: Any, what: str, root: Path | None = None) -> UsbDeviceLock:
    """Take the lock on pyusb device ``dev`` without waiting. DeviceInUseError naming
    ``what`` and the holder's pid when another process holds it. A node that is absent or
    that this user cannot open locks nothing (libusb then cannot open it either)."""
    node = usb_node(dev, root)
    try:
        fd = os.open(node, os.O_RDONLY | os.O_CLOEXEC | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:
        return UsbDeviceLock(node, None)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        pid = holder_pid(node)
        by = f"by pid {pid}" if pid is not None else "by another process"
        raise DeviceInUseError(
            f"{what}: in use ({by}, which holds {node}); nothing was sent to it", pid
        ) from None
    except OSError:
        os.close(fd)
        return UsbDeviceLock(node, None)
    return UsbDeviceLock(node, fd)


def pick_device(
    present: list[Any],
    index: int,
    serial_number: str | None,
    serial_of: Any,
    what: str,
    root: Path | None = None,
) -> tuple[Any, UsbDeviceLock] | None:
    """The ``index``-th of the pyusb devices ``present`` (of those whose serial number is
    ``serial_number``, when given), locked; None when there is none. Each device is locked
    before its serial number is read (``serial_of(dev)``), so a device another process
    holds is asked nothing: it is skipped, or, picked by index alone, DeviceInUseError. None
    found and some held: DeviceInUseError naming their holders (the one wanted may be
    among them)."""
    if serial_number is None:
        if len(present) <= index:
            return None
        return present[index], lock_usb_device(present[index], what, root)
    matches = 0
    held: list[DeviceInUseError] = []
    for dev in present:
        try:
            lock = lock_usb_device(dev, what, root)
        except DeviceInUseError as exc:
            held.append(exc)  # its serial number is not asked for
            continue
        if serial_of(dev) == serial_number:
            if matches == index:
                return dev, lock
            matches += 1
        lock.release()
    if held:
        pids = ", ".join(f"pid {e.pid}" if e.pid is not None else "another process" for e in held)
        raise DeviceInUseError(
            f"{what}: serial number {serial_number} is not among the free devices, and "
            f"{len(held)} in use ({pids}) were not asked theirs",
            held[0].pid,
        )
    return None
