"""One conformance suite for every backend, and the hid backend's faults through the emulator."""

import numpy as np
import pytest
from hapticd_drivers import DeviceError, DeviceState, open_device, registry
from hapticd_drivers.delta import load_description
from hapticd_drivers.emulator import DeltaEmulator, FakeHidModule
from hapticd_drivers.trajectory import Trajectory

from tests.conftest import AtTick

DESC = load_description("delta-omega-class")
TIMES = np.array([0.0, 0.5, 1.0])
POS = np.array([[0.0, 0.0, 0.0], [0.02, 0.01, -0.01], [0.03, -0.01, 0.02]])


class Clock:
    t = 0.0

    def __call__(self):
        return self.t


def make(backend, clock, request=None, **kw):
    if backend == "dhd":
        # The fake libdhd's device 0 is moved along the same path by the test's clock.
        path, lib = request.getfixturevalue("libdhd")
        lib.fake_reset(1)
        traj = Trajectory(TIMES, POS, "fake hand")
        dev = open_device("dhd", library=path, index=0, **kw)

        def move() -> None:
            p, v = traj.at(clock.t)
            lib.fake_set_state(0, *p, *v)

        dev.move = move
        return dev
    if backend == "falcon":
        from hapticd_drivers.falcon_emulator import EmulatedFalconBackend, FalconEmulator

        emu = FalconEmulator(
            Trajectory(TIMES, POS, "emu"), clock, "EMU-1", firmware_loaded=True, homed=True
        )
        seam = {"usb_backend": EmulatedFalconBackend([emu]), "clock": clock}
        dev = open_device(backend, serial_number="EMU-1", **seam, **kw)
        dev.emulator = emu
        return dev
    if backend in ("hid", "usb"):
        emu = DeltaEmulator(DESC, Trajectory(TIMES, POS, "emu"), clock, serial="EMU-1")
        if backend == "hid":
            seam = {"hid_module": FakeHidModule([emu])}
        else:
            from hapticd_drivers.usb_emulator import EmulatedUsbBackend

            seam = {"usb_backend": EmulatedUsbBackend([emu])}
        dev = open_device(backend, serial_number="EMU-1", **seam, **kw)
        dev.emulator = emu
        return dev
    if backend == "virtual":
        # A person's hand, here the test: the target follows the path each tick (slower
        # than the handle's top speed, so the handle is where the path is).
        traj = Trajectory(TIMES, POS, "mouse")
        dev = open_device("virtual", serial="V-1", clock=clock, **kw)
        dev.move = lambda: dev.move_to(traj.at(clock.t)[0])
        return dev
    return open_device(backend, times=TIMES, positions=POS, clock=clock, **kw)


BACKENDS = sorted(registry.BACKENDS)  # every registered backend passes the same suite
PROTOCOL = ["hid", "usb"]


@pytest.mark.parametrize("backend", BACKENDS)
def test_conformance_read_write_enable_close(backend, request):
    clock = Clock()
    dev = make(backend, clock, request)
    st = DeviceState()
    with pytest.raises(DeviceError):
        dev.read_state(st)  # not open yet
    dev.open()
    try:
        assert dev.info.max_force_n > 0 and dev.info.workspace_radius_m > 0
        dev.enable_forces(True)
        for k in range(300):
            clock.t = k * 1e-3
            if hasattr(dev, "move"):
                dev.move()
            dev.read_state(st)
            assert np.all(np.isfinite(st.position)) and np.all(np.isfinite(st.velocity))
            dev.write_force(np.array([0.5, -0.2, 0.1]))
        want, _ = Trajectory(TIMES, POS, "p").at(clock.t)
        # sim lags on its hand spring; encoders quantise (a Falcon's count is ~40 um)
        tol = {"sim": 0.01, "falcon": 1e-4}.get(backend, 2e-5)
        np.testing.assert_allclose(st.position, want, atol=tol)
        with pytest.raises(DeviceError, match="finite"):
            dev.write_force(np.array([np.nan, 0, 0]))
        with pytest.raises(DeviceError, match="above its limit"):
            dev.write_force(np.array([dev.info.max_force_n * 1.01, 0, 0]))
    finally:
        dev.close()
    with pytest.raises(DeviceError):
        dev.write_force(np.zeros(3))


