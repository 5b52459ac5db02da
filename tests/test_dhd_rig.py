"""A two-device dhd rig (configs/rigs/two-omega3.yaml) on the fake SDK as Force Dimension
documents it: the run, the bad input it must survive, and the walk from a shell."""

from __future__ import annotations

import ctypes
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from hapticd import recording
from hapticd.cli import main
from tests.conftest import IN_PROCESS_WATCHDOG_S, AtTick

ROOT = Path(__file__).resolve().parent.parent
RIG = ROOT / "configs" / "rigs" / "two-omega3.yaml"
# Each device's handle 40 mm along its own y axis, which its mount points at the cube:
# both fingertips 13 mm into the cube's near faces.
PRESSING = (0.0, 0.04, 0.0)


def _rig(tmp_path: Path, lib_path: str, serials: bool = False) -> Path:
    data = yaml.safe_load(RIG.read_text())
    for i, finger in enumerate(data["fingers"]):
        finger["device"]["library"] = lib_path
        if not serials:
            del finger["device"]["serial_number"]
            finger["device"]["index"] = i
    # The fake SDK's devices are not on the loop's nominal clock, so an unpaced run keeps
    # its wall-clock watchdog: a loaded machine's pause is not this file's subject.
    data["safety"]["watchdog_s"] = IN_PROCESS_WATCHDOG_S
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _applied(lib, i: int) -> np.ndarray:
    """Every force device ``i`` applied, (n, 3) N."""
    buf = np.zeros((65536, 3))
    n = lib.fake_force_log(i, buf.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), len(buf))
    return buf[:n]


def _pressing_without_serial_numbers(lib) -> None:
    lib.fake_reset(2)
    for i in range(2):
        lib.fake_set_serial(i, 0)
        lib.fake_set_state(i, *PRESSING, 0.0, 0.0, 0.0)


def _one_second_with_forces_on_both(tmp_path, lib_path, lib, paced: bool) -> None:
    summary = tmp_path / "summary.json"
    args = ["run", str(_rig(tmp_path, lib_path)), "--duration", "1", "--no-realtime"]
    args += ["--no-socket", "-q", "--summary-json", str(summary)]
    assert main(args + ([] if paced else ["--unpaced"])) == 0
    out = json.loads(summary.read_text())
    assert out["fault"] is None and out["ticks"] >= 1000
    log = lib.fake_log().decode()
    for i in range(2):
        assert f"enable {i} 1;" in log, log
        applied = np.linalg.norm(_applied(lib, i), axis=1)
        assert applied.max() > 0.5  # the cube pushed back on each finger
        assert applied[-1] == 0.0  # the last command: zero
        assert lib.fake_is_enabled(i) == 0 and lib.fake_is_open(i) == 0


def test_two_devices_run_one_second_with_forces_on_both_and_no_fault(tmp_path, libdhd_both):
    """The SDK as documented (DRD state only on DRD opens, the velocity window, no serial
    numbers, error codes) and as older fakes had it: the same run either way."""
    lib_path, lib = libdhd_both
    _pressing_without_serial_numbers(lib)
    _one_second_with_forces_on_both(tmp_path, lib_path, lib, paced=False)


@pytest.mark.timing("the velocity estimator's 20 ms window is met by a loop paced in real time")
def test_two_devices_run_one_second_paced_through_the_velocity_window(tmp_path, libdhd):
    lib_path, lib = libdhd
    _pressing_without_serial_numbers(lib)
    _one_second_with_forces_on_both(tmp_path, lib_path, lib, paced=True)


def _run(tmp_path, profile: Path, capsys) -> tuple[int, str]:
    code = main(
        ["run", str(profile), "--unpaced", "--duration", "1", "--no-realtime", "--no-socket"]
    )
    captured = capsys.readouterr()
    return code, captured.out + captured.err


def test_an_sdk_older_than_the_minimum_refuses_the_profile_naming_the_finger(
    tmp_path, libdhd, capsys
):
    lib_path, lib = libdhd
    lib.fake_reset(2)
    lib.fake_set_sdk_version(3, 15, 2, 0)
    code, out = _run(tmp_path, _rig(tmp_path, lib_path), capsys)
    assert code == 2, out
    assert "fingers[0:thumb].device" in out and "older than 3.16.0, the minimum" in out
    assert [lib.fake_is_open(i) for i in range(2)] == [0, 0]


