"""End to end: the `hapticd` command on the bundled profile, as a user runs it."""

import inspect
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from hapticd import recording
from hapticd.__main__ import main as hapticd_main
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
    # 4000 ticks, then the zero force the shutdown sent (the run ended mid-grasp).
    assert b.ticks == 4001 and not b["device_force"][-1].any() and b["device_force"][-2].any()
    np.testing.assert_allclose(b["device_pos"][:4000], a["device_pos"][:4000], atol=1e-15)
    # pinv renders less of the squeeze than IF with tilted actuators (cos^2 vs 1).
    pinch = (a["t"][:4000] > 2.6) & (a["t"][:4000] < 3.9)
    ratio = np.abs(b["lam_a"][:4000][pinch]) / np.abs(a["lam_a"][:4000][pinch])
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


@pytest.mark.timing("the signal must land while the run is still starting")
@pytest.mark.parametrize("after_s", [0.0, 0.05, 0.3, 0.6])
def test_ctrl_c_while_a_run_starts_says_interrupted_not_a_traceback(after_s, tmp_path):
    """SIGINT at any instant of a run's start-up once hapticd's code runs (the command line
    loading, the profile, the build, the loop's start): a line saying so and the shell's
    SIGINT code before the run began, or the orderly stop of a run that began; never a
    traceback. (The child says when the interpreter's own start-up and the import of
    hapticd's entry point, which does nothing, are over: a signal before that is Python's.)"""
    import select

    boot = (
        "import os, sys; from hapticd.__main__ import main; os.write(2, b'go\\n'); sys.exit(main())"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", boot, "run", str(GRASP_PROFILE), "--unpaced", "--quiet"],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        ready, _, _ = select.select([proc.stderr], [], [], 30.0)
        assert ready, "the child did not start within 30 s"
        assert os.read(proc.stderr.fileno(), 3) == b"go\n"
        time.sleep(after_s)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    err = err.decode()
    frames = [line for line in err.splitlines() if line.lstrip().startswith("File ")]
    entry = f"line {inspect.getsourcelines(hapticd_main)[1]}, in main"
    if "Traceback" in err and all('"<string>"' in line or entry in line for line in frames):
        # The signal landed between the boot's write and main's try: the boot's own
        # bytecode or main's entry, Python's to report (a few instructions, seen under load).
        assert proc.returncode != 0, err
    else:
        assert "Traceback" not in err, err
        assert proc.returncode in (0, 130), (proc.returncode, err)
        if proc.returncode == 130:
            assert "hapticd: interrupted" in err, err


def _says_interrupted(boot: str, cwd) -> None:
    """``boot`` (Python that ends in hapticd's main, ``--help``) says it was interrupted:
    the shell's SIGINT code, one line, no traceback."""
    proc = subprocess.run(
        [sys.executable, "-c", boot, "--help"], cwd=cwd, capture_output=True, timeout=60
    )
    err = proc.stderr.decode()
    assert "Traceback" not in err, err
    assert proc.returncode == 130, (proc.returncode, err)
    assert "hapticd: interrupted" in err, err


def test_ctrl_c_while_the_handler_is_installed_says_interrupted(tmp_path):
    """A Ctrl-C on main's first instruction that looks at the SIGINT handler (a slow
    enum lookup, hit in CI) is the interruption too, not a traceback."""
    boot = (
        "import signal, sys\n"
        "def landed(signum):\n"
        "    raise KeyboardInterrupt\n"
        "signal.getsignal = landed\n"
        "from hapticd.__main__ import main\n"
        "sys.exit(main())\n"
    )
    _says_interrupted(boot, tmp_path)


def test_ctrl_c_inside_an_extensions_import_says_interrupted(tmp_path):
    """A Ctrl-C that an extension module's import turns into an ImportError (numpy's does,
    when the signal lands while it imports datetime) still reads as the interruption."""
    boot = (
        "import importlib.abc, os, signal, sys, time\n"
        "class Ext(importlib.abc.MetaPathFinder, importlib.abc.Loader):\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        import importlib.util\n"
        "        if name == 'hapticd.cli':\n"
        "            return importlib.util.spec_from_loader(name, self)\n"
        "    def create_module(self, spec):\n"
        "        return None\n"
        "    def exec_module(self, module):\n"
        "        try:\n"
        "            os.kill(os.getpid(), signal.SIGINT)\n"
        "            time.sleep(5)\n"
        "        except BaseException as exc:\n"
        "            raise ImportError('an extension could not import datetime') from exc\n"
        "sys.meta_path.insert(0, Ext())\n"
        "from hapticd.__main__ import main\n"
        "sys.exit(main())\n"
    )
    _says_interrupted(boot, tmp_path)
