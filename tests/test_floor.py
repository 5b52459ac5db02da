"""The servo floor outside the renderer: the frame's item views, the device bank's reads
and writes for every finger count (the record's layout moves its fields), and the loop's
per-finger statistics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hapticd_drivers import DeviceError
from hapticd_drivers.replay import ReplayDevice

from hapticd.loop.device_bank import DeviceBank
from hapticd.physics.frame import Frame, item_view


@pytest.mark.parametrize("n_fingers", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("n_actuators", [1, 2, 3])
def test_item_views_store_what_numpy_stores_for_every_layout(n_fingers, n_actuators):
    """A memoryview where Python takes the field's format, the array where it does not
    (an unaligned field): either way the record holds the same bytes as a numpy store."""
    a, b = Frame(n_fingers, n_actuators), Frame(n_fingers, n_actuators)
    rng = np.random.default_rng(n_fingers * 10 + n_actuators)
    for name in ("device_pos", "device_vel"):
        view, arr = item_view(a.get(name)), b.get(name)
        for i in range(n_fingers):
            for j in range(3):
                x = float(rng.normal()) * 10.0 ** int(rng.integers(-300, 300))
                view[i, j] = x
                arr[i, j] = x
    view, arr = item_view(a.buttons), b.buttons
    for i in range(n_fingers):
        view[i] = arr[i] = int(rng.integers(0, 2**32))
    for name, value in (("t", 0.1 + 0.2), ("t_wall", 1e-7), ("compute_s", 3e-5), ("fault", 1)):
        item_view(a.get(name))[()] = value
        b.get(name)[()] = value
    assert a.record.tobytes() == b.record.tobytes()
    # Every field of a frame is aligned: a memoryview. An unaligned array (a packed record's
    # field after a byte) is given back as it is, and a store through it is numpy's.
    assert {type(item_view(Frame(f, 1).buttons)) for f in range(1, 4)} == {memoryview}
    packed = np.zeros((), dtype=[("flag", "u1"), ("buttons", "<u4", (2,))])
    unaligned = packed["buttons"]
    assert not unaligned.flags.aligned and item_view(unaligned) is unaligned


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def replay(clock: Clock, serial: str, offset: float) -> ReplayDevice:
    t = np.linspace(0.0, 1.0, 11)
    x = np.stack([offset + 0.01 * t, -0.02 * t**2, 0.003 * np.sin(3 * t)], axis=1)
    return ReplayDevice(t, x, clock=clock, serial=serial, buttons=np.arange(11) % 4)


@pytest.mark.parametrize("n_fingers", [1, 2, 3])
def test_the_bank_reads_and_writes_each_finger_bit_for_bit(n_fingers):
    """Positions, velocities and buttons in the frame are the devices' own, whatever the
    record's layout; forces written are the frame's rows; a swapped device is used."""
    clock = Clock()
    devices = [replay(clock, f"d{i}", 0.01 * i) for i in range(n_fingers)]
    faults: list = []
    bank = DeviceBank(
        devices, reconnect=False, on_fault=lambda *a: faults.append(a), on_event=print
    )
    bank.open()
    frame = Frame(n_fingers, n_fingers)
    for k in range(40):
        clock.t = t = k * 0.031
        bank.read(frame, k, t)
        for i, dev in enumerate(devices):
            pos, vel = dev.path.at(t)  # what the replay device reports at t
            assert frame.device_pos[i].tobytes() == np.array(pos, dtype=float).tobytes()
            assert frame.device_vel[i].tobytes() == np.array(vel, dtype=float).tobytes()
            assert int(frame.buttons[i]) == dev.path.buttons_at(t)
        frame.device_force[:] = np.linspace(-1.0, 1.0, 3 * n_fingers).reshape(-1, 3) * k / 40
        bank.write(frame, k, t)
        for i, dev in enumerate(devices):
            assert dev.last_force.tobytes() == frame.device_force[i].tobytes()
    assert faults == []
    # A device swapped in after the first tick is the one read and written.
    other = replay(clock, "other", 0.05)
    other.open()
    other.enable_forces(True)
    bank.devices[0] = other
    bank.read(frame, 40, 1.0)
    assert frame.device_pos[0].tolist() == pytest.approx([0.06, -0.02, 0.003 * math.sin(3.0)])
    bank.write(frame, 40, 1.0)
    assert other.last_force.tobytes() == frame.device_force[0].tobytes()


def test_a_new_frame_is_filled_not_the_old_one():
    clock = Clock()
    bank = DeviceBank(
        [replay(clock, "a", 0.0), replay(clock, "b", 0.01)],
        reconnect=False,
        on_fault=lambda *a: None,
        on_event=print,
    )
    bank.open()
    old, new = Frame(2, 2), Frame(2, 2)
    clock.t = 0.5
    bank.read(old, 0, 0.5)
    clock.t = 0.7
    bank.read(new, 1, 0.7)
    assert old.device_pos[0, 0] == pytest.approx(0.005)
    assert new.device_pos[0, 0] == pytest.approx(0.007)
    new.device_force[0] = (0.5, 0.0, 0.0)
    bank.write(new, 1, 0.7)
    assert bank.devices[0].last_force.tolist() == [0.5, 0.0, 0.0]


def test_a_lost_device_keeps_its_place_and_the_others_are_read():
    clock = Clock()
    devices = [replay(clock, "a", 0.0), replay(clock, "b", 0.01)]
    events: list = []
    bank = DeviceBank(devices, reconnect=True, on_fault=lambda *a: events.append(a), on_event=print)
    bank.open()
    frame = Frame(2, 2)
    clock.t = 0.2
    bank.read(frame, 0, 0.2)
    kept = frame.device_pos[0].copy()

    def unplugged(st):
        raise DeviceError("unplugged")

    devices[0].read_state = unplugged
    clock.t = 0.3
    bank.read(frame, 1, 0.3)
    assert bank.lost[0] == 0.3 and events and events[0][3] == "device"
    assert frame.device_pos[0].tolist() == kept.tolist() and not frame.device_vel[0].any()
    assert frame.device_pos[1, 0] == pytest.approx(0.013)
    clock.t = 0.4
    bank.read(frame, 2, 0.4)  # the lost one is skipped, the other read
    assert frame.device_pos[1, 0] == pytest.approx(0.014)
