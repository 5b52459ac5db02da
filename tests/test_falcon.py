"""The falcon backend: its packet codec and kinematics, and the backend through the
emulated FTDI chip under pyusb (firmware load, homing, LEDs, grip, faults)."""

import io
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from hapticd_drivers import (
    DeviceError,
    DeviceLostError,
    DeviceState,
    models,
    open_device,
    registry,
)
from hapticd_drivers import falcon_emulator as fe
from hapticd_drivers import falcon_model as fm
from hapticd_drivers.falcon_emulator import EmulatedFalconBackend, FalconEmulator
from hapticd_drivers.trajectory import Trajectory
from hypothesis import assume, given
from hypothesis import strategies as st

from tests.conftest import GRASP_PROFILE, ROOT, AtTick
from tests.test_backends import Clock, run

RADIUS = models.by_name("Falcon").workspace_radius_m
TIMES = np.array([0.0, 0.5, 1.0])
POS = np.array([[0.0, 0.0, 0.0], [0.02, 0.01, -0.01], [0.03, -0.01, 0.02]])

coord = st.floats(-RADIUS, RADIUS, allow_nan=False)


def in_workspace(p) -> bool:
    return float(np.linalg.norm(p)) <= RADIUS


# -- kinematics -------------------------------------------------------------------------------


@given(coord, coord, coord)
def test_forward_inverts_inverse_across_the_workspace(x, y, z):
    p = np.array([x, y, z])
    assume(in_workspace(p))
    theta = fm.inverse(p)
    np.testing.assert_allclose(fm.forward(theta), p, atol=1e-9)
    # from a far start too, as after a glitch
    np.testing.assert_allclose(fm.forward(theta, guess=-p), p, atol=1e-9)


@given(coord, coord, coord)
def test_each_leg_satisfies_stampers_loop_equations(x, y, z):
    p = np.array([x, y, z])
    assume(in_workspace(p))
    leg = fm.leg_coordinates(p)
    ang = fm.leg_angles(p)
    th1, th2, th3 = ang[:, 0], ang[:, 1], ang[:, 2]
    length = fm.D + fm.E + fm.B * np.sin(th3)
    np.testing.assert_allclose(
        leg[:, 0], fm.A * np.cos(th1) - fm.C + length * np.cos(th2), atol=1e-12
    )
    np.testing.assert_allclose(leg[:, 1], fm.B * np.cos(th3) - fm.F, atol=1e-12)
    np.testing.assert_allclose(leg[:, 2], fm.A * np.sin(th1) + length * np.sin(th2), atol=1e-12)


@given(coord, coord, coord)
def test_the_jacobian_is_the_derivative_of_the_inverse_kinematics(x, y, z):
    p = np.array([x, y, z])
    assume(in_workspace(p))
    h = 1e-7
    numeric = np.column_stack(
        [(fm.inverse(p + h * e) - fm.inverse(p - h * e)) / (2 * h) for e in np.eye(3)]
    )
    np.testing.assert_allclose(fm.joint_jacobian(p), numeric, rtol=1e-5, atol=1e-4)


# libnifalcon's geometry as its FalconGeometry.h publishes it (m, rad), typed in here
# independently of falcon_model, and its inverse kinematics in the expanded form of its
# FalconKinematicStamper.cpp (IK): the constants and our rearranged solution are both
# checked against them.
LIB = dict(a=0.060, b=0.1025, c=0.01443, d=0.01125, e=0.01125, f=-0.025, r=0.0400, s=-0.02309)
LIB_PHI = [np.pi / 2 + np.pi / 12, -np.pi / 6 + np.pi / 12, -5 * np.pi / 6 + np.pi / 12]


def libnifalcon_thighs(world):
    a, b, c, d, e, f, r, s = (LIB[k] for k in "abcdefrs")
    out = []
    for phi in LIB_PHI:
        rot = np.array([[np.cos(phi), np.sin(phi), 0], [-np.sin(phi), np.cos(phi), 0], [0, 0, 1]])
        pu, pv, pw = rot @ world + np.array([-r, -s, 0.0])
        th3 = np.arccos((pv + f) / b)
        s3 = np.sin(th3)
        common = pw**2 + pu**2 + a**2 + c**2 - d**2 - e**2 - b**2 * s3**2
        common -= 2 * b * e * s3 + 2 * b * d * s3 + 2 * d * e
        l0 = common + 2 * c * pu - 2 * a * pu - 2 * a * c
        l1 = -4 * a * pw
        l2 = common + 2 * c * pu + 2 * a * pu + 2 * a * c
        out.append(2 * np.arctan((-l1 - np.sqrt(l1 * l1 - 4 * l0 * l2)) / (2 * l2)))
    return np.array(out)


@given(coord, coord, coord)
def test_the_inverse_kinematics_are_libnifalcons(x, y, z):
    p = np.array([x, y, z])
    assume(in_workspace(p))
    world = p + np.array(fm.CENTER)  # libnifalcon's frame
    np.testing.assert_allclose(fm.inverse(p), libnifalcon_thighs(world), atol=1e-12)


