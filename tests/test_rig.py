"""The real rig on the fake Force Dimension SDK: hapticd run with backend dhd, mounted
devices and effector masses; hapticd calibrate; hapticd devices."""

from __future__ import annotations

import ctypes
import io

import numpy as np
import pytest
import yaml
from hapticd_drivers.trajectory import Trajectory

from hapticd import recording
from hapticd.cli import main
from hapticd.loop.mount import Mount
from tests.conftest import GRASP_PROFILE, IN_PROCESS_WATCHDOG_S
from tests.test_mount import MOUNTS, _trajectories

RATE_HZ = 1000.0
DURATION_S = 4.0
TICKS = int(DURATION_S * RATE_HZ)


def _mount(name: str) -> Mount:
    m = MOUNTS[name]
    return Mount.from_rpy(m["position_m"], m["orientation_rpy_rad"], m.get("workspace_scale", 1))


def _dhd_profile(tmp_path, lib_path: str, serials=False) -> tuple[dict, str]:
    data = yaml.safe_load(GRASP_PROFILE.read_text())
    for i, finger in enumerate(data["fingers"]):
        finger["device"] = {
            "backend": "dhd",
            "library": lib_path,
            "effector_mass_kg": 0.2 + 0.01 * i,
            "mount": MOUNTS[finger["name"]],
        }
        finger["device"].update({"serial_number": 10001 + i} if serials else {"index": i})
    # The fake SDK's devices are not on the loop's nominal clock, so an unpaced run keeps
    # its wall-clock watchdog: a loaded machine's pause is not this file's subject.
    data["safety"]["watchdog_s"] = IN_PROCESS_WATCHDOG_S
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data))
    return data, str(path)


def _play_world_motion_on_the_fake(lib, world_traj: str) -> None:
    """Each fake device plays the world motion, tick by tick, in its own frame."""
    rec = recording.read(world_traj)
    for j, name in enumerate(rec.fingers):
        path = Trajectory(rec["t"], rec["device_pos"][:, j], name)
        pos = np.zeros((TICKS + 10, 3))
        vel = np.zeros((TICKS + 10, 3))
        for k in range(len(pos)):
            pos[k], vel[k] = path.at(k / RATE_HZ)
        m = _mount(name)
        dev_pos = np.ascontiguousarray(m.point_to_device(pos))
        dev_vel = np.ascontiguousarray(vel @ m.rotation / m.scale)
        dp = ctypes.POINTER(ctypes.c_double)
        lib.fake_set_path(j, len(pos), dev_pos.ctypes.data_as(dp), dev_vel.ctypes.data_as(dp))


def test_hapticd_run_on_the_fake_sdk_renders_the_grasp_in_world_coordinates(
    tmp_path, libdhd, capsys
):
    lib_path, lib = libdhd
    lib.fake_reset(2)
    # The recordings are compared to 1e-12: a tick late by more than the velocity
    # estimator's 20 ms (a loaded machine) would keep the last velocity for a tick.
    lib.fake_set_velocity_window(60.0)
    world_traj, _ = _trajectories(tmp_path)
    _play_world_motion_on_the_fake(lib, world_traj)
    _, profile = _dhd_profile(tmp_path, lib_path)
    lib.fake_set_buttons(1, 0b101)  # the index's buttons 0 and 2 held all run
    rec_path = tmp_path / "dhd.hrec"
    common = ["--unpaced", "--duration", str(DURATION_S), "--no-realtime", "--no-socket", "-q"]
    assert main(["run", profile, *common, "--record", str(rec_path)]) == 0, capsys.readouterr()

    # The same world motion on replay devices, without mounts: what the rig must render.
    data = yaml.safe_load(GRASP_PROFILE.read_text())
    for finger in data["fingers"]:
        finger["device"]["trajectory"] = world_traj
    replay = tmp_path / "replay.yaml"
    replay.write_text(yaml.safe_dump(data))
    replay_rec = tmp_path / "replay.hrec"
    assert main(["run", str(replay), *common, "--record", str(replay_rec)]) == 0

    a, b = recording.read(rec_path), recording.read(replay_rec)
    assert a.ticks == b.ticks >= TICKS
    # The recording holds the motion in world coordinates, and the forces it renders.
    for name in ("device_pos", "device_vel", "contact_force", "rendered_force", "device_force"):
        np.testing.assert_allclose(a[name], b[name], rtol=0, atol=1e-12, err_msg=name)
    assert np.abs(a["device_force"]).max() > 0.5
    # The rig in the recording: each device's buttons every tick, its mount and effector mass.
    assert (a["buttons"][:, 0] == 0).all() and (a["buttons"][:, 1] == 0b101).all()
    rig = a.meta["devices"]
    assert [d["finger"] for d in rig] == ["thumb", "index"]
    for d in rig:
        assert d["mount"] == {"workspace_scale": 1.0, **MOUNTS[d["finger"]]}
    assert [d["effector_mass_kg"] for d in rig] == pytest.approx([0.2, 0.21])
    assert [d["model"] for d in rig] == ["dhd", "dhd"] and rig[1]["serial"] == "dhd#1"
    # What the SDK applied: each device's forces in its own frame, R^T f, summed over the run.
    for j, name in enumerate(a.fingers):
        applied = (ctypes.c_double * 3)()
        lib.fake_get_force_sum(j, applied)
        want = (a["device_force"][:, j] @ _mount(name).rotation).sum(axis=0)
        np.testing.assert_allclose(np.array(applied[:]), want, atol=1e-9)
        assert lib.fake_effector_mass(j) == pytest.approx(0.2 + 0.01 * j)
        assert lib.fake_gravity(j) == 1 and lib.fake_max_force(j) == 12.0
        # Every way out: zero force, forces off, the device closed.
        assert lib.fake_is_enabled(j) == 0 and lib.fake_is_open(j) == 0
        assert lib.fake_reads(j) == a.ticks - 1  # one read per tick (not the shutdown record)


