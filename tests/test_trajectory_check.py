"""``hapticd check`` refuses every trajectory ``hapticd run`` refuses, with one message
naming the profile, the key (``fingers[0:thumb].device.trajectory``), the trajectory's
file and what is wrong with which sample: the replay and sim trajectories, the usb and
hid backends' emulator paths and the bundled ones go through one check."""

from __future__ import annotations

import numpy as np
import pytest

from hapticd import recording
from hapticd.cli import main
from hapticd.daemon.build import BUILTIN, builtin_trajectory, load_trajectories
from hapticd.profile import load_profile

FINGERS = ["thumb", "index"]


def _times(n: int) -> np.ndarray:
    return np.arange(n) * 0.01


def _bad(kind: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(times, positions (N, 2, 3)) of a trajectory wrong in one way for the thumb, and a
    fragment the message must hold."""
    t, x = _times(5), np.zeros((5, 2, 3))
    if kind == "nan position":
        x[3, 0, 1] = np.nan
        return t, x, "sample 3 (t = 0.03 s) has a non-finite position"
    if kind == "inf position":
        x[1, 0, 2] = -np.inf
        return t, x, "sample 1 (t = 0.01 s) has a non-finite position"
    if kind == "nan time":
        t[2] = np.nan
        return t, x, "sample 2 has a non-finite time"
    if kind == "duplicate time":
        t[3] = t[2]
        return t, x, "sample 3 (t = 0.02 s) repeats sample 2"
    if kind == "decreasing time":
        t[4] = 0.0
        return t, x, "sample 4 (t = 0 s) goes back from sample 3"
    if kind == "one sample":
        return t[:1], x[:1], "1 sample(s); a trajectory needs at least 2"
    if kind == "no sample":
        return t[:0], x[:0], "0 sample(s); a trajectory needs at least 2"
    raise AssertionError(kind)


KINDS = [
    "nan position",
    "inf position",
    "nan time",
    "duplicate time",
    "decreasing time",
    "one sample",
    "no sample",
]


def _profile(grasp_data, write_profile, tmp_path, kind: str, backend: str):
    t, x, expect = _bad(kind)
    traj = tmp_path / "bad.hrec"
    recording.write(traj, {"t": t, "device_pos": x}, recording.trajectory_fields(2), FINGERS)
    for f in grasp_data["fingers"]:
        dev = f["device"]
        dev["backend"] = backend
        dev["trajectory"] = str(traj)
        if backend in ("usb", "hid"):
            dev.pop("max_force_n")
    return write_profile(grasp_data), traj, expect


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("backend", ["replay", "sim", "usb"])
def test_check_refuses_what_run_refuses_naming_key_and_file(
    grasp_data, write_profile, tmp_path, capsys, kind, backend
):
    path, traj, expect = _profile(grasp_data, write_profile, tmp_path, kind, backend)
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"hapticd: {path}: fingers[0:thumb].device.trajectory: {traj}"), err
    assert "finger 'thumb'" in err and expect in err, err
    assert "Traceback" not in err
    # run says the same thing, before any device opens
    extra = ["--emulate"] if backend == "usb" else []
    assert main(["run", str(path), "--unpaced", "--no-socket", "-q", *extra]) == 2
    assert capsys.readouterr().err == err


def test_a_recording_of_the_loop_is_checked_for_its_finger(grasp_data, write_profile, tmp_path):
    """Only the finger a device plays is checked: a NaN on the index's column does not
    refuse the thumb's replay of the same file, and names the index where it plays."""
    t, x = _times(5), np.zeros((5, 2, 3))
    x[2, 1, 0] = np.nan
    traj = tmp_path / "rec.hrec"
    recording.write(traj, {"t": t, "device_pos": x}, recording.trajectory_fields(2), FINGERS)
    grasp_data["fingers"][0]["device"]["trajectory"] = str(traj)
    profile = load_profile(write_profile(grasp_data))
    assert load_trajectories(profile)[0] is not None
    grasp_data["fingers"][1]["device"]["trajectory"] = str(traj)
    with pytest.raises(Exception, match=r"fingers\[1:index\]\.device\.trajectory: .*sample 2"):
        load_trajectories(load_profile(write_profile(grasp_data)))


def test_every_bundled_trajectory_passes_the_check():
    base = builtin_trajectory("grasp-stiffness").parent
    names = sorted(p.name.removesuffix(recording.SUFFIX) for p in base.glob("*.hrec"))
    assert names
    from hapticd_drivers.trajectory import check_samples

    for name in names:
        rec = recording.read(builtin_trajectory(name))
        for j in range(len(rec.fingers)):
            t, _x, _ = check_samples(rec["t"], rec["device_pos"][:, j, :])
            assert t.size >= 2 and np.all(np.diff(t) > 0), f"{BUILTIN}{name}"