def test_the_encoder_scale_is_libnifalcons():
    # getTheta: degrees = (shaft diameter pi / (slots 4)) counts / (pi arm diameter / 360) + 35
    deg_per_count = (0.01425 * np.pi / (320 * 4)) / (np.pi * 0.110 / 360.0)
    np.testing.assert_allclose(
        fm.angles_from_counts([1000, 0, -1000]),
        np.radians([1000 * deg_per_count + 35, 35, -1000 * deg_per_count + 35]),
        rtol=1e-12,
    )


def test_the_legs_are_symmetric_on_the_axis():
    # libnifalcon's three legs 120 degrees apart: on the z axis all thighs agree, and
    # further out (z toward the user) the thighs turn one way.
    a = fm.inverse(np.array([0.0, 0.0, -0.02]))
    b = fm.inverse(np.array([0.0, 0.0, 0.02]))
    np.testing.assert_allclose(a, a[0], atol=1e-12)
    np.testing.assert_allclose(b, b[0], atol=1e-12)
    assert b[0] > a[0]


@given(coord, coord, coord, st.floats(0.01, 8.0), st.integers(0, 2))
def test_motor_values_render_the_force_within_their_limit(x, y, z, magnitude, axis):
    p = np.array([x, y, z])
    assume(in_workspace(p))
    f = np.zeros(3)
    f[axis] = magnitude
    motor = fm.motor_values(p, f)
    assert np.abs(motor).max() <= fm.MOTOR_LIMIT
    produced = fm.force_from_motor(p, motor)
    if np.abs(motor).max() < fm.MOTOR_LIMIT:
        np.testing.assert_allclose(produced, f, atol=0.01)  # one motor unit is 1e-4 N m
    else:  # saturated: scaled down together, the direction kept
        assert np.dot(produced, f) / (np.linalg.norm(produced) * magnitude) > 0.999


def test_encoder_counts_round_trip_within_one_count():
    theta = np.array([-0.3, 0.2, 1.1])
    back = fm.angles_from_counts(fm.counts_from_angles(theta))
    assert np.abs(back - theta).max() <= fm.RAD_PER_COUNT / 2 + 1e-15


def test_a_position_out_of_reach_is_refused():
    with pytest.raises(fm.FalconKinematicsError, match="reach"):
        fm.inverse(np.array([0.0, 0.0, 0.2]))


# -- the codec --------------------------------------------------------------------------------

words = st.integers(-32768, 32767)
motors = st.integers(-fm.MOTOR_LIMIT, fm.MOTOR_LIMIT)


@given(st.tuples(motors, motors, motors), st.integers(0, 15), st.booleans())
def test_command_packets_round_trip(motor, leds, homing):
    raw = fm.encode_command(motor, leds, homing)
    assert len(raw) == 16 and raw[:1] == b"<" and raw[-1:] == b">"
    assert all(0x41 <= b <= 0x50 for b in raw[1:13])
    assert fm.decode_command(raw) == (motor, leds & 0xE, homing)


@given(st.tuples(words, words, words), st.integers(0, 7), st.integers(0, 15))
def test_state_packets_round_trip(encoders, homed, grip):
    assert fm.decode_state(fm.encode_state(encoders, homed, grip)) == (encoders, homed, grip)


def test_the_nibbles_are_offset_by_0x41_least_significant_first():
    raw = fm.encode_state((0x1234, -1, 0), 0b101, 0b0011)
    assert raw[1:5] == bytes([0x41 + 4, 0x41 + 3, 0x41 + 2, 0x41 + 1])
    assert raw[5:9] == bytes([0x41 + 0xF] * 4)
    assert raw[13] == 0x41 + 0x53


BROKEN = {
    "short": (lambda raw: raw[:15], "15 bytes"),
    "no start": (lambda raw: b"x" + raw[1:], "frame"),
    "no end": (lambda raw: raw[:15] + b"<", "frame"),
    "not a nibble": (lambda raw: raw[:3] + b"\x00" + raw[4:], "byte 3"),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_packets_are_refused_saying_what_is_wrong(case):
    breaking, message = BROKEN[case]
    raw = fm.encode_state((10, -20, 30), 7, 0)
    with pytest.raises(fm.FalconPacketError, match=message):
        fm.decode_state(breaking(raw))


def test_a_motor_value_beyond_the_limit_never_becomes_a_packet():
    with pytest.raises(ValueError, match="4096"):
        fm.encode_command((fm.MOTOR_LIMIT + 1, 0, 0), 0, False)


# -- the backend through the emulated chip ---------------------------------------------------


def falcon(clock, firmware_loaded=True, homed=True, **kw):
    emu = FalconEmulator(
        Trajectory(TIMES, POS, "emu"),
        clock,
        serial="EMU-1",
        firmware_loaded=firmware_loaded,
        homed=homed,
    )
    dev = open_device(
        "falcon", serial_number="EMU-1", usb_backend=EmulatedFalconBackend([emu]), clock=clock, **kw
    )
    return dev, emu


def test_renders_the_force_and_follows_the_path():
    clock = Clock()
    dev, emu = falcon(clock)
    dev.open()
    try:
        assert emu.leds == fm.LED_BLUE  # homed, forces off
        dev.enable_forces(True)
        st_ = run(dev, clock, 600)
        assert emu.leds == fm.LED_GREEN
        np.testing.assert_allclose(emu.end_effector_force(), [1.0, -2.0, 3.0], atol=0.01)
        want, vel = Trajectory(TIMES, POS, "p").at(clock.t)
        np.testing.assert_allclose(st_.position, want, atol=1e-4)  # ~40 um per count
        np.testing.assert_allclose(st_.velocity, vel, atol=0.005)  # over 20 ms
        dev.enable_forces(False)
        run(dev, clock, 1, start=600)
        np.testing.assert_array_equal(emu.motor, 0)
    finally:
        dev.close()
    np.testing.assert_array_equal(emu.motor, 0)
    assert emu.leds == 0


def test_a_path_beyond_the_reach_holds_the_emulated_arms_at_their_stops():
    clock = Clock()
    far = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.2], [0.0, 0.0, 0.2]])  # 20 cm out
    emu = FalconEmulator(Trajectory(TIMES, far, "far"), clock, "EMU-1", True, True)
    dev = open_device(
        "falcon", serial_number="EMU-1", usb_backend=EmulatedFalconBackend([emu]), clock=clock
    )
    dev.open()
    st_ = run(dev, clock, 1000, force=(0.0, 0.0, 0.0))
    assert 0.05 < st_.position[2] < 0.2  # the last pose the arms reached, no error
    dev.close()