def test_hapticd_run_refuses_forces_on_an_uncalibrated_device(tmp_path, libdhd, capsys):
    lib_path, lib = libdhd
    lib.fake_reset(2)
    lib.fake_set_calibrated(1, 0)
    _, profile = _dhd_profile(tmp_path, lib_path, serials=True)
    code = main(["run", profile, "--unpaced", "--duration", "1", "--no-realtime", "--no-socket"])
    out = capsys.readouterr().out
    assert code == 3, out
    assert "device setup failed" in out and "not calibrated" in out
    assert "hapticd calibrate PROFILE" in out
    assert "enable 1 1" not in lib.fake_log().decode()  # it never had its forces on
    for j in range(2):
        assert lib.fake_is_enabled(j) == 0 and lib.fake_is_open(j) == 0


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("serials", [False, True])
def test_calibrate_warns_asks_and_runs_the_automatic_initialisation(
    tmp_path, libdhd, capsys, monkeypatch, serials
):
    lib_path, lib = libdhd
    lib.fake_reset(2)
    lib.fake_set_calibrated(0, 0)
    _, profile = _dhd_profile(tmp_path, lib_path, serials=serials)

    monkeypatch.setattr("sys.stdin", _Terminal("no\n"))
    assert main(["calibrate", profile]) == 1
    out, err = capsys.readouterr()
    assert "MOVE ON THEIR OWN" in out and "empty every workspace" in out
    assert "thumb: dhd " + ("serial number 10001" if serials else "index 0") in out
    assert "cancelled; nothing moved" in err
    assert lib.fake_autoinits(0) == lib.fake_autoinits(1) == 0

    monkeypatch.setattr("sys.stdin", _Terminal("yes\n"))
    assert main(["calibrate", profile]) == 0
    out = capsys.readouterr().out
    assert "thumb: omega.3 10001 calibrated (was not)" in out
    assert "index: omega.3 10002 calibrated (already calibrated, done again)" in out
    assert lib.fake_autoinits(0) == lib.fake_autoinits(1) == 1
    assert [lib.fake_is_open(j) for j in range(2)] == [0, 0]
    assert [lib.fake_is_enabled(j) for j in range(2)] == [0, 0]


def test_calibrate_without_a_terminal_needs_yes(tmp_path, libdhd, capsys, monkeypatch):
    lib_path, lib = libdhd
    lib.fake_reset(2)
    _, profile = _dhd_profile(tmp_path, lib_path)
    monkeypatch.setattr("sys.stdin", io.StringIO("yes\n"))  # piped: not a confirmation
    assert main(["calibrate", profile]) == 2
    assert "not a terminal" in capsys.readouterr().err
    assert lib.fake_autoinits(0) == lib.fake_autoinits(1) == 0
    assert main(["calibrate", profile, "--yes", "--finger", "index"]) == 0
    assert "MOVE ON THEIR OWN" in capsys.readouterr().out  # the warning, even with --yes
    assert (lib.fake_autoinits(0), lib.fake_autoinits(1)) == (0, 1)


def test_calibrate_reports_a_failure_and_a_profile_with_nothing_to_calibrate(
    tmp_path, libdhd, capsys
):
    lib_path, lib = libdhd
    lib.fake_reset(2)
    lib.fake_block_autoinit(1)
    _, profile = _dhd_profile(tmp_path, lib_path)
    assert main(["calibrate", profile, "--yes"]) == 1
    err = capsys.readouterr().err
    assert "thumb: dhd omega.3 index 0, serial 10001: automatic initialisation failed" in err
    assert [lib.fake_is_open(i) for i in range(2)] == [0, 0]
    assert [lib.fake_is_enabled(i) for i in range(2)] == [0, 0]
    assert main(["calibrate", str(GRASP_PROFILE), "--yes"]) == 2
    assert "nothing to calibrate" in capsys.readouterr().err