def test_a_device_type_not_in_the_table_ends_the_run_at_setup_naming_the_device(
    tmp_path, libdhd, capsys
):
    lib_path, lib = libdhd
    _pressing_without_serial_numbers(lib)
    lib.fake_set_serial(1, 1)
    lib.fake_set_type(1, 91)
    code, out = _run(tmp_path, _rig(tmp_path, lib_path), capsys)
    assert code == 3, out
    assert "device setup failed: dhd type 91 custom index 1, serial 10002: its device type" in out
    assert "enable 0 1" not in lib.fake_log().decode()  # the thumb's forces never came on
    for i in range(2):
        assert lib.fake_is_enabled(i) == 0 and lib.fake_is_open(i) == 0
        assert not _applied(lib, i).any()


def test_a_velocity_timeout_that_never_ends_latches_a_fault_and_keeps_the_recording(
    tmp_path, libdhd
):
    from hapticd_drivers.dhd_backend import MAX_VELOCITY_TIMEOUTS

    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile

    lib_path, lib = libdhd
    _pressing_without_serial_numbers(lib)
    rec_path = tmp_path / "stuck.hrec"
    s = build_session(
        load_profile(_rig(tmp_path, lib_path)), paced=False, duration_s=2.0, record_path=rec_path
    )
    s.loop.realtime_settings = None
    s.renderer.insert(AtTick(600, lambda f: lib.fake_set_velocity_stuck(1, 1)), after="contact")
    fault = s.run()["fault"]
    # Tick 600 still read its velocity; 601 on time out: the last one kept for
    # MAX_VELOCITY_TIMEOUTS reads, and the next read fails.
    assert fault["tick"] == 601 + MAX_VELOCITY_TIMEOUTS
    cause = fault["cause"]
    assert cause.startswith("DeviceError: dhd omega.3 index 1 (no serial number): the SDK's")
    assert "velocity estimator timed out" in cause
    rec = recording.read(rec_path)
    np.testing.assert_array_equal(rec["tick"], np.arange(rec.ticks))
    assert rec.ticks == fault["tick"] + 1  # every tick before the fault, then the zero force
    assert np.abs(rec["device_force"][-2]).max() > 0.1 and not rec["device_force"][-1].any()
    for i in range(2):
        assert _applied(lib, i)[-1].tolist() == [0.0, 0.0, 0.0]
        assert lib.fake_is_enabled(i) == 0 and lib.fake_is_open(i) == 0