def proto_dev(backend="hid", **kw):
    clock = Clock()
    dev = make(backend, clock, **kw)
    dev.open()
    dev.enable_forces(True)
    return dev, dev.emulator, clock


def run(dev, clock, ticks, force=(1.0, -2.0, 3.0), start=0):
    st = DeviceState()
    for k in range(start, start + ticks):
        clock.t = k * 1e-3
        dev.read_state(st)
        dev.write_force(np.array(force))
    return st


@pytest.mark.parametrize("backend", PROTOCOL)
def test_renders_the_requested_force_within_quantisation(backend):
    dev, emu, clock = proto_dev(backend)
    run(dev, clock, 200)
    np.testing.assert_allclose(emu.end_effector_force(), [1.0, -2.0, 3.0], atol=5e-3)


@pytest.mark.parametrize("backend", PROTOCOL)
def test_saturation_keeps_the_force_direction(backend):
    dev, _, clock = proto_dev(backend)
    st = run(dev, clock, 5)
    f = np.array([12.0, 0.0, 0.0])  # at the limit, in a direction the motors cannot all reach
    current = dev.currents_for(f)
    assert np.abs(current).max() <= DESC.max_current + 1e-12
    theta = dev.delta.inverse(st.position)  # the last read pose's joint angles
    produced = np.linalg.solve(
        dev.delta.jacobian(theta).T, current * DESC.torque_constant * DESC.gear_ratio
    )
    np.testing.assert_allclose(produced / np.linalg.norm(produced), [1, 0, 0], atol=1e-9)


@pytest.mark.parametrize("backend", PROTOCOL)
def test_one_lost_report_is_tolerated_three_are_a_timeout(backend):
    dev, emu, clock = proto_dev(backend)
    run(dev, clock, 10)
    emu.drop_next = 1
    run(dev, clock, 10, start=10)
    assert dev.lost_reports == 1
    emu.drop_next = 3
    with pytest.raises(DeviceError, match=r"no input report for 3 reads \(timeout\)"):
        run(dev, clock, 1, start=20)


@pytest.mark.parametrize("backend", PROTOCOL)
def test_corrupt_report_is_an_error(backend):
    dev, emu, clock = proto_dev(backend)
    run(dev, clock, 10)
    emu.corrupt_next = 1
    with pytest.raises(DeviceError, match=r"corrupt input report.*CRC"):
        run(dev, clock, 1, start=10)


@pytest.mark.parametrize("backend", PROTOCOL)
def test_repeated_report_is_out_of_sequence(backend):
    dev, emu, clock = proto_dev(backend)
    run(dev, clock, 10)
    emu.repeat_next = 1
    with pytest.raises(DeviceError, match="out of sequence"):
        run(dev, clock, 1, start=10)


@pytest.mark.parametrize("backend", PROTOCOL)
def test_unplug_is_an_error_and_the_device_exerts_no_force(backend):
    dev, emu, clock = proto_dev(backend)
    run(dev, clock, 10)
    emu.unplug()
    with pytest.raises(DeviceError, match="unplugged"):
        run(dev, clock, 1, start=10)
    np.testing.assert_array_equal(emu.currents, 0)


@pytest.mark.parametrize("backend", PROTOCOL)
def test_device_watchdog_zeroes_forces_when_the_host_stops_writing(backend):
    dev, emu, clock = proto_dev(backend, device_watchdog_s=0.02)
    run(dev, clock, 10)
    assert emu.watchdog_s == pytest.approx(0.02)
    assert np.abs(emu.currents).max() > 0
    clock.t = 0.05  # 40 ms without an output report
    with pytest.raises(DeviceError, match="watchdog cut the forces"):
        dev.read_state(DeviceState())
    np.testing.assert_array_equal(emu.currents, 0)