@pytest.mark.parametrize("polls", [0, 1, 2])
def test_an_answer_the_chip_holds_is_waited_for_a_few_polls(polls):
    clock = Clock()
    dev, emu = falcon(clock)
    emu.latency_polls = polls
    dev.open()
    dev.enable_forces(True)
    run(dev, clock, 50)
    np.testing.assert_allclose(emu.end_effector_force(), [1.0, -2.0, 3.0], atol=0.01)
    dev.close()


def test_each_tick_asks_for_one_state_packet_in_one_usb_transfer():
    clock = Clock()
    dev, emu = falcon(clock)
    emu.latency_polls = 0  # the answer is there by the time it is asked for
    dev.open()
    dev.enable_forces(True)
    before = emu.in_transfers
    run(dev, clock, 100)
    # One IN transfer a tick: asking for more than the 16 bytes would add an empty
    # transfer, which on the chip waits for its latency timer.
    assert emu.in_transfers - before == 100
    dev.close()


@pytest.mark.timing("a stalled USB transfer is bounded by its wall-clock timeout")
def test_a_stalled_read_is_a_lost_falcon_within_the_watchdog_and_its_force_goes_to_zero():
    clock = Clock()
    dev, emu = falcon(clock)
    dev.open()
    dev.enable_forces(True)
    run(dev, clock, 50)
    assert emu.motor.any()
    emu.stall_in = True
    t0 = time.perf_counter()
    with pytest.raises(DeviceLostError, match="falcon EMU-1: read stalled"):
        run(dev, clock, 1, start=50)
    elapsed = time.perf_counter() - t0
    # The loop's watchdog is 100 ms: the whole failed read ends well within it (each
    # transfer given a few ms, not pyftdi's default 5 s).
    assert elapsed < 0.1, f"the stalled read took {elapsed * 1000:.0f} ms"
    assert emu.in_timeout_max_ms <= 10
    dev.close()  # what the loop does with a lost device: the OUT side still works
    np.testing.assert_array_equal(emu.motor, 0)


def test_a_falcon_answering_twice_per_command_is_a_fault_not_a_lagging_state():
    clock = Clock()
    dev, emu = falcon(clock)
    dev.open()
    dev.enable_forces(True)
    run(dev, clock, 10)
    emu.answers_per_command = 2
    st_ = DeviceState()
    want = None
    with pytest.raises(DeviceError, match="answers more often than it is asked") as err:
        for k in range(10, 200):
            clock.t = k * 1e-3
            dev.read_state(st_)
            # Until the fault, what is read is the answer to the last command, never an
            # older one (within one tick of the path: ~0.1 mm).
            want, _ = Trajectory(TIMES, POS, "p").at(clock.t)
            np.testing.assert_allclose(st_.position, want, atol=2e-4)
            dev.write_force(np.array([1.0, -2.0, 3.0]))
    assert not isinstance(err.value, DeviceLostError)
    assert clock.t < 0.015  # found within a few ticks, not seconds later
    dev.close()
    np.testing.assert_array_equal(emu.motor, 0)


def test_the_grip_buttons_are_the_device_buttons():
    clock = Clock()
    dev, emu = falcon(clock)
    dev.open()
    emu.grip = 0b1010
    assert run(dev, clock, 2).buttons == 0b1010
    dev.close()


