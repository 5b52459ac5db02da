"""The dhd backend against a fake libdhd compiled here (tests/fakes/fake_dhd.c)."""

import ctypes

import numpy as np
import pytest
from hapticd_drivers import DeviceError, DeviceLostError, DeviceState, open_device

from tests.conftest import FAKE_LEGACY


def force_of(lib, i):
    buf = (ctypes.c_double * 3)()
    lib.fake_get_force(i, buf)
    return np.array(buf[:])


def test_open_by_serial_read_write_and_close(libdhd_both):
    path, lib = libdhd_both
    lib.fake_reset(2)
    lib.fake_set_state(1, 0.01, -0.02, 0.03, 0.1, 0.0, -0.1)
    dev = open_device("dhd", library=path, serial_number=10002, device_watchdog_s=0.01)
    dev.open()
    assert dev.info.serial == "10002" and dev.info.model == "omega.3"
    assert lib.fake_watchdog(1) == 80  # 10 ms in 125 us units
    st = DeviceState()
    dev.read_state(st)
    np.testing.assert_allclose(st.position, [0.01, -0.02, 0.03])
    np.testing.assert_allclose(st.velocity, [0.1, 0.0, -0.1])
    dev.write_force(np.array([1.0, 2.0, 3.0]))
    np.testing.assert_array_equal(force_of(lib, 1), 0)  # not enabled yet: zero
    dev.enable_forces(True)
    dev.write_force(np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(force_of(lib, 1), [1.0, 2.0, 3.0])
    with pytest.raises(DeviceError, match="above its limit"):
        dev.write_force(np.array([20.0, 0, 0]))
    dev.close()
    np.testing.assert_array_equal(force_of(lib, 1), 0)
    assert lib.fake_is_enabled(1) == 0


def test_open_by_index_and_a_missing_device(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    dev = open_device("dhd", library=path, index=0)
    dev.open()
    assert dev.info.serial == "10001"
    dev.close()
    with pytest.raises(DeviceError, match="no device at index 3; 1 present"):
        open_device("dhd", library=path, index=3).open()
    with pytest.raises(DeviceError, match="no device with serial number 4242 among 1"):
        open_device("dhd", library=path, serial_number=4242).open()


def test_unplug_is_a_lost_device_by_its_error_code_naming_the_device(libdhd):
    path, lib = libdhd
    lib.fake_reset(2)
    dev = open_device("dhd", library=path, index=1)
    dev.open()
    dev.enable_forces(True)
    lib.fake_unplug(1)
    who = "dhd omega.3 index 1, serial 10002"
    with pytest.raises(DeviceLostError, match=f"{who}: lost .cannot read the position.: "):
        dev.read_state(DeviceState())
    with pytest.raises(DeviceLostError, match=f"{who}: lost .cannot set the force.: "):
        dev.write_force(np.ones(3))


def test_without_error_codes_an_unplug_is_still_a_device_error_but_not_a_lost_device(libdhd):
    """An SDK that reads every error as DHD_ERROR: the device fails, and is not called lost
    (only DHD_ERROR_COM and DHD_ERROR_NO_DEVICE_FOUND are)."""
    path, lib = libdhd
    lib.fake_reset(1)
    lib.fake_set_legacy(FAKE_LEGACY["no_codes"])
    dev = open_device("dhd", library=path)
    dev.open()
    lib.fake_unplug(0)
    with pytest.raises(DeviceError, match="cannot read the position: DHD_ERROR: ") as info:
        dev.read_state(DeviceState())
    assert not isinstance(info.value, DeviceLostError)


def test_missing_library_says_how_to_get_it(monkeypatch, tmp_path):
    monkeypatch.delenv("HAPTICD_LIBDHD", raising=False)
    with pytest.raises(DeviceError, match="cannot load libdhd"):
        open_device("dhd", library=str(tmp_path / "nope.so")).open()


def test_opening_disables_and_zeroes_first_then_sets_limit_mass_and_gravity(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    dev = open_device("dhd", library=path, max_force_n=7.5, effector_mass_kg=0.21)
    dev.open()
    log = lib.fake_log().decode()
    # Forces off, then a zero force: the first two commands, before anything else is set.
    assert log.startswith("open 0;enable 0 0;force 0 0 0 0;"), log
    assert "maxforce 0 7.5;" in log and "mass 0 0.21;" in log and "gravity 0 1;" in log
    assert lib.fake_max_force(0) == 7.5  # the SDK's own, independent limit
    assert lib.fake_effector_mass(0) == pytest.approx(0.21)
    assert lib.fake_gravity(0) == 1
    assert lib.fake_watchdog(0) == 240  # 30 ms in 125 us units, set in expert mode
    assert "enable 0 1" not in log  # nothing enables forces but the loop
    dev.enable_forces(True)
    dev.write_force(np.array([0.0, 0.0, 7.0]))
    np.testing.assert_allclose(force_of(lib, 0), [0, 0, 7.0])
    dev.close()


def test_without_an_effector_mass_the_sdk_default_stays(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    dev = open_device("dhd", library=path)
    dev.open()
    assert lib.fake_effector_mass(0) == pytest.approx(0.19)  # the fake's model default
    assert "mass" not in lib.fake_log().decode() and lib.fake_gravity(0) == 1
    dev.close()


def test_an_uncalibrated_device_opens_but_refuses_forces_and_says_what_to_do(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    lib.fake_set_calibrated(0, 0)
    dev = open_device("dhd", library=path)
    dev.open()
    assert dev.calibrated() is False
    with pytest.raises(DeviceError, match=r"not calibrated.*hapticd calibrate PROFILE"):
        dev.enable_forces(True)
    assert lib.fake_is_enabled(0) == 0
    dev.write_force(np.array([1.0, 0.0, 0.0]))
    np.testing.assert_array_equal(force_of(lib, 0), 0)  # never enabled: nothing rendered
    dev.close()


def test_a_bare_libdhd_cannot_check_the_calibration_so_forces_stay_off(libdhd_only):
    path, lib = libdhd_only
    lib.fake_reset(1)
    dev = open_device("dhd", library=path)
    dev.open()
    assert dev.calibrated() is None
    with pytest.raises(DeviceError, match=r"cannot tell whether .* calibrated.*libdrd"):
        dev.enable_forces(True)
    assert lib.fake_is_enabled(0) == 0
    dev.close()
    with pytest.raises(DeviceError, match=r"calibrating needs libdrd"):
        from hapticd_drivers.dhd_backend import calibrate

        calibrate(library=path)


def test_a_controller_memory_fault_refuses_the_device_and_closes_it(libdhd_both):
    """Documented: dhdCheckControllerMemory returns DHD_ERROR_CONFIGURATION; older: -1."""
    path, lib = libdhd_both
    lib.fake_reset(1)
    lib.fake_set_memory_fault(0, 1)
    dev = open_device("dhd", library=path)
    with pytest.raises(DeviceError, match=r"memory check failed.*(CONFIGURATION|DHD_ERROR)"):
        dev.open()
    assert lib.fake_is_open(0) == 0 and lib.fake_is_enabled(0) == 0
    with pytest.raises(DeviceError, match="closed"):
        dev.read_state(DeviceState())


def test_buttons_are_read_from_the_sdk(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    dev = open_device("dhd", library=path)
    dev.open()
    st = DeviceState()
    lib.fake_set_buttons(0, 0b101)
    dev.read_state(st)
    assert st.buttons == 0b101
    lib.fake_set_buttons(0, 0)
    dev.read_state(st)
    assert st.buttons == 0
    dev.close()


def test_calibrate_runs_the_automatic_initialisation_by_index_and_by_serial(libdhd):
    from hapticd_drivers.dhd_backend import calibrate

    path, lib = libdhd
    lib.fake_reset(2)
    lib.fake_set_calibrated(1, 0)
    lib.fake_set_state(1, 0.02, 0.01, 0.0, 0, 0, 0)
    out = calibrate(library=path, serial_number=10002)
    assert out == {"model": "omega.3", "serial": "10002", "was_calibrated": False}
    assert lib.fake_brakes(1) == 1  # drdStop(false) leaves it in brake mode
    assert lib.fake_autoinits(1) == 1 and lib.fake_autoinits(0) == 0
    # Every device it looked at is closed again, forces off.
    assert [lib.fake_is_open(i) for i in range(2)] == [0, 0]
    assert lib.fake_is_enabled(1) == 0
    assert "drdstop 1 0;" in lib.fake_log().decode()
    out = calibrate(library=path, index=0)
    assert out["serial"] == "10001" and out["was_calibrated"] is True
    assert lib.fake_autoinits(0) == 1
    with pytest.raises(DeviceError, match="no device with serial number 4242 among 2"):
        calibrate(library=path, serial_number=4242)
    lib.fake_set_calibrated(0, 0)
    lib.fake_block_autoinit(1)
    with pytest.raises(DeviceError, match=r"automatic initialisation failed: .*end stop"):
        calibrate(library=path, index=0)
    assert lib.fake_is_open(0) == 0


def test_discover_lists_model_serial_and_calibration(libdhd_both, monkeypatch):
    from hapticd_drivers.dhd_backend import discover

    path, lib = libdhd_both
    monkeypatch.setenv("HAPTICD_LIBDHD", path)
    lib.fake_reset(2)
    lib.fake_set_calibrated(1, 0)
    (entry,) = discover()
    assert entry["model"] == "omega.3"
    assert entry["found"] == ["10001 (index 0, calibrated)", "10002 (index 1, NOT calibrated)"]
    assert [d["serial"] for d in entry["devices"]] == ["10001", "10002"]
    assert [lib.fake_is_open(i) for i in range(2)] == [0, 0]
    # A device another program holds open is listed, not skipped.
    lib.fake_set_in_use(0, 1)
    entries = discover()
    lib.fake_set_in_use(0, 0)
    assert any("in use" in s and "DHD_ERROR" in s for e in entries for s in e["found"])


def _enabled(path, lib, **keys):
    """One fresh fake device (omega.3, serial 10001), opened with ``keys``, forces on."""
    lib.fake_reset(1)
    dev = open_device("dhd", library=path, **keys)
    dev.open()
    dev.enable_forces(True)
    return dev


# The SDK's force-off causes (DHD_FORCE_OFF_*, dhdc.h) the fake can trip, by value.
FORCE_OFF = {
    1: "DHD_FORCE_OFF_BUTTON",
    2: "DHD_FORCE_OFF_VELOCITY",
    3: "DHD_FORCE_OFF_WATCHDOG",
    4: "DHD_FORCE_OFF_SOFTWARE",
    5: "DHD_FORCE_OFF_USBDISCN",
    6: "DHD_FORCE_OFF_DEADMAN",
}


@pytest.mark.parametrize("cause", sorted(FORCE_OFF))
def test_forces_the_sdk_turned_off_itself_fail_the_device_naming_the_cause(libdhd, cause):
    """The force button, the velocity threshold, the watchdog...: the SDK's status says its
    forces are off, and the read that sees it fails naming the cause; the device renders
    zero from then on."""
    path, lib = libdhd
    dev = _enabled(path, lib, status_period_s=0.0)
    st = DeviceState()
    dev.read_state(st)
    dev.write_force(np.array([0.0, 2.0, 0.0]))
    np.testing.assert_allclose(force_of(lib, 0), [0.0, 2.0, 0.0])
    lib.fake_force_off(0, cause)
    with pytest.raises(DeviceError) as info:
        dev.read_state(st)
    msg = str(info.value)
    assert msg.startswith("dhd omega.3 index 0, serial 10001: ")
    assert f"the SDK turned its forces off ({FORCE_OFF[cause]}: " in msg
    # Only a lost USB connection is a lost device: the others still answer.
    assert isinstance(info.value, DeviceLostError) == (cause == 5)
    dev.write_force(np.array([0.0, 2.0, 0.0]))
    assert ";force 0 0 0 0;" in lib.fake_log().decode().split("forceoff")[-1]  # zero after
    dev.close()


def test_the_status_is_read_within_its_period_not_on_every_read(libdhd, monkeypatch):
    """A status read per period (s, on the backend's clock), the first at once after
    enabling."""
    from hapticd_drivers import dhd_backend

    path, lib = libdhd
    lib.fake_reset(1)
    now = [100.0]
    monkeypatch.setattr(dhd_backend, "_clock", lambda: now[0])
    dev = open_device("dhd", library=path, status_period_s=0.01)
    dev.open()
    st = DeviceState()
    dev.enable_forces(True)
    dev.read_state(st)  # reads the status: due at once
    lib.fake_force_off(0, 1)
    now[0] += 0.009
    dev.read_state(st)  # not due yet
    now[0] += 0.002
    with pytest.raises(DeviceError, match="DHD_FORCE_OFF_BUTTON"):
        dev.read_state(st)
    dev.close()
    for bad in (-0.001, float("nan"), float("inf")):
        with pytest.raises(DeviceError, match=r"dhd: status_period_s must be >= 0 s, got"):
            open_device("dhd", library=path, status_period_s=bad)


def test_a_model_with_a_wrist_or_gripper_is_commanded_through_the_combined_call(libdhd):
    """sigma.7: the translational force with zero wrist torques and gripper force, in one
    call (dhdSetForceAndTorqueAndGripperForce); an omega.3 through dhdSetForce."""
    path, lib = libdhd
    lib.fake_reset(2)
    lib.fake_set_type(1, 104)  # DHD_DEVICE_SIGMA331
    for i, model in enumerate(("omega.3", "sigma.7")):
        dev = open_device("dhd", library=path, index=i)
        dev.open()
        assert dev.info.model == model
        dev.enable_forces(True)
        dev.write_force(np.array([1.0, -2.0, 3.0]))
        np.testing.assert_allclose(force_of(lib, i), [1.0, -2.0, 3.0])
        dev.close()
    log = lib.fake_log().decode()
    assert ";force7 1 1 -2 3;" in log and ";force 1 " not in log, log
    assert ";force 0 1 -2 3;" in log and ";force7 0 " not in log, log
    out = (ctypes.c_double * 4)(9.0, 9.0, 9.0, 9.0)
    lib.fake_get_torque_and_gripper(1, out)
    assert list(out) == [0.0, 0.0, 0.0, 0.0]  # hapticd renders translations only


def test_closing_stops_the_device_brakes_on_then_closes(libdhd):
    path, lib = libdhd
    dev = _enabled(path, lib)
    dev.write_force(np.array([0.0, 0.0, 1.0]))
    dev.close()
    assert lib.fake_stops(0) == 1 and lib.fake_brakes(0) == 1
    assert lib.fake_is_enabled(0) == 0 and lib.fake_is_open(0) == 0
    log = lib.fake_log().decode()
    assert log.endswith("force 0 0 0 0;stop 0;close 0;"), log


def test_the_sdks_positive_return_codes_are_counted(libdhd):
    """DHD_MOTOR_SATURATED (a motor could not deliver the force: the SDK scaled it) and
    DHD_TIMEGUARD (a command skipped): no errors, counted."""
    path, lib = libdhd
    dev = _enabled(path, lib)
    lib.fake_set_saturation(0, 2.0)
    lib.fake_set_timeguard_every(0, 5)
    sent = [np.array([0.0, 0.0, f]) for f in (1.0, 3.0, 4.0, 1.5, 5.0, 3.0, 0.5)]
    for f in sent:
        dev.write_force(f)
    assert dev.counts() == {
        "motor_saturated": lib.fake_saturated(0),
        "timeguard": lib.fake_timeguards(0),
    }
    assert lib.fake_saturated(0) >= 2 and lib.fake_timeguards(0) >= 1
    dev.close()


def test_the_factory_velocity_threshold_is_left_as_it_is(libdhd):
    """CHAI3D sets it to 0, which turns the SDK's safety off; hapticd does not touch it."""
    path, lib = libdhd
    _enabled(path, lib).close()
    assert lib.fake_velocity_threshold_sets(0) == 0
