"""hapticd bringup: the pulse's shape, and whole bring-ups with scripted answers on replay,
emulated and fake-SDK devices, read back from the forces the devices were actually sent."""

from __future__ import annotations

import argparse
import ctypes
import datetime
import io
import json
import math
import os
import threading
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hapticd.cli import main
from hapticd.daemon import bringup as bringup_module
from hapticd.loop.pulse import MAX_PULSE_N, PulseStage, envelope
from hapticd.physics.frame import Frame
from tests.conftest import GRASP_PROFILE
from tests.test_rig import _dhd_profile, _mount

RAMP, HOLD = bringup_module.PULSE_RAMP_S, bringup_module.PULSE_HOLD_S
DT = 1e-3
# The steepest change of a pulse's force in one tick, N: A pi / (2 ramp) N/s over dt.
MAX_STEP_N = MAX_PULSE_N * math.pi / (2 * RAMP) * DT
FAST = ["--unpaced", "--no-realtime", "--live-s", "0"]


# -- the pulse --------------------------------------------------------------------------------


@given(st.floats(-1.0, 2.0, allow_nan=False))
def test_the_envelope_is_bounded_and_continuous(t):
    s = envelope(t, RAMP, HOLD)
    assert 0.0 <= s <= 1.0
    h = 1e-6
    # Continuous, with a bounded slope (pi / (2 ramp) per s) everywhere.
    assert abs(envelope(t + h, RAMP, HOLD) - s) <= math.pi / (2 * RAMP) * h * (1 + 1e-6) + 1e-15
    if t <= 0 or t >= 2 * RAMP + HOLD:
        assert s == 0.0
    if RAMP <= t <= RAMP + HOLD:
        assert s == 1.0


def test_the_stage_pulses_one_finger_smoothly_and_nothing_else():
    stage = PulseStage(2, DT, RAMP, HOLD)
    frame = Frame(2, 2)
    d = np.array([0.0, 3.0, 4.0])
    forces = []
    for k in range(1200):
        frame.tick[()] = k
        frame.rendered_force[:] = 7.0  # the scene's forces: replaced, never added to
        if k == 100:
            stage.start(k, 1, d, 0.4)
        stage.run(frame)
        forces.append(frame.rendered_force.copy())
    f = np.array(forces)
    assert not f[:, 0].any() and not f[:100].any()
    mags = np.linalg.norm(f[:, 1], axis=1)
    on = np.flatnonzero(mags)
    assert on[0] == 101 and on[-1] < 100 + stage.n_ticks  # zero at its first and last tick
    assert mags.max() == pytest.approx(0.4) and mags.max() <= 0.4
    np.testing.assert_allclose(f[on, 1] / mags[on, None], np.tile(d / 5, (len(on), 1)))
    assert np.abs(np.diff(mags)).max() <= 0.4 * math.pi / (2 * RAMP) * DT * (1 + 1e-9)
    assert stage.done and stage.peak_commanded_n == pytest.approx(0.4)


@pytest.mark.parametrize(
    ("amp", "d", "finger", "what"),
    [
        (0.51, [1, 0, 0], 0, "amplitude"),
        (0.0, [1, 0, 0], 0, "amplitude"),
        (float("nan"), [1, 0, 0], 0, "amplitude"),
        (0.3, [0, 0, 0], 0, "direction"),
        (0.3, [float("inf"), 0, 0], 0, "direction"),
        (0.3, [1, 0, 0], 2, "no finger"),
    ],
)
def test_the_stage_refuses_a_pulse_it_must_not_send(amp, d, finger, what):
    stage = PulseStage(2, DT)
    with pytest.raises(ValueError, match=what):
        stage.start(0, finger, np.array(d, dtype=float), amp)
    assert stage.done and stage.start_tick == -1


def test_a_second_pulse_waits_for_the_first():
    stage = PulseStage(1, DT)
    stage.start(0, 0, np.array([1.0, 0, 0]), 0.5)
    with pytest.raises(ValueError, match="still running"):
        stage.start(1, 0, np.array([1.0, 0, 0]), 0.5)


# -- a whole bring-up ----------------------------------------------------------------------------


@pytest.fixture
def captured(monkeypatch):
    """The sessions hapticd bringup builds, to read their devices afterwards."""
    sessions = []
    real = bringup_module.build_session

    def build(*a, **kw):
        s = real(*a, **kw)
        sessions.append(s)
        return s

    monkeypatch.setattr(bringup_module, "build_session", build)
    return sessions