@pytest.mark.parametrize("backend", PROTOCOL)
def test_corrupt_output_reports_are_rejected_by_the_device(backend):
    dev, emu, clock = proto_dev(backend)
    run(dev, clock, 10)
    before = emu.currents.copy()
    bad = bytearray(
        dev.protocol["output"].encode({"flags": 1, "sequence": 99, "current": (2.0, 2.0, 2.0)})
    )
    bad[5] ^= 0xFF
    emu.output_report(bytes(bad))
    assert emu.rejected_outputs == 1
    np.testing.assert_array_equal(emu.currents, before)


def test_no_device_found_says_why():
    dev = open_device("hid", hid_module=FakeHidModule([]), serial_number="NOPE")
    with pytest.raises(DeviceError, match=r"no device 1209:0001 \(NOPE\) found; 0 present"):
        dev.open()


def test_hid_backend_without_hidapi_names_the_extra(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "hid", None)  # as if cython-hidapi were not installed
    dev = open_device("hid")
    with pytest.raises(DeviceError, match=r"pip install 'hapticd\[hid\]'"):
        dev.open()


def test_hapticd_run_on_emulated_hid_devices_renders_what_replay_renders(tmp_path, capsys):
    from hapticd import recording
    from hapticd.cli import main
    from tests.conftest import GRASP_PROFILE

    hid_rec, replay_rec = tmp_path / "hid.hrec", tmp_path / "replay.hrec"
    assert (
        main(
            [
                "run",
                str(GRASP_PROFILE),
                "--device",
                "hid",
                "--emulate",
                "--unpaced",
                "-q",
                "--record",
                str(hid_rec),
            ]
        )
        == 0
    )
    assert main(["run", str(GRASP_PROFILE), "--unpaced", "-q", "--record", str(replay_rec)]) == 0
    a, b = recording.read(hid_rec), recording.read(replay_rec)
    n = min(a.ticks, b.ticks)
    assert n >= 7800
    # Positions through quantised encoders and the kinematics: within a few micrometres.
    assert np.abs(a["device_pos"][:n] - b["device_pos"][:n]).max() < 2e-5
    diff = np.abs(a["device_force"][:n] - b["device_force"][:n]).max(axis=(1, 2))
    assert np.percentile(diff, 99) < 2e-3  # the same forces, within quantisation
    assert diff.max() < 0.02  # at contact onset a quantum shifts the blend by a tick
    assert np.abs(a["device_force"]).max() > 1.0  # and they did render the pinch


def test_emulate_needs_the_hid_backend(capsys):
    from hapticd.cli import main
    from tests.conftest import GRASP_PROFILE

    assert main(["run", str(GRASP_PROFILE), "--emulate", "--unpaced"]) == 2
    err = capsys.readouterr().err
    assert "--emulate works with the hid, usb and falcon backends, not 'replay'" in err


def test_no_usb_device_found_says_why():
    from hapticd_drivers.usb_emulator import EmulatedUsbBackend

    dev = open_device("usb", usb_backend=EmulatedUsbBackend([]), index=1)
    with pytest.raises(DeviceError, match=r"no device 1209:0001 \(index 1\) found; 0 present"):
        dev.open()


def test_usb_backend_without_pyusb_names_the_extra(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "usb.core", None)
    dev = open_device("usb")
    with pytest.raises(DeviceError, match=r"pip install 'hapticd\[usb\]'"):
        dev.open()


FAULTS = {
    "lost reports": (lambda emu: setattr(emu, "drop_next", 5), "timeout"),
    "corrupt report": (lambda emu: setattr(emu, "corrupt_next", 1), "corrupt input report"),
    "out-of-sequence report": (lambda emu: setattr(emu, "repeat_next", 1), "out of sequence"),
    "unplug": (lambda emu: emu.unplug(), "unplugged"),
}


@pytest.mark.parametrize("backend", PROTOCOL)
@pytest.mark.parametrize("fault", list(FAULTS))
def test_a_fault_in_a_running_loop_ends_in_zero_force_and_a_latched_fault(backend, fault):
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile
    from tests.conftest import GRASP_PROFILE

    s = build_session(load_profile(GRASP_PROFILE), paced=False, device=backend, emulate=True)
    inject, cause = FAULTS[fault]

    def fault(frame):  # mid-pinch, both devices pushing
        assert np.abs(s.emulators[0].currents).max() > 0
        inject(s.emulators[0])

    s.renderer.insert(AtTick(2999, fault), after="allocation")
    out = s.run()
    assert out["end_reason"] == "fault"
    assert cause in out["fault"]["cause"]
    for emu in s.emulators:  # neither device exerts any force afterwards
        np.testing.assert_array_equal(emu.currents, 0)
        assert not emu.forces_enabled


