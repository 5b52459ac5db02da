"""The daemon as a researcher runs it: a background process changed over its socket,
stopped by signals, reloaded by SIGHUP, killed with -9 while recording."""

from __future__ import annotations

import contextlib
import copy
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from hapticd import recording
from hapticd.allocation import METHODS
from hapticd.control import ControlClient
from hapticd.protocol import ProtocolError
from tests.conftest import GRASP_PROFILE, ROOT, wait_for


def start_daemon(tmp_path: Path, *args: str, profile: Path = GRASP_PROFILE, **popen) -> tuple:
    sock = tmp_path / "hapticd.sock"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "hapticd",
            "run",
            str(profile),
            "--socket",
            str(sock),
            "--record-dir",
            str(tmp_path),
            *args,
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **popen,
    )
    deadline = time.monotonic() + 20
    while True:
        with contextlib.suppress(OSError):
            client = ControlClient(sock)
            return proc, sock, client
        if proc.poll() is not None or time.monotonic() > deadline:
            _out, err = proc.communicate(timeout=10)
            pytest.fail(f"daemon did not come up (rc {proc.returncode}): {err}")
        time.sleep(0.05)


def finish(proc: subprocess.Popen, timeout_s: float = 20.0) -> tuple[int, str, str]:
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"daemon did not exit: {err}")
    return proc.returncode, out, err