def test_devices_lists_the_sdk_devices_with_model_and_serial(libdhd, capsys, monkeypatch):
    lib_path, lib = libdhd
    lib.fake_reset(2)
    lib.fake_set_calibrated(1, 0)
    monkeypatch.setenv("HAPTICD_LIBDHD", lib_path)
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    want = "dhd  omega.3 (SDK 3.17.5-0): 10001 (index 0, calibrated), 10002 (index 1, NOT "
    assert want + "calibrated)" in out


def test_the_hardware_guide_mounting_example(tmp_path, libdhd, capsys):
    """docs/hardware.md's two-device example: each device's y axis points at the object,
    and both fingers reach it."""
    import re

    from hapticd.daemon.build import build_mounts
    from hapticd.profile import load_profile

    text = (GRASP_PROFILE.parent.parent / "docs" / "hardware.md").read_text()
    block = re.search(r"```yaml\n(fingers:.*?)```", text, re.S).group(1)
    fingers = yaml.safe_load(block)["fingers"]
    data = yaml.safe_load(GRASP_PROFILE.read_text())
    for finger, given in zip(data["fingers"], fingers, strict=True):
        assert finger["name"] == given["name"]
        finger["device"] = {**given["device"], "library": libdhd[0]}
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data))
    thumb, index = build_mounts(load_profile(path))
    np.testing.assert_allclose(thumb.rotation @ [0, 1, 0], [1, 0, 0], atol=1e-7)
    np.testing.assert_allclose(thumb.rotation @ [1, 0, 0], [0, -1, 0], atol=1e-7)
    np.testing.assert_allclose(index.rotation @ [0, 1, 0], [-1, 0, 0], atol=1e-7)
    assert main(["check", str(path)]) == 0
    out = capsys.readouterr().out
    assert out.count("the object is reachable") == 2 and "out of reach" not in out
    assert out.count("nearest object point 35.0 mm") == 2


def test_a_device_index_that_does_not_exist_ends_the_run_at_setup_naming_it(
    tmp_path, libdhd, capsys
):
    lib_path, lib = libdhd
    lib.fake_reset(2)
    data, _ = _dhd_profile(tmp_path, lib_path)
    data["fingers"][1]["device"]["index"] = 5
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data))
    code = main(["run", str(path), "--unpaced", "--duration", "1", "--no-realtime", "--no-socket"])
    out = capsys.readouterr().out
    assert code == 3, out
    assert "device setup failed: dhd index 5: no device at index 5; 2 present" in out
    assert "enable 0 1" not in lib.fake_log().decode()  # the thumb's forces never came on
    assert lib.fake_is_enabled(0) == 0 and lib.fake_is_open(0) == 0


def test_a_device_unplugged_mid_run_latches_a_fault_zeroes_and_keeps_the_recording(
    tmp_path, libdhd
):
    """The index's cable pulled at tick 3000 of the grasp (in the pinch): the fault names the
    device, the thumb's device ends at zero force with its forces off, and the recording
    holds every tick before the fault, then the zero force the shutdown sent."""
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile
    from tests.conftest import AtTick

    lib_path, lib = libdhd
    lib.fake_reset(2)
    world_traj, _ = _trajectories(tmp_path)
    _play_world_motion_on_the_fake(lib, world_traj)
    _, profile = _dhd_profile(tmp_path, lib_path, serials=True)
    rec_path = tmp_path / "unplug.hrec"
    s = build_session(
        load_profile(profile), paced=False, duration_s=DURATION_S, record_path=rec_path
    )
    s.loop.realtime_settings = None
    s.renderer.insert(AtTick(3000, lambda f: lib.fake_unplug(1)), after="contact")
    summary = s.run()
    fault = summary["fault"]
    assert fault["tick"] == 3000 and "unplugged" in fault["cause"]
    assert "DeviceLostError: dhd omega.3 index 1, serial 10002: lost" in fault["cause"]
    rec = recording.read(rec_path)
    np.testing.assert_array_equal(rec["tick"], np.arange(rec.ticks))
    assert rec.ticks == 3001  # ticks 0-2999, then tick 3000: the shutdown's zero force
    assert np.abs(rec["device_force"][-2]).max() > 0.1 and not rec["device_force"][-1].any()
    applied = (ctypes.c_double * 3)()
    lib.fake_get_force(0, applied)
    assert list(applied) == [0.0, 0.0, 0.0]
    assert lib.fake_is_enabled(0) == 0 and lib.fake_is_open(0) == 0
