"""End to end: the `hapticd` command on the bundled profile, as a user runs it."""

import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from hapticd import recording
from hapticd.cli import main
from tests.conftest import GRASP_PROFILE, ROOT, wait_for

SUMMARY_KEYS = {
    "ticks",
    "rate_hz",
    "period_error_us",
    "overruns",
    "tick_compute_us",
    "allocator",
    "max_rendered_force_n",
}
LIMIT = 8.0  # safety.max_force_n in the bundled profile


def hapticd_cmd():
    """The command line of this checkout's hapticd (not whichever is first on PATH)."""
    return [sys.executable, "-m", "hapticd"]


def check_grasp_recording(rec, limit=LIMIT):
    t = rec["t"]
    f = rec["device_force"]
    mag = np.linalg.norm(f, axis=2)
    pinch = (t > 2.6) & (t < 5.4)
    after = t > 6.4
    assert np.all(rec["in_contact"][pinch] == 1)
    assert np.all(mag[pinch] > 0.3), "both fingers feel the squeeze"
    assert np.all(mag[after] == 0), "no force after release"
    assert np.all(mag[rec["in_contact"] == 0] == 0), "no force out of contact"
    assert mag.max() <= limit * (1 + 1e-12)
    assert np.all(np.isfinite(f))
    # Rendered force lies along the finger's one actuated direction: its rows of M_a lam_a.
    np.testing.assert_allclose(
        np.linalg.norm(rec["rendered_force"], axis=2), np.abs(rec["lam_a"]), atol=1e-12
    )
    # The thumb is pushed toward -x (out of the cube), the index toward +x.
    assert np.all(f[pinch, 0, 0] < 0) and np.all(f[pinch, 1, 0] > 0)


def test_unpaced_run_summary_and_recording(tmp_path, capsys):
    s_path, r_path = tmp_path / "s.json", tmp_path / "r.hrec"
    rc = main(
        [
            "run",
            str(GRASP_PROFILE),
            "--unpaced",
            "--summary-json",
            str(s_path),
            "--record",
            str(r_path),
        ]
    )
    assert rc == 0
    out = capsys.readouterr().out
    assert "allocator       if" in out and "trajectory ended" in out
    summary = json.loads(s_path.read_text())
    assert summary.keys() >= SUMMARY_KEYS
    assert summary["allocator"] == "if"
    rec = recording.read(r_path)
    assert rec.ticks == summary["ticks"]
    check_grasp_recording(rec)
    assert summary["max_rendered_force_n"] == pytest.approx(
        np.linalg.norm(rec["device_force"], axis=2).max(), abs=1e-6
    )


