"""Rehearsal without hardware: a device that plays its path again and again (``repeat``),
the bundled rehearsal profiles (a simulated hand that touches the cube for as long as the
daemon runs), the reduced stiffness experiment run against one with every trial answered
over the socket, and a runner that says the daemon stopped when it did."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from hapticd_drivers.base import DeviceError, DeviceState
from hapticd_drivers.replay import KEPT_FORCES, ReplayDevice
from hapticd_drivers.sim import SimulatedFinger

from hapticd import recording
from hapticd.daemon.session import build_session
from hapticd.experiment import load_experiment, make_plan
from hapticd.experiment import runner as rn
from hapticd.loop.commands import SetParam
from hapticd.profile import load_profile
from hapticd.protocol import ProtocolError
from tests.conftest import ROOT, wait_for
from tests.test_runner import (
    HAPTICD,
    Answerer,
    Daemon,
    finish,
    periodic_grasp,
    rows,
    setup_files,
)

REHEARSE_GRASP = ROOT / "configs" / "rehearse-grasp.yaml"
REHEARSE_LIFT = ROOT / "configs" / "rehearse-lift.yaml"
STIFFNESS = ROOT / "configs" / "experiments" / "stiffness-jnd.yaml"


def _closed_path(n: int = 11) -> tuple[np.ndarray, np.ndarray]:
    """A 1 s path out along x and back (ends where it starts), n samples."""
    t = np.linspace(0.0, 1.0, n)
    x = np.zeros((n, 3))
    x[:, 0] = 0.01 * np.sin(np.pi * t)
    return t, x


def test_a_repeated_path_plays_again_and_never_finishes():
    t, x = _closed_path()
    now = [0.0]
    dev = ReplayDevice(t, x, clock=lambda: now[0], repeat=True)
    once = ReplayDevice(t, x, clock=lambda: now[0])
    state, other = DeviceState(), DeviceState()
    dev.open()
    once.open()
    for s in (0.25, 0.5, 0.9):
        now[0] = s
        dev.read_state(state)
        first = state.position.copy()
        now[0] = s + 7.0  # seven cycles later: the same place
        dev.read_state(state)
        np.testing.assert_allclose(state.position, first, atol=1e-12)
        once.read_state(other)
        np.testing.assert_allclose(other.position, x[-1])  # played once: held at its end
    assert not dev.finished and once.finished


def test_a_repeated_path_must_close():
    t, x = _closed_path()
    x[-1, 2] = 0.002  # ends 2 mm above where it starts
    with pytest.raises(DeviceError, match=r"must end where it starts .* 2 mm away"):
        ReplayDevice(t, x, repeat=True)
    with pytest.raises(DeviceError, match="must end where it starts"):
        SimulatedFinger(t, x, repeat=True)
    ReplayDevice(t, x)  # played once, it may end anywhere


def test_check_names_the_finger_whose_repeated_path_does_not_close(tmp_path, capsys):
    from hapticd.cli import main

    path = periodic_grasp(tmp_path / "open.hrec", 3)
    rec = recording.read(path)
    pos = rec["device_pos"].copy()
    pos[:, :, 2] += np.linspace(0.0, 0.004, len(pos))[:, None]  # drifts 4 mm up
    recording.write(path, {"t": rec["t"], "device_pos": pos}, rec.fields, rec.fingers)
    data = yaml.safe_load(REHEARSE_GRASP.read_text())
    for f in data["fingers"]:
        f["device"]["trajectory"] = str(path)
    profile = tmp_path / "open.yaml"
    profile.write_text(yaml.safe_dump(data))
    assert main(["check", str(profile)]) == 2
    err = capsys.readouterr().err
    assert "fingers[0:thumb].device" in err and "must end where it starts" in err
    assert "4 mm away" in err


def test_a_device_on_a_repeated_path_keeps_a_bounded_history_of_forces():
    t, x = _closed_path()
    now = [0.0]
    dev = ReplayDevice(t, x, clock=lambda: now[0], repeat=True)
    dev.open()
    dev.enable_forces(True)
    state = DeviceState()
    n = 3 * KEPT_FORCES + 5
    for k in range(n):
        now[0] = k * 1e-3
        dev.read_state(state)
        dev.write_force(np.array([k * 1e-6, 0.0, 0.0]))
    kept = dev.forces
    assert KEPT_FORCES // 2 <= len(kept) <= KEPT_FORCES
    # The latest, in order, ending with the last one written.
    assert kept[-1, 0] == pytest.approx((n - 1) * 1e-6)
    assert np.all(np.diff(kept[:, 0]) > 0)
    assert dev.force_times[-1] == pytest.approx((n - 1) * 1e-3)


@pytest.mark.parametrize(
    ("profile", "seconds", "touches", "lifted_mm"),
    [(REHEARSE_GRASP, 9.0, 4, None), (REHEARSE_LIFT, 13.0, 4, 20.0)],
)
def test_the_rehearsal_hand_touches_the_cube_every_cycle_while_the_run_lasts(
    tmp_path, profile, seconds, touches, lifted_mm
):
    """Unpaced, well past where a path played once would end: each touch begins and ends
    (the experiment's intervals end on the release), every cycle, on both fingers; the
    lift raises the cube each time."""
    prof = load_profile(profile)  # its kernels compiled, from the run's cache
    assert prof.rendering.kernels == "auto"
    assert all(f.device.backend == "sim" and f.device.repeat for f in prof.fingers)
    # No hardware: no wall-clock fault ends a rehearsal on a busy laptop.
    assert prof.safety.watchdog_s is None and prof.loop.max_consecutive_overruns == 0
    session = build_session(prof, paced=False, duration_s=seconds, record_path=tmp_path / "r.hrec")
    session.run()
    assert session.loop.end_reason == "duration reached" and session.loop.safety.fault is None
    rec = recording.read(tmp_path / "r.hrec")
    both = rec["in_contact"].all(axis=1).astype(int)
    begins = np.flatnonzero(np.diff(both) == 1)
    ends = np.flatnonzero(np.diff(both) == -1)
    assert len(begins) == touches and len(ends) >= touches - 1
    if lifted_mm is not None:
        z = rec["object_pos"][:, 2]
        for b, e in zip(begins, ends, strict=False):
            assert z[b : e + 1].max() > lifted_mm * 1e-3  # lifted within each touch
            assert abs(z[e + 1]) < 1e-3  # and set down before the release


def test_a_command_to_a_daemon_whose_loop_ended_says_it_stopped_and_why():
    session = build_session(load_profile(REHEARSE_GRASP), paced=False, duration_s=0.01)
    session.run()
    with pytest.raises(ProtocolError, match="the daemon stopped: duration reached") as got:
        session.apply(SetParam("stiffness_n_per_m", 70.0))
    assert got.value.code == "stopped"


def test_the_runner_says_the_daemon_stopped_when_its_trajectory_ended(tmp_path):
    """The newcomer's mistake: a daemon on a path played once (here 20 grasps, 10 s); the
    first question is left unanswered, so the daemon's run ends during the trial: the
    runner ends with the daemon's reason, the trial stored incomplete."""
    profile, exp_path = setup_files(tmp_path, one_condition=True)
    data = yaml.safe_load(profile.read_text())
    short = periodic_grasp(tmp_path / "short.hrec", 20)
    for f in data["fingers"]:
        f["device"]["trajectory"] = str(short)
    profile.write_text(yaml.safe_dump(data, sort_keys=False))
    sock = tmp_path / "d.sock"
    daemon = Daemon(profile, sock)
    try:
        code, _, err = finish(_runner(exp_path, tmp_path / "t.db", sock), 60)
    finally:
        daemon.close()
    assert code == 1
    assert "the daemon stopped: trajectory ended" in err
    assert "timeout" not in err and "tick boundary" not in err and "Traceback" not in err
    assert rows(tmp_path / "t.db", "incomplete")


def _runner(exp: object, db, sock, *extra: str) -> subprocess.Popen:
    """``hapticd experiment run`` of subject s1, reduced to the standard 60 and one
    repetition, answers over the socket only (no keys)."""
    args = ["experiment", "run", str(exp), "--subject", "s1", "--db", str(db)]
    args += ["--socket", str(sock), "--standards", "60", "--repetitions", "1", "--no-keys"]
    with open(db.with_suffix(".out"), "w") as out, open(db.with_suffix(".err"), "w") as err:
        proc = subprocess.Popen(
            [*HAPTICD, *args, *extra],
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=err,
            text=True,
            cwd=ROOT,
        )
    proc.db = db  # type: ignore[attr-defined]
    return proc


class RehearsalDaemon(Daemon):
    """``hapticd run configs/rehearse-grasp.yaml`` serving ``sock``, recording into ``recs``,
    its kernels as the file leaves them (auto): loaded from the run's cache, which the
    suite fills before its workers start (tests/conftest.py), so the daemon's 1 kHz tick
    takes a fraction of the core the Python kernels burnt beside the other tests; with no
    cache it renders in Python while a background compiler fills one."""

    def __init__(self, sock: Path, recs: Path) -> None:
        self.sock = sock
        self.log = open(sock.with_suffix(".log"), "w")  # noqa: SIM115
        args = ["run", str(REHEARSE_GRASP), "--socket", str(sock), "--record-dir", str(recs)]
        self.proc = subprocess.Popen(
            [*HAPTICD, *args],
            stdout=self.log,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
        )
        wait_for(self._ready, "the rehearsal daemon's socket", timeout_s=30)


@pytest.mark.slow
def test_the_reduced_stiffness_experiment_completes_against_the_rehearsal_daemon(tmp_path):
    """The bundled files as a newcomer runs them: `hapticd run configs/rehearse-grasp.yaml`
    and `hapticd experiment run configs/experiments/stiffness-jnd.yaml --standards 60
    --repetitions 1 --break-s 2`, every trial answered by a `respond` over the socket (as
    the subject page sends it). It lasts as long as the design does: 12 trials of two
    touches, a 1 s gap each, and its break between the two conditions (2 s, not the
    file's 60 s: a rehearsal's reduced design)."""
    sock, db = tmp_path / "d.sock", tmp_path / "t.db"
    daemon = RehearsalDaemon(sock, tmp_path / "recs")
    choice: dict[int, str] = {}

    def answer(pid: int) -> tuple[str, str]:
        choice[pid] = "yes" if pid % 2 else "no"
        return ("respond", choice[pid])

    try:
        proc = _runner(STIFFNESS, db, sock, "--break-s", "2")
        answers = Answerer(sock, answer)
        try:
            code, out, err = finish(proc, 600)
        finally:
            answers.close()
    finally:
        daemon.close()
    assert not answers.errors
    assert code == 0, err[-3000:]
    assert "12 trial(s) answered; 0 left: done" in out
    assert err.count("break: 2 s") == 1 and "the break is over" in err
    exp = rn.reduced(load_experiment(STIFFNESS), standards=[60.0], repetitions=1)
    plan = make_plan(exp, exp.subject_seed("s1"))
    got = rows(db)
    assert len(got) == len(plan) == 12
    assert all(r["status"] == "complete" and r["source"] == "respond" for r in got)
    for r in got:
        t = plan[r["plan_index"]]
        assert r["answer_second_more"] == (choice[t.index] == "yes")
        # Each interval recorded: its last touch, by both fingers, at the trial's value.
        paths = json.loads(r["recording"])
        assert len(paths) == 2
        for path, value in zip(paths, rn.interval_values(exp, t), strict=True):
            rec = recording.read(path)
            touching = rec["in_contact"].any(axis=1)
            last = np.flatnonzero(touching)[-1]
            first = np.flatnonzero(~touching[:last])[-1] + 1
            assert rec["in_contact"][first : last + 1].all()
            assert set(rec["stiffness_n_per_m"][first : last + 1].tolist()) == {value}