@pytest.mark.parametrize("backend", PROTOCOL)
def test_an_unplugged_device_is_reopened_with_forces_off(grasp_data, write_profile, backend):
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile

    grasp_data["safety"]["reconnect"] = True
    s = build_session(
        load_profile(write_profile(grasp_data)), paced=False, device=backend, emulate=True
    )
    s.renderer.insert(AtTick(2999, lambda f: s.emulators[0].unplug()), after="allocation")
    s.renderer.insert(AtTick(3799, lambda f: s.emulators[0].replug()), after="allocation")
    out = s.run()
    assert out["end_reason"] == "duration reached"  # the run went on
    assert "unplugged" in out["fault"]["cause"]  # with the fault latched
    events = [e["event"] for e in out["events"]]
    assert any("lost" in e for e in events) and any(
        "reconnected; forces stay off" in e for e in events
    )
    lost_at = next(e["t"] for e in out["events"] if "lost" in e["event"])
    back_at = next(e["t"] for e in out["events"] if "reconnected" in e["event"])
    assert 3.79 <= back_at <= 3.8 + 0.5 + 0.002 and lost_at < back_at
    for emu in s.emulators:  # reopened, and never pushed again
        np.testing.assert_array_equal(emu.currents, 0)
        assert not emu.forces_enabled


@pytest.mark.parametrize("backend", PROTOCOL)
def test_a_late_report_is_tolerated_three_late_are_a_timeout(backend):
    dev, emu, clock = proto_dev(backend)
    run(dev, clock, 10)
    emu.delay_next = 1
    run(dev, clock, 10, start=10)  # in sequence once it arrives: no error
    assert dev.lost_reports == 1
    emu.delay_next = 3
    with pytest.raises(DeviceError, match="timeout"):
        run(dev, clock, 1, start=20)


@pytest.mark.parametrize("backend", PROTOCOL)
def test_emulator_moved_by_a_hand_feels_the_rendered_force(backend):
    from hapticd_drivers.sim import Hand

    clock = Clock()
    path = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)), "still hand")
    hand = Hand(path, mass=0.05, k=300.0, b=3.0)
    emu = DeltaEmulator(DESC, path, clock, serial="EMU-1", hand=hand)
    if backend == "hid":
        seam = {"hid_module": FakeHidModule([emu])}
    else:
        from hapticd_drivers.usb_emulator import EmulatedUsbBackend

        seam = {"usb_backend": EmulatedUsbBackend([emu])}
    dev = open_device(backend, serial_number="EMU-1", **seam)
    dev.open()
    dev.enable_forces(True)
    st = DeviceState()
    for k in range(1000):
        clock.t = k * 1e-3
        dev.read_state(st)
        dev.write_force(np.array([0.6, 0.0, -0.3]))
    # The device pushes the fingertip off the hand's path until the hand spring balances it.
    np.testing.assert_allclose(st.position, np.array([0.6, 0.0, -0.3]) / 300.0, atol=3e-5)
    dev.close()


def test_a_usb_device_another_process_holds_is_refused_and_the_open_takes_the_lock(
    tmp_path, monkeypatch
):
    import fcntl

    from hapticd_drivers import device_lock

    node = tmp_path / "usb" / "001" / "001"  # the emulated bus's first device
    node.parent.mkdir(parents=True)
    node.write_bytes(b"")
    monkeypatch.setattr(device_lock, "USB_NODES", tmp_path / "usb")
    clock = Clock()
    dev = make("usb", clock)
    dev.open()
    try:
        with open(node) as f, pytest.raises(BlockingIOError):
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)  # the open holds it
        second = make("usb", clock)
        with pytest.raises(device_lock.DeviceInUseError, match="in use"):
            second.open()
    finally:
        dev.close()
    with open(node) as f:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)  # released at close