@pytest.mark.slow
@pytest.mark.timing(
    "checks real-time pacing: the achieved rate within 3 % of 1 kHz and the recorded "
    "wall-clock span of the ticks within 0.2 s of the nominal one"
)
def test_paced_subprocess_run_is_real_time_and_matches_unpaced(tmp_path):
    s_path, r_path = tmp_path / "s.json", tmp_path / "r.hrec"
    proc = subprocess.run(
        [
            *hapticd_cmd(),
            "run",
            str(GRASP_PROFILE),
            "--summary-json",
            str(s_path),
            "--record",
            str(r_path),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr
    assert "period error" in proc.stdout
    s = json.loads(s_path.read_text())
    assert s.keys() >= SUMMARY_KEYS
    assert {"target", "achieved"} <= s["rate_hz"].keys()
    assert {"p50", "p99", "max"} <= s["period_error_us"].keys() == s["tick_compute_us"].keys()
    assert s["rate_hz"]["target"] == 1000
    assert abs(s["rate_hz"]["achieved"] - 1000) / 1000 < 0.03
    rec = recording.read(r_path)
    assert s["recording"]["dropped"] == 0 and rec.ticks == s["ticks"] == 7801
    check_grasp_recording(rec)
    # Wall-clock tick times follow the nominal ones (real-time pacing).
    assert abs((rec["t_wall"][-1] - rec["t_wall"][0]) - (rec["t"][-1] - rec["t"][0])) < 0.2
    # Apart from timing, identical to the unpaced run.
    u_path = tmp_path / "u.hrec"
    assert main(["run", str(GRASP_PROFILE), "--unpaced", "-q", "--record", str(u_path)]) == 0
    unpaced = recording.read(u_path)
    for key in (
        "device_pos",
        "proxy_pos",
        "contact_force",
        "rendered_force",
        "device_force",
        "lam_a",
    ):
        np.testing.assert_array_equal(rec[key], unpaced[key], err_msg=key)


@pytest.mark.slow
def test_sigterm_stops_with_summary_and_exit_0(tmp_path, grasp_data, write_profile):
    s_path, r_path = tmp_path / "s.json", tmp_path / "r.hrec"
    # Held a minute after the trajectory: the run cannot end before the signal.
    for finger in grasp_data["fingers"]:
        finger["device"]["hold_s"] = 60.0
    proc = subprocess.Popen(
        [
            *hapticd_cmd(),
            "run",
            str(write_profile(grasp_data)),
            "--summary-json",
            str(s_path),
            "--record",
            str(r_path),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        # Wait for a few hundred recorded ticks (the writer flushes every 10 ms; a torn
        # last record is fine to read).
        def recorded() -> int:
            if not r_path.exists() or r_path.stat().st_size < 1000:
                return 0
            return recording.read(r_path).ticks

        wait_for(recorded, "300 recorded ticks", until=lambda n: n >= 300, poll_s=0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    s = json.loads(s_path.read_text())
    assert s["end_reason"] == "signal SIGTERM"
    assert s["ticks"] > 300
    assert recording.read(r_path).ticks == s["ticks"]


def test_check_accepts_the_bundled_profile(capsys):
    assert main(["check", str(GRASP_PROFILE)]) == 0
    assert "OK" in capsys.readouterr().out


def test_check_rejects_a_misspelled_key_naming_file_and_key(grasp_data, write_profile, capsys):
    grasp_data["rendering"]["alocator"] = grasp_data["rendering"].pop("allocator")
    path = write_profile(grasp_data)
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert str(path.resolve()) in err
    assert "rendering.alocator: unknown key; did you mean 'allocator'?" in err


def test_missing_or_mismatched_trajectory_names_the_key(
    grasp_data, write_profile, tmp_path, capsys
):
    grasp_data["fingers"][0]["device"]["trajectory"] = "nowhere.hrec"
    assert main(["check", str(write_profile(grasp_data))]) == 2
    err = capsys.readouterr().err
    assert "fingers[0:thumb].device.trajectory" in err and "nowhere.hrec" in err
    grasp_data["fingers"][0]["device"]["trajectory"] = "builtin:grasp-stiffness"
    grasp_data["fingers"][0]["device"]["finger"] = "pinky"
    assert main(["run", str(write_profile(grasp_data)), "--unpaced"]) == 2
    err = capsys.readouterr().err
    assert "fingers[0:thumb].device.finger" in err and "'pinky'" in err
    grasp_data["fingers"][0]["device"].pop("finger")
    grasp_data["fingers"][0]["device"]["trajectory"] = "builtin:nope"
    assert main(["check", str(write_profile(grasp_data))]) == 2
    assert "no bundled trajectory 'nope'" in capsys.readouterr().err
    (tmp_path / "junk.hrec").write_bytes(b"junk")
    grasp_data["fingers"][0]["device"]["trajectory"] = "junk.hrec"
    assert main(["check", str(write_profile(grasp_data))]) == 2
    assert "bad magic" in capsys.readouterr().err


def test_relative_trajectory_path_and_duration(grasp_data, write_profile, tmp_path):
    # A recording made by the loop is itself a trajectory the replay device plays.
    first = tmp_path / "first.hrec"
    assert main(["run", str(GRASP_PROFILE), "--unpaced", "-q", "--record", str(first)]) == 0
    for f in grasp_data["fingers"]:
        f["device"]["trajectory"] = "first.hrec"
    grasp_data["rendering"]["allocator"] = "pinv"
    second = tmp_path / "second.hrec"
    s_path = tmp_path / "s.json"
    assert (
        main(
            [
                "run",
                str(write_profile(grasp_data)),
                "--unpaced",
                "-q",
                "--record",
                str(second),
                "--duration",
                "4",
                "--summary-json",
                str(s_path),
            ]
        )
        == 0
    )
    s = json.loads(s_path.read_text())
    assert s["ticks"] == 4000 and s["end_reason"] == "duration reached" and s["allocator"] == "pinv"
    a, b = recording.read(first), recording.read(second)
    np.testing.assert_allclose(b["device_pos"], a["device_pos"][:4000], atol=1e-15)
    # pinv renders less of the squeeze than IF with tilted actuators (cos^2 vs 1).
    pinch = (a["t"][:4000] > 2.6) & (a["t"][:4000] < 3.9)
    ratio = np.abs(b["lam_a"][pinch]) / np.abs(a["lam_a"][:4000][pinch])
    np.testing.assert_allclose(ratio, np.cos(np.radians(30)) ** 2, rtol=0.05)


def test_bad_duration_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["run", str(GRASP_PROFILE), "--duration", "-1"])
    assert exc.value.code == 2
    assert "positive number of seconds" in capsys.readouterr().err


def test_python_dash_m_entry_point():
    env = dict(os.environ)
    proc = subprocess.run(
        [sys.executable, "-m", "hapticd", "--version"],
        capture_output=True,
        text=True,
        env=env,
        timeout=30,
    )
    assert proc.returncode == 0 and "hapticd 0.1.0" in proc.stdout


@pytest.mark.parametrize("allocator", ["if", "pinv", "adaptive"])
def test_recorded_accuracy_shows_what_each_allocator_keeps(
    grasp_data, write_profile, tmp_path, allocator
):
    grasp_data["rendering"]["allocator"] = allocator
    path = tmp_path / f"{allocator}.hrec"
    assert (
        main(["run", str(write_profile(grasp_data)), "--unpaced", "-q", "--record", str(path)]) == 0
    )
    rec = recording.read(path)
    check_grasp_recording(rec)
    pinch = (rec["t"] > 2.6) & (rec["t"] < 5.4)
    internal = rec["residual_internal"][pinch]
    if allocator == "pinv":
        # The squeeze is rendered at cos^2(30 deg): a quarter is lost.
        assert np.all(internal > 0.1)
    else:
        # IF renders the squeeze exactly; adaptive stays on IF while squeezing a fixed cube.
        assert np.all(internal < 1e-9)
    assert np.all(rec["residual_total"][pinch] > 0)  # underactuated: never exact overall
    assert np.all(rec["amplification"][pinch] > 0.5)
    if allocator == "adaptive":
        assert rec["alpha"].max() < 0.05
    else:
        assert np.all(rec["alpha"] == 0)