def _shell(args: list[str], env: dict[str, str]) -> str:
    proc = subprocess.run(
        [sys.executable, "-m", "hapticd", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


def test_the_fake_sdk_from_a_shell_walks_devices_calibrate_bringup_and_run(tmp_path):
    """As docs/devices.md tells a person to: build the fake with its command, set the
    environment, and run hapticd's commands on the bundled two-device rig, each a new
    process (the calibration kept in the fake's state file)."""
    lib_dir = tmp_path / "sdk"
    built = subprocess.run(
        [sys.executable, "tests/fakes/fake_sdk.py", "--out", str(lib_dir)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    if built.returncode != 0 and "no C compiler" in built.stderr:
        pytest.skip(built.stderr.strip())
    assert built.returncode == 0, built.stderr
    exports = dict(
        line.removeprefix("export ").split("=", 1)
        for line in built.stdout.splitlines()
        if line.startswith("export ")
    )
    assert exports["HAPTICD_LIBDHD"] == str(lib_dir / "libfakedrd.so")
    env = {
        **os.environ,
        **exports,
        "HAPTICD_FAKE_DHD_CALIBRATED": "0",
        "HAPTICD_FAKE_DHD_STATE": str(tmp_path / "calibration"),
        "HAPTICD_FAKE_DHD_MOTION": "sine",
        "HAPTICD_FAKE_DHD_POSITION": "0,0.03,0",
        "HAPTICD_FAKE_DHD_AMPLITUDE": "0,0.01,0",
    }
    out = _shell(["devices"], env)
    assert (
        "dhd  omega.3 (SDK 3.17.5-0): 10001 (index 0, NOT calibrated), 10002 (index 1, NOT" in out
    )
    _shell(["calibrate", str(RIG), "--yes"], env)
    assert "10001 (index 0, calibrated), 10002 (index 1, calibrated)" in _shell(["devices"], env)
    out = _shell(
        [
            "bringup",
            str(RIG),
            "--answers",
            "yy",
            "--live-s",
            "0",
            "--no-realtime",
            "--out",
            str(tmp_path / "bringup"),
        ],
        env,
    )
    assert "thumb: dhd omega.3 10001: calibrated; rated 8 N, workspace radius 75 mm" in out
    assert "RESULT: PASS" in out
    summary = tmp_path / "summary.json"
    _shell(
        [
            "run",
            str(RIG),
            "--duration",
            "1",
            "--unpaced",
            "--no-realtime",
            "--no-socket",
            "-q",
            "--summary-json",
            str(summary),
        ],
        env,
    )
    run = json.loads(summary.read_text())
    assert run["fault"] is None and run["ticks"] >= 1000


def test_check_uses_the_named_model_and_says_when_the_workspace_is_not_known(
    tmp_path, libdhd, capsys
):
    lib_path, _ = libdhd
    data = yaml.safe_load(_rig(tmp_path, lib_path).read_text())
    data["fingers"][0]["device"].update(model="Falcon")  # 8 N, 40 mm, at most 3000 N/m
    del data["fingers"][1]["device"]["model"]
    data["scene"]["object"]["stiffness_n_per_m"] = 4000.0
    path = tmp_path / "falcon.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["check", str(path)]) == 0
    out = capsys.readouterr().out
    assert "thumb: device workspace about (-60.0, 0.0, 0.0) mm (world), radius 40.0 mm" in out
    assert "index: device workspace about (60.0, 0.0, 0.0) mm (world); its workspace is not " in out
    assert (
        "thumb: the Falcon renders at most 3000 N/m and 20 N s/m; the scene asks 4000 N/m "
        "(object) and 0 N s/m (object): WARNING: above" in out
    )
    assert "index: the" not in out  # its model is not known before it opens


def test_bringup_fails_a_scene_stiffer_than_the_device_model_renders(tmp_path, libdhd, capsys):
    lib_path, lib = libdhd
    _pressing_without_serial_numbers(lib)
    data = yaml.safe_load(_rig(tmp_path, lib_path).read_text())
    data["scene"]["object"]["stiffness_n_per_m"] = 6000.0  # an omega.3: at most 5000 N/m
    path = tmp_path / "stiff.yaml"
    path.write_text(yaml.safe_dump(data))
    code = main(
        [
            "bringup",
            str(path),
            "--answers",
            "yy",
            "--live-s",
            "0",
            "--no-realtime",
            "--unpaced",
            "--out",
            str(tmp_path),
        ]
    )
    out = capsys.readouterr().out
    assert code == 1, out
    assert "index: the omega.3 renders at most 5000 N/m and 30 N s/m; the scene asks 6000" in out
    assert "RESULT: FAIL" in out


def _reconnecting_session(tmp_path, lib_path: str):
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile

    data = yaml.safe_load(_rig(tmp_path, lib_path).read_text())
    data["safety"]["reconnect"] = True
    path = tmp_path / "reconnect.yaml"
    path.write_text(yaml.safe_dump(data))
    s = build_session(load_profile(path), paced=False, duration_s=2.0)
    s.loop.realtime_settings = None
    return s


def test_in_reconnect_mode_only_a_lost_device_is_looked_for_again(tmp_path, libdhd):
    """A cable pulled and plugged back: lost, then reconnected with its forces off, the
    run going on. A velocity estimator that never answers is no lost device: the run ends
    with the fault, and nothing was closed and looked for again."""
    lib_path, lib = libdhd
    _pressing_without_serial_numbers(lib)
    s = _reconnecting_session(tmp_path, lib_path)
    s.renderer.insert(AtTick(500, lambda f: lib.fake_unplug(1)), after="contact")
    s.renderer.insert(AtTick(900, lambda f: lib.fake_replug(1)), after="contact")
    out = s.run()
    assert out["end_reason"] == "duration reached"
    events = [e["event"] for e in out["events"]]
    assert any(e.startswith("device index 1 lost: dhd omega.3 index 1") for e in events), events
    assert any(e == "device index 1 reconnected; forces stay off" for e in events), events
    for i in range(2):
        assert lib.fake_is_enabled(i) == 0 and lib.fake_is_open(i) == 0

    _pressing_without_serial_numbers(lib)
    s = _reconnecting_session(tmp_path, lib_path)
    s.renderer.insert(AtTick(500, lambda f: lib.fake_set_velocity_stuck(1, 1)), after="contact")
    out = s.run()
    assert out["end_reason"] == "fault"
    assert "velocity estimator timed out" in out["fault"]["cause"]
    assert not any("lost" in e["event"] for e in out["events"])
    for i in range(2):
        assert _applied(lib, i)[-1].tolist() == [0.0, 0.0, 0.0]
        assert lib.fake_is_enabled(i) == 0 and lib.fake_is_open(i) == 0


def _session(tmp_path, lib_path: str, record: Path | None = None, **device):
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile

    data = yaml.safe_load(_rig(tmp_path, lib_path).read_text())
    for finger in data["fingers"]:
        finger["device"].update(device)
    path = tmp_path / "keys.yaml"
    path.write_text(yaml.safe_dump(data))
    s = build_session(load_profile(path), paced=False, duration_s=2.0, record_path=record)
    s.loop.realtime_settings = None
    return s


@pytest.mark.parametrize(
    ("cause", "name"),
    [(1, "DHD_FORCE_OFF_BUTTON"), (2, "DHD_FORCE_OFF_VELOCITY"), (3, "DHD_FORCE_OFF_WATCHDOG")],
)
def test_forces_the_sdk_turns_off_latch_a_fault_naming_the_cause_with_zero_force(
    tmp_path, libdhd, cause, name
):
    """The force button, the velocity threshold, the watchdog: the loop sees the SDK's
    force-off on the next status read, latches a device fault naming it, and every device
    ends at zero force, disabled, stopped (brakes on) and closed."""
    lib_path, lib = libdhd
    _pressing_without_serial_numbers(lib)
    rec_path = tmp_path / "off.hrec"
    s = _session(tmp_path, lib_path, rec_path, status_period_s=0.0)
    s.renderer.insert(AtTick(600, lambda f: lib.fake_force_off(1, cause)), after="contact")
    out = s.run()
    fault = out["fault"]
    assert out["end_reason"] == "fault" and fault["kind"] == "device", fault
    # Tick 600's force went out before the SDK cut it; tick 601's read sees it.
    assert fault["tick"] == 601
    assert fault["cause"].startswith(
        f"DeviceError: dhd omega.3 index 1 (no serial number): the SDK turned its forces off "
        f"({name}: "
    )
    rec = recording.read(rec_path)
    assert rec.ticks == fault["tick"] + 1
    assert np.abs(rec["device_force"][600]).max() > 0.1 and not rec["device_force"][-1].any()
    log = lib.fake_log().decode()
    for i in range(2):
        assert _applied(lib, i)[-1].tolist() == [0.0, 0.0, 0.0]
        assert lib.fake_is_enabled(i) == 0 and lib.fake_is_open(i) == 0
        assert lib.fake_stops(i) == 1 and f"stop {i};close {i};" in log


def test_saturated_motors_and_skipped_commands_are_counted_in_the_summary(tmp_path, libdhd, capsys):
    lib_path, lib = libdhd
    _pressing_without_serial_numbers(lib)
    lib.fake_set_saturation(0, 0.3)  # the thumb's motors saturate above 0.3 N
    lib.fake_set_timeguard_every(1, 100)
    summary = tmp_path / "summary.json"
    args = ["run", str(_rig(tmp_path, lib_path)), "--duration", "1", "--no-realtime"]
    args += ["--no-socket", "--unpaced", "--summary-json", str(summary)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    out = json.loads(summary.read_text())
    assert out["fault"] is None
    thumb, index = (out["fingers"][n]["device_counts"] for n in ("thumb", "index"))
    assert thumb == {"motor_saturated": lib.fake_saturated(0), "timeguard": 0}
    assert index == {"motor_saturated": 0, "timeguard": lib.fake_timeguards(1)}
    assert thumb["motor_saturated"] > 100 and index["timeguard"] >= 10
    assert f"{thumb['motor_saturated']} motor saturated\n" in printed, printed
    assert f"{index['timeguard']} timeguard\n" in printed, printed


def test_enabling_forces_happens_outside_every_tick(tmp_path, libdhd):
    """At the start and after `enable`: the SDK's blocking calls (brakes, the estimator's
    reads, dhdEnableForce) run between ticks, never inside one; forces come on the tick
    after `enable` applies."""
    from hapticd.loop.commands import Enable

    lib_path, lib = libdhd
    _pressing_without_serial_numbers(lib)
    s = _session(tmp_path, lib_path)
    loop = s.loop
    in_tick = [False]
    tick = loop._tick

    def timed_tick(*args):
        in_tick[0] = True
        try:
            tick(*args)
        finally:
            in_tick[0] = False

    loop._tick = timed_tick
    enabled_in_tick: list[bool] = []
    for dev in loop.devices:
        enable = dev.enable_forces

        def watched(on, enable=enable):
            if on:
                enabled_in_tick.append(in_tick[0])
            enable(on)

        dev.enable_forces = watched
    s.renderer.insert(AtTick(300, lambda f: loop.submit(Enable())), after="contact")
    out = s.run()
    assert out["fault"] is None, out["fault"]
    assert enabled_in_tick == [False] * 4  # both at the start, both after `enable`
