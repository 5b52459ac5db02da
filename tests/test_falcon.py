"""The falcon backend: its packet codec and kinematics, and the backend through the
emulated FTDI chip under pyusb (firmware load, homing, LEDs, grip, faults)."""

import io

import numpy as np
import pytest
from hapticd_drivers import DeviceError, DeviceLostError, models, open_device, registry
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


def test_a_firmware_echo_that_differs_is_a_failed_load(tmp_path):
    dev, emu = falcon(Clock(), firmware_loaded=False, firmware=str(firmware_file(tmp_path)))
    emu.corrupt_echo = 1
    with pytest.raises(DeviceError, match=r"firmware load failed: byte 0 of 7324"):
        dev.open()


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