def wait_gone(pid: int, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while Path(f"/proc/{pid}").exists():
        stat = Path(f"/proc/{pid}/stat").read_text() if Path(f"/proc/{pid}").exists() else ""
        if stat.rpartition(")")[2].split()[:1] == ["Z"]:
            return  # exited; its new parent reaps it
        assert time.monotonic() < deadline, f"process {pid} is still running"
        time.sleep(0.01)


def hold_after_the_trajectory(data: dict, hold_s: float = 60.0) -> dict:
    """The profile ``data`` with every finger held for ``hold_s`` s after its trajectory:
    a daemon that cannot end on its own before the test is done with it."""
    for finger in data["fingers"]:
        finger["device"]["hold_s"] = hold_s
    return data


def test_live_changes_over_the_socket_land_at_tick_boundaries_in_the_recording(
    tmp_path, grasp_data, write_profile
):
    """The daemon as an experiment script drives it: stiffness and allocator changed over
    the socket while it records, SIGTERM, the changes found at their ticks."""
    rec_path = tmp_path / "trial.hrec"
    profile = write_profile(hold_after_the_trajectory(grasp_data))
    proc, _sock, c = start_daemon(tmp_path, "--no-realtime", profile=profile)
    with c:
        # Start recording while the fingers approach (starting the writer process can take
        # seconds on a loaded machine), then change the stiffness early in the squeeze
        # (ticks 2250-5750 of the bundled grasp).
        wait_for(c.status, "the approach", until=lambda s: s["tick"] > 1000)
        started = c.record_start(rec_path)
        wait_for(c.status, "the grasp", until=lambda s: s["tick"] > 2400)
        k_stiff = c.set("stiffness_n_per_m", 90.0)["applied_at_tick"]
        wait_for(c.status, "50 ticks more", until=lambda s: s["tick"] >= k_stiff + 50)
        k_alloc = c.call("set", param="allocator", value="pinv")["applied_at_tick"]
        wait_for(c.status, "50 ticks more", until=lambda s: s["tick"] >= k_alloc + 50)
        k_stiff2 = c.set("stiffness_n_per_m", 30.0)["applied_at_tick"]
        assert c.status()["recording"]["path"] == str(rec_path)
        wait_for(c.status, "100 ticks more", until=lambda s: s["tick"] >= k_stiff2 + 100)
    proc.send_signal(signal.SIGTERM)
    rc, out, err = finish(proc)
    assert rc == 0, err
    assert "ended: signal SIGTERM" in out
    rec = recording.read(rec_path)
    assert rec.torn_bytes == 0 and rec.ticks > 200
    ticks = np.rint(rec["t"] * 1000).astype(int)
    assert ticks[0] == started["applied_at_tick"]
    np.testing.assert_array_equal(np.diff(ticks), 1)  # every tick, none dropped
    row = {int(k): i for i, k in enumerate(ticks)}
    k = rec["stiffness_n_per_m"]
    assert k[row[k_stiff] - 1] == 60.0 and k[row[k_stiff]] == 90.0
    assert k[row[k_stiff2] - 1] == 90.0 and k[row[k_stiff2]] == 30.0
    alloc = rec["allocator"]
    assert alloc[row[k_alloc] - 1] == METHODS.index("if")
    assert alloc[row[k_alloc]] == METHODS.index("pinv")
    seq = rec["control_seq"]
    assert np.count_nonzero(np.diff(seq.astype(int))) == 3
    assert {int(ticks[i + 1]) for i in np.flatnonzero(np.diff(seq.astype(int)))} == {
        k_stiff,
        k_alloc,
        k_stiff2,
    }
    # The physics used the new stiffness from that very tick: penetration is continuous,
    # so the contact force jumps by 90/60.
    f = np.linalg.norm(rec["contact_force"][:, 0], axis=1)
    i = row[k_stiff]
    assert f[i - 1] > 0.3
    assert f[i] / f[i - 1] == pytest.approx(1.5, rel=0.02)
    # SIGTERM: forces ramped to zero, and the recording was flushed to the last tick.
    dev = np.linalg.norm(rec["device_force"], axis=2).max(axis=1)
    assert dev[-1] == 0.0
    ramp = dev[-52:-1]
    assert ramp[0] > 0.1 and np.all(np.diff(ramp) <= 1e-3)  # at 30 N/m: 0.3-0.6 N squeezing


def test_sighup_reloads_and_an_invalid_profile_leaves_the_old_one_running(
    tmp_path, grasp_data, write_profile
):
    path = write_profile(grasp_data)
    proc, _sock, c = start_daemon(tmp_path, "--no-realtime", profile=path)
    with c:
        wait_for(c.status, "the loop", until=lambda s: s["tick"] > 100)
        grasp_data["scene"]["object"]["stiffness_n_per_m"] = 120.0
        write_profile(grasp_data)
        proc.send_signal(signal.SIGHUP)
        st = wait_for(c.status, "the reload", until=lambda s: s["reloads"])
        assert st["reloads"][0].startswith(f"reloaded {path} at tick")
        assert c.get("stiffness_n_per_m") == 120.0
        # A typo: rejected with the file and key named; the running profile stays.
        grasp_data["scene"]["object"]["stifness_n_per_m"] = 10.0
        write_profile(grasp_data)
        proc.send_signal(signal.SIGHUP)
        st = wait_for(c.status, "the second reload", until=lambda s: len(s["reloads"]) == 2)
        assert "reload rejected" in st["reloads"][1]
        assert "stifness_n_per_m" in st["reloads"][1] and str(path) in st["reloads"][1]
        tick = st["tick"]
        assert c.get("stiffness_n_per_m") == 120.0
        wait_for(
            c.status,
            "the loop going on",
            until=lambda s: s["tick"] > tick + 50 and s["fault"] is None,
        )
        # Over the socket: a profile that changes the devices needs a restart.
        bad = dict(grasp_data)
        del bad["scene"]["object"]["stifness_n_per_m"]
        bad["loop"] = {"rate_hz": 2000.0}
        other = write_profile(bad, "other.yaml")
        with pytest.raises(ProtocolError, match="loop settings changed") as exc:
            c.reload(other)
        assert exc.value.code == "bad_profile"
        c.stop()
    rc, _out, err = finish(proc)
    assert rc == 0, err
    assert "reload rejected" in err


def test_kill_9_of_the_daemon_loses_no_recorded_tick(tmp_path):
    rec_path = tmp_path / "crash.hrec"
    proc, _sock, c = start_daemon(tmp_path, "--no-realtime", "--record", str(rec_path))
    with c:
        st = wait_for(c.status, "ticks", until=lambda s: s["tick"] > 1500)
        writer = st["recording"]["writer_pid"]
        st = c.status()
        os.kill(proc.pid, signal.SIGKILL)
    finish(proc)
    wait_gone(writer)  # it drained the ring after its parent died, then exited
    rec = recording.read(rec_path)
    # Every tick up to the last status (and more) is there: older than 100 ms is the promise.
    assert rec.ticks >= st["tick"]
    assert rec.torn_bytes == 0
    np.testing.assert_array_equal(np.diff(np.rint(rec["t"] * 1000)), 1)
    assert not list(Path("/dev/shm").glob(f"hapticd-ring-{proc.pid}-*"))


@pytest.mark.timing(
    "the writer drains the ring every 10 ms of wall-clock time; the test allows it 100 ms "
    "(a loaded machine can leave it further behind when both are killed)"
)
def test_kill_9_of_daemon_and_writer_keeps_all_but_the_last_100_ms(tmp_path):
    rec_path = tmp_path / "crash.hrec"
    proc, _sock, c = start_daemon(
        tmp_path, "--no-realtime", "--record", str(rec_path), start_new_session=True
    )
    with c:
        wait_for(c.status, "ticks", until=lambda s: s["tick"] > 1500)
        st = c.status()
        os.killpg(proc.pid, signal.SIGKILL)  # the whole group: no one is left to drain
    finish(proc)
    wait_gone(st["recording"]["writer_pid"])
    rec = recording.read(rec_path)
    assert rec.ticks >= st["tick"] - 100  # 100 ticks = 100 ms at 1 kHz
    np.testing.assert_array_equal(np.diff(np.rint(rec["t"] * 1000)), 1)
    # The ring is an anonymous memory file: killing everyone leaves nothing behind.
    assert not list(Path("/dev/shm").glob(f"hapticd-ring-{proc.pid}-*"))


def test_a_recording_replays_on_the_replay_device(tmp_path, grasp_data, write_profile):
    first = tmp_path / "first.hrec"
    again = tmp_path / "again.hrec"
    from hapticd.cli import main

    assert main(["run", str(GRASP_PROFILE), "--unpaced", "--no-socket", "-q",
                 "--duration", "4", "--record", str(first)]) == 0  # fmt: skip
    for finger in grasp_data["fingers"]:
        finger["device"]["trajectory"] = str(first)
    replay = write_profile(grasp_data)
    assert main(["run", str(replay), "--unpaced", "--no-socket", "-q",
                 "--record", str(again)]) == 0  # fmt: skip
    a, b = recording.read(first), recording.read(again)
    # Each run ended mid-grasp: its last record is the shutdown's zero force, which the
    # replay plays as one more position (the last one, repeated).
    assert b.ticks == a.ticks + 1 and not a["device_force"][-1].any()
    np.testing.assert_array_equal(b["device_pos"][: a.ticks], a["device_pos"])
    for name in ("device_pos", "proxy_pos", "contact_force", "device_force", "lam_a"):
        np.testing.assert_array_equal(b[name][: a.ticks - 1], a[name][:-1], err_msg=name)


def test_realtime_is_applied_or_its_absence_explained(tmp_path):
    proc, _sock, c = start_daemon(tmp_path, "--duration", "30")
    with c:
        rt = wait_for(c.status, "real time", until=lambda s: s["realtime"] is not None)["realtime"]
        c.stop()
    rc, _out, err = finish(proc)
    assert rc == 0, err
    if os.geteuid() == 0:
        assert rt["fifo_priority"] == 80 and rt["memory_locked"], rt
    else:
        assert rt["fifo_priority"] > 0 or any("SCHED_FIFO" in p for p in rt["problems"])
        assert all(p in err for p in rt["problems"])


@pytest.mark.timing("counts the control thread's watchdog pings over 1 s")
def test_a_rejected_sighup_leaves_the_control_thread_serving_and_a_later_reload_works(
    tmp_path, grasp_data, write_profile
):
    """Profiles that once killed the control thread (an item of the wrong type in a
    list, 5,000 nested brackets) or froze the daemon (an alias bomb): each reload is
    rejected, status still answers, watchdog pings go on, and a valid profile then
    reloads. (timing: it counts the control thread's watchdog pings over 1 s.)"""

    def dump(change) -> str:
        data = copy.deepcopy(grasp_data)
        change(data)
        return yaml.safe_dump(data, sort_keys=False)

    path = write_profile(grasp_data)
    good = path.read_text()
    bomb = "lol0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
        f"lol{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]\n" for i in range(1, 9)
    )
    start, end = good.index("fingers:"), good.index("rendering:")
    hostile = {
        "wrong item": dump(lambda d: d["fingers"][0].update(actuated_directions=[[1, 0]])),
        "deep nesting": dump(lambda d: d["scene"]["object"].update(size_m="DEEP")).replace(
            "DEEP", "[" * 5000 + "]" * 5000
        ),
        "alias bomb": bomb + good[:start] + "fingers: *l8\n" + good[end:],
    }
    assert all(text != good for text in hostile.values())
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)  # the service manager's end
    notify.bind(str(tmp_path / "notify"))
    notify.settimeout(0.05)
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "200000"}
    proc, _sock, c = start_daemon(tmp_path, "--no-realtime", profile=path, env=env)
    with c, notify:
        wait_for(c.status, "the loop", until=lambda s: s["tick"] > 100)
        for n, (what, text) in enumerate(hostile.items(), start=1):
            path.write_text(text)
            proc.send_signal(signal.SIGHUP)
            st = wait_for(
                c.status,
                f"{what} rejected",
                until=lambda s, n=n: len(s["reloads"]) == n,
                timeout_s=10.0,
            )
            assert st["reloads"][-1].startswith("reload rejected"), (what, st["reloads"])
            assert str(path) in st["reloads"][-1], (what, st["reloads"])
            assert st["fault"] is None, what
        # The control thread still pings the watchdog (every 0.1 s for a 0.2 s watchdog).
        with contextlib.suppress(TimeoutError):
            while notify.recv(4096):
                pass  # what came before
        pings, until = 0, time.monotonic() + 1.0
        while time.monotonic() < until:
            with contextlib.suppress(TimeoutError):
                pings += notify.recv(4096) == b"WATCHDOG=1"
        assert pings >= 5, f"{pings} watchdog pings in 1 s after the rejected reloads"
        # Over the socket too: a bad_profile error, not a hang or a dropped connection.
        with pytest.raises(ProtocolError, match="aliases") as exc:
            c.reload(path)
        assert exc.value.code == "bad_profile"
        grasp_data["scene"]["object"]["stiffness_n_per_m"] = 120.0
        write_profile(grasp_data)
        proc.send_signal(signal.SIGHUP)
        st = wait_for(
            c.status, "the valid reload", until=lambda s: len(s["reloads"]) == 4, timeout_s=10.0
        )
        assert st["reloads"][-1].startswith(f"reloaded {path} at tick"), st["reloads"]
        assert c.get("stiffness_n_per_m") == 120.0
        c.stop()
    rc, _out, err = finish(proc)
    assert rc == 0, err
    assert "Traceback" not in err


def test_the_stop_signals_are_the_daemons_before_its_socket_is_served(tmp_path, monkeypatch):
    """A client, or systemd, may signal the daemon as soon as its socket exists: by then
    SIGTERM, SIGINT and SIGHUP are the daemon's own (a SIGTERM that came first killed it
    without its orderly stop: forces to zero, devices off, the recording closed)."""
    from hapticd.cli import main
    from hapticd.daemon.server import ControlServer

    seen: dict[int, object] = {}
    start = ControlServer.start

    def spy(self) -> None:
        seen.update(
            {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
        )
        start(self)

    monkeypatch.setattr(ControlServer, "start", spy)
    sock = tmp_path / "c.sock"
    args = ["run", str(GRASP_PROFILE), "--unpaced", "--duration", "0.05", "--no-realtime", "-q"]
    assert main([*args, "--socket", str(sock)]) == 0
    assert len(seen) == 3
    defaults = (signal.SIG_DFL, signal.SIG_IGN, signal.default_int_handler, None)
    assert all(callable(h) and h not in defaults for h in seen.values()), seen