def _pulses(forces: np.ndarray) -> list[np.ndarray]:
    """The runs of non-zero force (n, 3) N, each a pulse."""
    on = np.linalg.norm(forces, axis=1) > 0
    edges = np.flatnonzero(np.diff(np.r_[0, on.astype(int), 0]))
    return [forces[a:b] for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _check_pulse(p: np.ndarray, direction: np.ndarray, amp: float = MAX_PULSE_N) -> None:
    """One pulse as the device got it: never above amp, rising from and falling to zero in
    steps no larger than the envelope allows, along ``direction``."""
    mags = np.linalg.norm(p, axis=1)
    assert mags.max() <= amp * (1 + 1e-12) and mags.max() >= 0.99 * amp
    steps = np.abs(np.diff(np.r_[0.0, mags, 0.0]))
    assert steps.max() <= amp * math.pi / (2 * RAMP) * DT * (1 + 1e-6)
    assert len(p) >= round((2 * RAMP + HOLD) / DT) - 2  # the whole pulse, not a spike
    np.testing.assert_allclose(p / mags[:, None], np.tile(direction, (len(p), 1)), atol=1e-9)


def _report(tmp_path) -> dict:
    (path,) = tmp_path.glob("bringup-*.json")
    (text,) = tmp_path.glob("bringup-*.txt")
    assert path.stem == text.stem and "RESULT:" in text.read_text()
    return json.loads(path.read_text())


@pytest.mark.parametrize("device", ["replay", "sim"])
def test_bringup_passes_and_sends_only_small_smooth_pulses(tmp_path, captured, capsys, device):
    """Scripted answers r, y, y: the thumb's direction is pulsed twice (repeat), the index's
    once; each device gets exactly those pulses, each at most 0.5 N, ramped, along the
    direction announced; the report is saved with the date. On replay devices, and on sim
    fingers that the pulses move."""
    argv = ["bringup", str(GRASP_PROFILE), *FAST, "--device", device, "--answers", "ryy"]
    code = main([*argv, "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "RESULT: PASS (devices, limits and workspace, 2 of 2 directions)" in out
    assert out.count("felt in that direction? [y/n/r]") == 3
    report = _report(tmp_path)
    assert report["passed"] is True and report["failures"] == []
    (session,) = captured
    for i, (dev, row, n) in enumerate(zip(session.devices, report["pulses"], (2, 1), strict=True)):
        assert row["finger"] == session.profile.finger_names[i] and row["answers"][-1] == "y"
        pulses = _pulses(dev.forces)
        assert len(pulses) == n, f"finger {i}: {len(pulses)} pulses"
        for p in pulses:
            _check_pulse(p, np.array(row["world"]))  # identity mounts: world = device frame
        assert row["peak_sent_n"] == pytest.approx(MAX_PULSE_N)
        assert row["peak_other_fingers_n"] == 0.0
        assert not dev.enabled and dev.last_force.tolist() == [0.0, 0.0, 0.0]
    assert [r["finger"] for r in report["positions"]] == ["thumb", "index"]
    # Saved with the date: in the files' names and in the text.
    stamp = datetime.datetime.fromisoformat(report["date_utc"])
    (text,) = tmp_path.glob(f"bringup-grasp-stiffness-{stamp:%Y%m%d-%H%M%S}.txt")
    assert f"{stamp:%Y-%m-%d %H:%M:%S} UTC" in text.read_text().splitlines()[0]


def test_bringup_fails_when_a_direction_is_not_felt(tmp_path, captured, capsys):
    code = main(["bringup", str(GRASP_PROFILE), *FAST, "--answers", "yn", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 1
    assert "RESULT: FAIL" in out and "index direction 1: not felt in that direction" in out
    report = _report(tmp_path)
    assert report["passed"] is False
    assert [r["result"] for r in report["pulses"]] == ["pass", "fail"]


def test_answers_from_stdin_and_running_out_of_them(tmp_path, captured, capsys, monkeypatch):
    monkeypatch.setattr("sys.stdin", io.StringIO("maybe\ny\n"))  # one bad line, asked again
    code = main(["bringup", str(GRASP_PROFILE), *FAST, "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 1 and "answer y, n or r" in out
    assert "(end of input)" in out and "index direction 1: no answer" in out
    assert [r["answers"] for r in _report(tmp_path)["pulses"]] == [["y"], [""]]


def test_a_released_deadman_holds_the_pulse_back_and_fails_without_asking(
    tmp_path, grasp_data, write_profile, captured, capsys
):
    """The pulse goes through the safety chain: a deadman never pressed keeps the thumb's
    device at zero force, and the bring-up says why instead of asking."""
    grasp_data["fingers"][0]["buttons"] = [{"button": 0, "role": "deadman"}]
    profile = write_profile(grasp_data)
    code = main(["bringup", str(profile), *FAST, "--answers", "y", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 1
    assert "hold button 0 (deadman) down" in out
    assert "thumb direction 1: the safety chain let at most 0.000 N of 0.5 N through" in out
    assert out.count("felt in that direction?") == 1  # only the index was asked
    thumb, index = captured[0].devices
    assert not thumb.forces.any() and len(_pulses(index.forces)) == 1


@pytest.mark.parametrize("backend", ["hid", "usb"])
def test_bringup_on_emulated_devices(tmp_path, captured, capsys, monkeypatch, backend):
    """Through the hid or usb backend's reports to the device emulator: the force the
    emulated motors exert never exceeds 0.5 N (plus the current's quantisation)."""
    from hapticd_drivers.emulator import DeltaEmulator

    felt: dict[int, list] = {}
    real = DeltaEmulator.output_report

    def spy(self, data):
        real(self, data)
        felt.setdefault(id(self), []).append(self.end_effector_force())

    monkeypatch.setattr(DeltaEmulator, "output_report", spy)
    args = ["bringup", str(GRASP_PROFILE), *FAST, "--device", backend, "--emulate"]
    code = main([*args, "--answers", "yy", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 0, out
    assert f"thumb: {backend}" in out and "EMU-thumb" in out
    assert len(felt) == 2
    for forces in felt.values():
        mags = np.linalg.norm(np.array(forces), axis=1)
        assert 0.45 < mags.max() <= MAX_PULSE_N * 1.02


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--pulse-n", "0.6"], "amplitude is in (0, 0.5] N"),
        (["--pulse-n", "-1"], "amplitude is in (0, 0.5] N"),
        (["--answers", "yx"], "expected answers y"),
        (["--live-s", "-1"], "expected 0 to 3600 s"),
    ],
)
def test_bad_arguments_are_refused(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bringup", str(GRASP_PROFILE), *argv])
    assert exc.value.code == 2 and message in capsys.readouterr().err


def test_a_bad_profile_is_bad_input(tmp_path, capsys):
    code = main(["bringup", str(GRASP_PROFILE), "--set", "safety.max_force_n=-1"])
    assert code == 2 and "safety.max_force_n" in capsys.readouterr().err
    assert not list(tmp_path.glob("bringup-*"))


def test_the_report_goes_to_the_profiles_recording_directory(tmp_path, capsys):
    where = tmp_path / "reports"
    args = [*FAST, "--answers", "yy", "--set", f"recording.directory={where}"]
    assert main(["bringup", str(GRASP_PROFILE), *args]) == 0
    assert len(list(where.glob("bringup-grasp-stiffness-*.json"))) == 1
    assert f"saved: {where}" in capsys.readouterr().out


# -- on the fake Force Dimension SDK ----------------------------------------------------------


def _sent(lib, j: int) -> np.ndarray:
    """Every force fake device j applied, (n, 3) N (its own frame)."""
    buf = (ctypes.c_double * (3 * 65536))()
    n = lib.fake_force_log(j, buf, 65536)
    assert n < 65536, "the fake's force log is full: the test would miss forces"
    return np.frombuffer(buf, dtype=float, count=3 * n).reshape(n, 3).copy()


def test_bringup_on_the_fake_sdk_with_mounted_devices(tmp_path, libdhd, capsys):
    """Two mounted dhd devices with effector masses: each device gets one pulse, in its own
    frame R^T d of the world direction announced, at most 0.5 N and ramped."""
    lib_path, lib = libdhd
    lib.fake_reset(2)
    _, profile = _dhd_profile(tmp_path, lib_path)
    code = main(["bringup", profile, *FAST, "--answers", "yy", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "thumb: dhd omega.3 10001: calibrated" in out
    assert "effector mass 0.2 kg with gravity compensation" in out
    report = _report(tmp_path)
    assert [d["calibrated"] for d in report["devices"]] == [True, True]
    for j, row in enumerate(report["pulses"]):
        R = _mount(row["finger"]).rotation
        np.testing.assert_allclose(R.T @ row["world"], row["device"], atol=1e-12)
        (p,) = _pulses(_sent(lib, j))
        _check_pulse(p, np.array(row["device"]))
        assert lib.fake_is_enabled(j) == 0 and lib.fake_is_open(j) == 0


def test_bringup_fails_on_an_uncalibrated_device_and_never_enables_forces(tmp_path, libdhd, capsys):
    lib_path, lib = libdhd
    lib.fake_reset(2)
    lib.fake_set_calibrated(1, 0)
    _, profile = _dhd_profile(tmp_path, lib_path, serials=True)
    code = main(["bringup", profile, *FAST, "--answers", "yy", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 1
    assert "index: dhd omega.3 10002: NOT CALIBRATED: run hapticd calibrate PROFILE" in out
    assert "index: device 10002 is not known to be calibrated" in out
    assert "skipped (the devices failed)" in out and "felt in that direction" not in out
    assert (
        "enable 0 1" not in lib.fake_log().decode() and "enable 1 1" not in lib.fake_log().decode()
    )
    for j in range(2):
        assert not _sent(lib, j).any()
        assert lib.fake_is_enabled(j) == 0 and lib.fake_is_open(j) == 0
    report = _report(tmp_path)
    assert report["passed"] is False and [d["calibrated"] for d in report["devices"]] == [
        True,
        False,
    ]


def test_a_device_unplugged_during_the_bringup_ends_it_in_a_fault_at_zero_force(
    tmp_path, libdhd, capsys, monkeypatch
):
    """The index's USB cable pulled at tick 200 (before the pulses): the loop latches the
    fault naming the device, every force goes to zero, and the bring-up fails with it."""
    from tests.conftest import AtTick

    lib_path, lib = libdhd
    lib.fake_reset(2)
    _, profile = _dhd_profile(tmp_path, lib_path, serials=True)
    real = bringup_module.build_session

    def build(*a, **kw):
        s = real(*a, **kw)
        s.renderer.insert(AtTick(200, lambda f: lib.fake_unplug(1)), after="contact")
        return s

    monkeypatch.setattr(bringup_module, "build_session", build)
    code = main(["bringup", profile, *FAST, "--answers", "yy", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 3, out
    assert "FAULT at tick 200" in out and "unplugged" in out
    assert "dhd omega.3 index 1, serial 10002: lost" in out
    assert "RESULT: FAIL" in out and "felt in that direction" not in out
    assert _report(tmp_path)["fault"]["tick"] == 200
    assert lib.fake_is_enabled(0) == 0 and lib.fake_is_open(0) == 0
    assert not _sent(lib, 0).any()  # no pulse had started


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_on_a_terminal_positions_refresh_until_enter_and_answers_are_typed(tmp_path, monkeypatch):
    """stdin and stdout terminals (stdin a pseudo-terminal): the position lines are redrawn
    in place until Enter (long before --live-s), then each answer is a typed line."""
    out = _Terminal()
    monkeypatch.setattr("sys.stdout", out)
    master, slave = os.openpty()
    stdin = os.fdopen(slave, "r")

    def type_later() -> None:
        # Enter only once the lines have been redrawn in place (whatever the machine's
        # speed): the test sees a refresh, then the final redraw that Enter brings.
        # Each answer likewise waits for its question.
        deadline = time.monotonic() + 20.0
        for seen, times, typed in (
            ("\x1b[2F", 1, b"\n"),
            ("[y/n/r]", 1, b"y\n"),
            ("[y/n/r]", 2, b"n\n"),
        ):
            while out.getvalue().count(seen) < times:
                if time.monotonic() > deadline:
                    return  # the assertions below say what was missing
                time.sleep(0.01)
            os.write(master, typed)

    typist = threading.Thread(target=type_later)
    typist.start()
    ap = argparse.ArgumentParser()
    bringup_module.add_arguments(ap)
    ns = ap.parse_args(
        [str(GRASP_PROFILE), "--unpaced", "--no-realtime", "--live-s", "60", "--out", str(tmp_path)]
    )
    ns.set = None
    t0 = time.monotonic()
    try:
        code = bringup_module.bringup(ns, stdin=stdin)
    finally:
        typist.join(timeout=10)
        stdin.close()
        os.close(master)
    assert time.monotonic() - t0 < 30  # Enter ended the live view, not --live-s
    text = out.getvalue()
    assert code is bringup_module.Outcome.FAIL
    assert "index direction 1: not felt in that direction" in text
    assert "(live for 60 s; Enter goes on)" in text
    assert text.count("\x1b[2F") >= 2  # redrawn in place, two lines up
    saved = next(tmp_path.glob("*.txt")).read_text()
    assert "\x1b" not in saved and saved.count("  thumb  world (") == 1
    assert [r["answers"] for r in _report(tmp_path)["pulses"]] == [["y"], ["n"]]