FAULTS = {  # fault: (inject, message, a lost device rather than one answering wrongly)
    "broken frame": (lambda emu: setattr(emu, "corrupt_next", 1), "broken packet", False),
    "encoder jump": (lambda emu: setattr(emu, "jump_next", 1), "impossible encoder jump", False),
    "silence": (lambda emu: setattr(emu, "silent", True), "stopped answering", True),
    "unplug": (lambda emu: emu.unplug(), "unplugged", True),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_a_device_fault_is_a_clear_error_naming_the_falcon(fault):
    clock = Clock()
    dev, emu = falcon(clock)
    dev.open()
    dev.enable_forces(True)
    run(dev, clock, 20)
    inject, message, lost = FAULTS[fault]
    inject(emu)
    with pytest.raises(DeviceError, match=rf"falcon EMU-1: .*{message}") as err:
        run(dev, clock, 3, start=20)
    assert isinstance(err.value, DeviceLostError) == lost
    dev.close()


@pytest.mark.parametrize("outside_homing", [False, True])
def test_a_homed_falcon_opens_and_renders_whether_its_homed_bits_need_homing_mode(
    outside_homing,
):
    # libnifalcon's header: the homed bits are reported only in homing mode (False); a
    # real Falcon may report them either way (True). The backend works under both.
    clock = Clock()
    emu = FalconEmulator(
        Trajectory(TIMES, POS, "emu"),
        clock,
        "EMU-1",
        firmware_loaded=True,
        homed=True,
        homed_bits_outside_homing=outside_homing,
    )
    dev = open_device(
        "falcon", serial_number="EMU-1", usb_backend=EmulatedFalconBackend([emu]), clock=clock
    )
    dev.open()
    dev.enable_forces(True)
    run(dev, clock, 300)
    assert dev.calibrated() and emu.leds == fm.LED_GREEN
    np.testing.assert_allclose(emu.end_effector_force(), [1.0, -2.0, 3.0], atol=0.01)
    dev.close()
    np.testing.assert_array_equal(emu.motor, 0)


def test_a_falcon_not_homed_is_refused_and_never_gets_force():
    clock = Clock()
    dev, emu = falcon(clock, homed=False)
    with pytest.raises(DeviceError, match=r"not homed.*hapticd calibrate"):
        dev.open()
    assert emu.leds == 0 and not emu.motor.any()
    assert emu.commands > 0  # it was asked, and answered


def test_homing_while_the_user_sweeps_the_grip_then_the_falcon_opens():
    from hapticd_drivers.falcon_backend import FalconDevice

    clock = Clock()
    _, emu = falcon(clock, homed=False)
    dev = FalconDevice(serial_number="EMU-1", usb_backend=EmulatedFalconBackend([emu]), clock=clock)
    dev.open(require_homed=False)
    assert emu.leds == fm.LED_RED
    dev.enable_forces(True)
    dev.write_force(np.array([1.0, 0.0, 0.0]))  # not homed: zero reaches the motors
    assert not emu.motor.any()

    def sleep(s):
        clock.t += s

    assert dev.home(timeout_s=10.0, sleep=sleep) == fm.ALL_HOMED
    assert clock.t < 3.5  # homed within the user's sweep
    dev.close()
    clock.t = 4.0  # the user's sweep is over: the grip follows the path again
    dev.open()  # now it opens, and the encoders read absolute angles
    st_ = run(dev, clock, 1, start=4001)
    want, _ = Trajectory(TIMES, POS, "p").at(clock.t)
    np.testing.assert_allclose(st_.position, want, atol=1e-4)
    dev.close()


def test_homing_that_never_completes_times_out():
    clock = Clock()
    _, emu = falcon(clock, homed=False)
    emu.HOMING_SWEEP = ((0.0, 0.0), (3.0, 0.0))  # a user who does not move the grip
    from hapticd_drivers.falcon_backend import FalconDevice

    dev = FalconDevice(serial_number="EMU-1", usb_backend=EmulatedFalconBackend([emu]), clock=clock)
    dev.open(require_homed=False)

    def sleep(s):
        clock.t += s

    with pytest.raises(DeviceError, match="not homed after 2 s"):
        dev.home(timeout_s=2.0, sleep=sleep)
    dev.close()


def firmware_file(tmp_path, size=7324):
    path = tmp_path / "falcon.bin"
    path.write_bytes(bytes((i * 7) & 0xFF for i in range(size)))
    return path


def test_the_firmware_is_loaded_through_the_bootloader(tmp_path):
    clock = Clock()
    path = firmware_file(tmp_path)
    dev, emu = falcon(clock, firmware_loaded=False, firmware=str(path))
    dev.open()
    assert emu.state == "run" and bytes(emu.image) == path.read_bytes()
    dev.enable_forces(True)
    run(dev, clock, 50)
    np.testing.assert_allclose(emu.end_effector_force(), [1.0, -2.0, 3.0], atol=0.01)
    dev.close()


def test_a_falcon_without_firmware_and_no_file_says_to_name_one():
    dev, emu = falcon(Clock(), firmware_loaded=False)
    with pytest.raises(DeviceError, match=r"firmware is not loaded.*'firmware'"):
        dev.open()
    assert emu.state == "boot"


@pytest.mark.parametrize(
    ("size", "message"), [(None, "cannot read it"), (100, "100 bytes, expected")]
)
def test_a_missing_or_wrong_sized_firmware_file_is_refused_before_the_falcon(
    tmp_path, size, message
):
    path = tmp_path / "missing.bin" if size is None else firmware_file(tmp_path, size)
    dev, emu = falcon(Clock(), firmware_loaded=False, firmware=str(path))
    with pytest.raises(DeviceError, match=message):
        dev.open()
    assert emu.state == "boot" and not emu.image


@pytest.mark.timing("a file that never ends or a FIFO without writer would hang the read")
@pytest.mark.parametrize("kind", ["dev-zero", "fifo", "directory"])
def test_a_firmware_that_is_not_a_regular_file_is_refused_without_reading_it(tmp_path, kind):
    if kind == "dev-zero":
        path = "/dev/zero"
    elif kind == "fifo":
        path = str(tmp_path / "firmware.fifo")
        os.mkfifo(path)
    else:
        path = str(tmp_path)
    # In a child process with a deadline: a read that hangs (a FIFO with no writer) or
    # never ends (/dev/zero) fails the test there instead of hanging the suite.
    code = (
        "import sys\n"
        "from hapticd_drivers import DeviceError\n"
        "from hapticd_drivers.falcon_backend import preflight\n"
        "try:\n"
        "    preflight(firmware=sys.argv[1])\n"
        "except DeviceError as exc:\n"
        "    print(exc)\n"
    )
    try:
        done = subprocess.run(
            [sys.executable, "-c", code, path], capture_output=True, text=True, timeout=10
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"reading {path} as the firmware did not end within 10 s")
    assert done.returncode == 0, done.stderr
    assert f"falcon firmware {path} (device key 'firmware'): not a regular file" in done.stdout


def test_a_firmware_echo_that_differs_is_a_failed_load(tmp_path):
    dev, emu = falcon(Clock(), firmware_loaded=False, firmware=str(firmware_file(tmp_path)))
    emu.corrupt_echo = 100  # every attempt
    with pytest.raises(DeviceError, match=r"load failed 10 times.*: byte 0 of 7324 came back"):
        dev.open()
    assert emu.loads == 10


FIRMWARE_READINGS = [
    pytest.param({"firmware_start": "framing"}, id="framing"),
    pytest.param({"firmware_start": "length", "image_size": 7324}, id="length"),
    pytest.param(
        {"firmware_start": "quiet", "quiet_s": 0.02},
        id="quiet",
        marks=pytest.mark.timing("the bootloader's quiet line is timed in real time"),
    ),
]


def _loads_and_renders(tmp_path, uploads=1, **emulator):
    """Open an emulated Falcon (``emulator``: its options) that runs no firmware with a
    firmware file: the image is loaded in ``uploads`` uploads and the force rendered."""
    clock = Clock()
    path = firmware_file(tmp_path)
    emu = FalconEmulator(Trajectory(TIMES, POS, "emu"), clock, "EMU-1", homed=True, **emulator)
    dev = open_device(
        "falcon", serial_number="EMU-1", usb_backend=EmulatedFalconBackend([emu]),
        clock=clock, firmware=str(path),
    )  # fmt: skip
    dev.open()
    try:
        assert emu.state == "run" and bytes(emu.image) == path.read_bytes()
        assert emu.loads == uploads
        dev.enable_forces(True)
        run(dev, clock, 50)
        np.testing.assert_allclose(emu.end_effector_force(), [1.0, -2.0, 3.0], atol=0.01)
    finally:
        dev.close()


@pytest.mark.parametrize("reading", FIRMWARE_READINGS)
def test_the_firmware_loads_however_the_bootloader_ends_the_upload(tmp_path, reading):
    """Nothing public says how the Falcon's bootloader knows the upload is over; the
    backend loads the firmware under each reading the emulator offers."""
    _loads_and_renders(tmp_path, **reading)


def _bootloaded(emu, image):
    """Drive the emulated microcontroller through the handshake and ``image``, by hand."""
    emu.control(fe.SIO_MODEM_CTRL, 0x100, 0)
    emu.control(fe.SIO_MODEM_CTRL, 0x101, 0)  # the DTR pulse: the bootloader
    emu.baud = fe.LOADER_BAUD
    emu.write(fe.LOADER_HELLO)
    emu.baud = fe.BOOT_BAUD
    emu.write(b"A")
    emu.write(image)


@pytest.mark.parametrize("start", ["framing", "quiet"])
def test_the_chips_baud_setting_alone_never_starts_the_firmware(start):
    """The microcontroller cannot see what the host sets in the FTDI chip: switching it to
    the firmware's baud rate after an upload starts nothing until a byte (framing) or
    the quiet time (quiet) says the upload is over."""
    emu = FalconEmulator(Trajectory(TIMES, POS, "emu"), Clock(), "EMU-1",
                         firmware_start=start, quiet_s=60.0)  # fmt: skip
    _bootloaded(emu, bytes(7324))
    emu.control(fe.SIO_SET_BAUDRATE, 2, 0)  # 3 MHz / 2: the firmware's rate
    assert emu.baud == pytest.approx(fe.NORMAL_BAUD)
    assert emu.state == "load"
    emu.write(b"<")
    assert emu.state == ("run" if start == "framing" else "load")


def test_a_bootloader_that_knows_its_length_runs_the_firmware_at_its_last_byte():
    emu = FalconEmulator(Trajectory(TIMES, POS, "emu"), Clock(), "EMU-1",
                         firmware_start="length", image_size=5000)  # fmt: skip
    _bootloaded(emu, bytes(4999))
    assert emu.state == "load"
    emu.write(b"\x00\x01")  # its last byte, then one the running firmware ignores
    assert emu.state == "run" and len(emu.image) == 5000


@pytest.mark.parametrize(("hellos", "uploads"), [(60, 0), (0, 4), (30, 2)])
def test_a_bootloader_that_needs_several_tries_gets_its_firmware(tmp_path, hellos, uploads):
    _loads_and_renders(tmp_path, uploads + 1, hello_failures=hellos, firmware_failures=uploads)


def test_max_force_above_the_falcons_is_refused():
    with pytest.raises(DeviceError, match="at most the Falcon's 8 N"):
        open_device("falcon", max_force_n=9.0)


def test_discovery_says_why_it_cannot_look_without_libusb():
    # The tests' libusb_package is missing (conftest): discovery says so, no crash.
    entries = [e for e in registry.discover() if e["backend"] == "falcon"]
    assert len(entries) == 1 and "libusb" in entries[0]["problem"]


def test_discovery_lists_each_falcon_with_its_firmware_and_homing():
    from hapticd_drivers.falcon_backend import discover

    path = Trajectory(TIMES, POS, "emu")
    emus = [
        FalconEmulator(path, Clock(), "SN-A"),
        FalconEmulator(path, Clock(), "SN-B", firmware_loaded=True),
        FalconEmulator(path, Clock(), "SN-C", firmware_loaded=True, homed=True),
    ]
    (entry,) = discover(EmulatedFalconBackend(emus))
    assert entry["found"] == [
        "SN-A (index 0, firmware not loaded: hapticd loads the profile's 'firmware' file)",
        "SN-B (index 1, firmware running, NOT homed: hapticd calibrate PROFILE)",
        "SN-C (index 2, firmware running, homed)",
    ]
    assert emus[0].state == "boot" and not any(e.motor.any() for e in emus)


def test_the_udev_rules_cover_the_falcon():
    from hapticd_drivers.udev import rules

    assert 'ATTRS{idVendor}=="0403", ATTRS{idProduct}=="cb48"' in rules()


# -- the loop --------------------------------------------------------------------------------


def test_an_emulated_falcon_run_renders_what_the_replay_run_renders(tmp_path, capsys):
    """hapticd run PROFILE --device falcon --emulate --record R, as a user types it, against
    the replay run: the forces sent to the devices agree within 0.1 N over the run, after
    the Falcon's own force limit (8 N, which the safety chain applies to both runs)."""
    from hapticd import recording
    from hapticd.cli import main

    common = ["run", str(GRASP_PROFILE), "--unpaced", "--no-socket", "-q"]
    falcon_rec, replay_rec = tmp_path / "falcon.hrec", tmp_path / "replay.hrec"
    assert main([*common, "--device", "falcon", "--emulate", "--record", str(falcon_rec)]) == 0
    assert main([*common, "--record", str(replay_rec)]) == 0, capsys.readouterr().err
    a, b = recording.read(falcon_rec), recording.read(replay_rec)
    n = min(a.ticks, b.ticks)
    assert n > 7000 and np.abs(b["device_force"]).max() > 1.0  # the pinch happened
    assert not a["fault"].any()
    assert np.abs(a["device_force"][:n] - b["device_force"][:n]).max() < 0.1
    # the Falcon's encoders: ~40 um per count, through forward kinematics
    assert np.abs(a["device_pos"][:n] - b["device_pos"][:n]).max() < 2e-4


def test_a_fault_mid_run_ends_in_zero_force_and_a_latched_fault():
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile

    s = build_session(load_profile(GRASP_PROFILE), paced=False, device="falcon", emulate=True)

    def fault(frame):  # mid-pinch, both devices pushing
        assert np.abs(s.emulators[0].motor).max() > 0
        s.emulators[0].corrupt_next = 1

    s.renderer.insert(AtTick(2999, fault), after="allocation")
    out = s.run()
    assert out["end_reason"] == "fault" and "broken packet" in out["fault"]["cause"]
    for emu in s.emulators:
        np.testing.assert_array_equal(emu.motor, 0)
        assert np.isfinite(emu.end_effector_force()).all()


def test_bringup_pulses_each_actuated_direction_through_the_falcons(tmp_path, capsys, monkeypatch):
    """hapticd bringup on emulated Falcons: both pass as homed, each actuated direction is
    pulsed, and the force the emulated motors exert stays at most 0.5 N (plus a motor
    unit's quantisation)."""
    from hapticd.cli import main
    from hapticd.daemon import bringup
    from hapticd.loop.pulse import MAX_PULSE_N

    sessions = []
    build = bringup.build_session

    def build_and_keep(*a, **kw):
        # Each emulated Falcon is held by a hand that follows its path and feels its motors.
        sessions.append(build(*a, **kw))
        for emu in sessions[-1].emulators:
            emu.hand = FeelingHand(emu.path)
        return sessions[-1]

    monkeypatch.setattr(bringup, "build_session", build_and_keep)
    args = ["bringup", str(GRASP_PROFILE), "--unpaced", "--no-realtime", "--live-s", "0"]
    code = main(
        [*args, "--device", "falcon", "--emulate", "--answers", "yy", "--out", str(tmp_path)]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "thumb: falcon Falcon EMU-thumb: calibrated" in out
    assert "RESULT: PASS (devices, limits and workspace, 2 of 2 directions)" in out
    (session,) = sessions
    assert len(session.emulators) == 2
    for emu in session.emulators:
        assert isinstance(emu, FalconEmulator) and len(emu.hand.felt) > 1000
        mags = np.linalg.norm(np.array(emu.hand.felt), axis=1)
        assert 0.45 < mags.max() <= MAX_PULSE_N * 1.02


class FeelingHand:
    """A hand on an emulated device (its ``hand`` seam) that follows the device's path and
    keeps each force (3,) N the motors exert on it."""

    def __init__(self, path):
        self.path, self.felt = path, []
        self.x = tuple(path.at(0.0)[0])

    def advance(self, now, force):
        self.felt.append(force)
        self.x = tuple(self.path.at(now)[0])


class TickingClock:
    """A device clock that moves on 1 ms each time it is read: homing runs in no time."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        self.t += 1e-3
        return self.t


def test_calibrate_loads_the_firmware_and_homes_the_falcon(tmp_path):
    clock = TickingClock()
    _, emu = falcon(clock, firmware_loaded=False, homed=False)
    path = firmware_file(tmp_path)
    seam = {"usb_backend": EmulatedFalconBackend([emu]), "clock": clock}
    out = registry.calibrate("falcon", firmware=str(path), serial_number="EMU-1", **seam)
    assert out == {"model": "Falcon", "serial": "EMU-1", "was_calibrated": False}
    assert emu.state == "run" and emu.homed == fm.ALL_HOMED
    assert not emu.homing and not emu.motor.any()  # homing asked off, forces zero
    again = registry.calibrate("falcon", serial_number="EMU-1", **seam)
    assert again["was_calibrated"] is True


def test_hapticd_calibrate_tells_the_user_to_move_each_falcon(
    grasp_data, write_profile, monkeypatch, capsys
):
    from hapticd_drivers import falcon_backend

    from hapticd.cli import main

    for f in grasp_data["fingers"]:
        f["device"] = {"backend": "falcon", "index": 0 if f["name"] == "thumb" else 1}
    homed = []
    monkeypatch.setattr(
        falcon_backend,
        "calibrate",
        lambda **kw: (
            homed.append(kw["index"])
            or {"model": "Falcon", "serial": f"SN{kw['index']}", "was_calibrated": False}
        ),
    )
    monkeypatch.setattr("sys.stdin", io.StringIO(""))  # not a terminal
    assert main(["calibrate", str(write_profile(grasp_data))]) == 0  # nothing moves itself
    out = capsys.readouterr().out
    assert homed == [0, 1]
    assert "MOVE ON THEIR OWN" not in out
    assert "thumb: now move its grip all the way out, then push it straight in" in out
    assert "index: Falcon SN1 calibrated" in out


def test_a_run_on_a_falcon_whose_firmware_file_is_missing_ends_at_setup_naming_the_key(
    grasp_data, write_profile, tmp_path
):
    from hapticd.daemon.build import build_devices
    from hapticd.profile import ProfileError, load_profile

    grasp_data["fingers"][1]["device"] = {
        "backend": "falcon",
        "firmware": str(tmp_path / "nowhere.bin"),
    }
    profile = load_profile(write_profile(grasp_data))
    with pytest.raises(ProfileError, match=r"fingers\[1:index\]\.device: .*nowhere\.bin"):
        build_devices(profile, clock=lambda: 0.0)


def test_the_two_falcon_rig_passes_check(capsys):
    from hapticd.cli import main

    assert main(["check", str(ROOT / "configs" / "rigs" / "two-falcons.yaml")]) == 0
    out = capsys.readouterr().out
    assert "thumb (falcon, 1 actuated), index (falcon, 1 actuated)" in out
    assert out.count("radius 40.0 mm") == 2 and "the object is reachable" in out


def test_reconnect_mode_looks_for_an_unplugged_falcon_and_keeps_its_forces_off(
    grasp_data, write_profile
):
    """Unplugged mid-pinch and plugged back: the run goes on with the fault latched; the
    Falcon lost its firmware and homing with its power, so it is not opened again (the
    profile names no firmware) and neither Falcon pushes again."""
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile

    grasp_data["safety"]["reconnect"] = True
    profile = load_profile(write_profile(grasp_data))
    s = build_session(profile, paced=False, device="falcon", emulate=True)
    s.renderer.insert(AtTick(2999, lambda f: s.emulators[0].unplug()), after="allocation")
    s.renderer.insert(AtTick(3799, lambda f: s.emulators[0].replug()), after="allocation")
    out = s.run()
    assert out["end_reason"] == "duration reached"
    assert "unplugged" in out["fault"]["cause"]
    events = [e["event"] for e in out["events"]]
    assert any("lost" in e for e in events) and not any("reconnected" in e for e in events)
    assert s.emulators[0].state == "boot"
    for emu in s.emulators:
        np.testing.assert_array_equal(emu.motor, 0)


def test_in_reconnect_mode_a_falcon_answering_wrongly_still_ends_the_run(grasp_data, write_profile):
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile

    grasp_data["safety"]["reconnect"] = True
    profile = load_profile(write_profile(grasp_data))
    s = build_session(profile, paced=False, device="falcon", emulate=True)
    s.renderer.insert(
        AtTick(2999, lambda f: setattr(s.emulators[1], "jump_next", 1)), after="allocation"
    )
    out = s.run()
    assert out["end_reason"] == "fault" and "impossible encoder jump" in out["fault"]["cause"]
    for emu in s.emulators:
        np.testing.assert_array_equal(emu.motor, 0)


# -- a Falcon another process holds ------------------------------------------------------------


def usb_nodes(tmp_path, monkeypatch, count):
    """Stand-ins for /dev/bus/usb/001/NNN of the emulated bus's ``count`` devices."""
    from hapticd_drivers import device_lock

    root = tmp_path / "usb"
    (root / "001").mkdir(parents=True)
    for i in range(count):
        (root / "001" / f"{i + 1:03d}").write_bytes(b"")
    monkeypatch.setattr(device_lock, "USB_NODES", root)
    return root


@pytest.fixture
def holder():
    """Another process holding the lock on a node: holder(path) -> its pid."""
    procs = []

    def hold(node):
        code = (
            "import fcntl, sys\n"
            f"f = open({str(node)!r})\n"
            "fcntl.flock(f, fcntl.LOCK_EX)\n"
            "print('held', flush=True)\n"
            "sys.stdin.read()\n"
        )
        p = subprocess.Popen(
            [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        procs.append(p)
        import select

        ready, _, _ = select.select([p.stdout], [], [], 10.0)
        assert ready, "the holder did not take the lock within 10 s"
        assert p.stdout.readline().strip() == "held"
        return p.pid

    yield hold
    for p in procs:
        p.stdin.close()
        p.wait(timeout=10)


def test_discovery_sends_nothing_to_a_falcon_another_process_holds(tmp_path, monkeypatch, holder):
    from hapticd_drivers.falcon_backend import discover

    path = Trajectory(TIMES, POS, "emu")
    emus = [FalconEmulator(path, Clock(), f"SN-{c}", True, True) for c in "AB"]
    nodes = usb_nodes(tmp_path, monkeypatch, 2)
    pid = holder(nodes / "001" / "001")
    (entry,) = discover(EmulatedFalconBackend(emus))
    assert entry["found"][0] == f"index 0: in use (by pid {pid}), not asked"
    assert entry["found"][1] == "SN-B (index 1, firmware running, homed)"
    held = emus[0]
    assert (held.control_transfers, held.out_transfers, held.in_transfers) == (0, 0, 0)
    assert emus[1].control_transfers > 0  # the free one was probed as before


def test_an_open_falcon_holds_its_lock_until_closed(tmp_path, monkeypatch):
    from hapticd_drivers.device_lock import DeviceInUseError, lock_usb_device

    clock = Clock()
    nodes = usb_nodes(tmp_path, monkeypatch, 1)
    dev, emu = falcon(clock)
    node_dev = type("D", (), {"bus": 1, "address": 1})()  # the emulated bus's first device
    dev.open()
    try:
        with pytest.raises(DeviceInUseError):
            lock_usb_device(node_dev, "probe", nodes).release()
        # A second open of the same Falcon (a second run) is refused, sending nothing.
        other = open_device(
            "falcon", serial_number="EMU-1", usb_backend=EmulatedFalconBackend([emu]), clock=clock
        )
        before = emu.control_transfers + emu.out_transfers + emu.in_transfers
        with pytest.raises(DeviceInUseError) as exc:
            other._connect()
        assert exc.value.pid == os.getpid()
        assert emu.control_transfers + emu.out_transfers + emu.in_transfers == before
    finally:
        dev.close()
    lock_usb_device(node_dev, "probe", nodes).release()  # free again once closed


@pytest.mark.parametrize("axis", range(3))
def test_the_backend_never_sends_a_motor_value_beyond_what_the_emulated_falcon_takes(axis):
    clock = Clock()
    emu = FalconEmulator(Trajectory(TIMES, POS, "emu"), clock, "EMU-1", True, True)
    assert emu.motor_limit == fm.MOTOR_LIMIT  # libnifalcon's documented cap, the default
    dev = open_device(
        "falcon", serial_number="EMU-1", usb_backend=EmulatedFalconBackend([emu]), clock=clock
    )
    dev.open()
    try:
        dev.enable_forces(True)
        force = np.zeros(3)
        force[axis] = -dev.info.max_force_n  # the rated force: the motors saturate
        peak = 0
        for k in range(200):
            run(dev, clock, 1, force=tuple(force), start=k)
            peak = max(peak, int(np.abs(emu.motor).max()))
        assert emu.motor_over_limit == 0 and 0 < peak <= emu.motor_limit
        for bad in (np.nan, np.inf):
            with pytest.raises(DeviceError):
                dev.write_force(np.array([bad, 0.0, 0.0]))
        assert emu.motor_over_limit == 0 and np.isfinite(emu.motor).all()
    finally:
        dev.close()


def test_an_emulated_falcon_with_a_lower_motor_limit_counts_what_goes_beyond():
    emu = FalconEmulator(Trajectory(TIMES, POS, "emu"), Clock(), "EMU-1", True, True,
                         motor_limit=1000)  # fmt: skip
    emu.baud = 1_500_000.0  # the running firmware's rate
    emu.write(fm.encode_command((1500, 0, -200), 0, True))
    assert emu.motor_over_limit == 1 and list(emu.motor) == [1000, 0, -200]
