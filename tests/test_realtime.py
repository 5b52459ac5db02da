"""Real-time settings: applied where permitted, each refusal explained, or refused to run."""

from __future__ import annotations

import os
import threading

import pytest

from hapticd.daemon.session import build_session
from hapticd.loop import realtime
from hapticd.profile import load_profile
from tests.conftest import GRASP_PROFILE


def _in_thread(fn):
    """Run fn in a fresh thread (scheduling settings are per thread) and return its result."""
    out = {}

    def body():
        try:
            out["value"] = fn()
        except BaseException as exc:
            out["error"] = exc

    t = threading.Thread(target=body, name="rt-test")
    t.start()
    t.join()
    if "error" in out:
        raise out["error"]
    return out["value"]


def test_an_impossible_cpu_is_explained_and_the_rest_still_applies():
    def body():
        rep = realtime.apply(realtime.RealtimeSettings(priority=0, cpu=4096, lock_memory=False))
        realtime.restore(rep)
        return rep

    rep = _in_thread(body)
    assert rep.cpu is None and rep.timer_slack_ns == 1
    assert any(p.startswith("cpu affinity 4096:") and "available" in p for p in rep.problems)


def test_required_real_time_refuses_rather_than_run_without_it():
    settings = realtime.RealtimeSettings(priority=0, cpu=4096, lock_memory=False, required=True)
    with pytest.raises(realtime.RealtimeError, match="real time is required but: cpu affinity"):
        _in_thread(lambda: realtime.apply(settings))


def test_fifo_is_granted_to_root_and_given_back_after_the_loop():
    if os.geteuid() != 0:
        pytest.skip("SCHED_FIFO needs root or RLIMIT_RTPRIO here")

    def body():
        rep = realtime.apply(realtime.RealtimeSettings(priority=10, lock_memory=False))
        during = os.sched_getscheduler(0)
        realtime.restore(rep)
        return rep, during, os.sched_getscheduler(0)

    rep, during, after = _in_thread(body)
    assert rep.fifo_priority == 10 and not rep.problems
    assert during == os.SCHED_FIFO and after == os.SCHED_OTHER


def test_a_required_setting_that_fails_latches_a_fault_at_tick_zero():
    s = build_session(load_profile(GRASP_PROFILE), duration_s=0.1)
    s.loop.realtime_settings = realtime.RealtimeSettings(cpu=4096, required=True)
    out = _in_thread(s.run)
    assert out["end_reason"] == "fault" and out["ticks"] == 0
    assert "real time is required" in out["fault"]["cause"]
    for dev in s.devices:
        assert not dev.enabled


@pytest.mark.parametrize("command", ["check", "run"])
def test_a_cpu_this_process_may_not_run_on_is_refused_by_check_and_run(command, capsys):
    from hapticd.cli import EXIT_BAD_INPUT, main

    cpu = os.cpu_count() or 1  # CPUs count from 0: this one is beyond the last
    assume_ok = cpu <= 4095 and cpu not in os.sched_getaffinity(0)
    if not assume_ok:
        pytest.skip(f"CPU {cpu} is usable here")
    extra = ["--unpaced", "--duration", "0.01", "--no-socket", "-q"] if command == "run" else []
    argv = [command, str(GRASP_PROFILE), "--set", f"loop.realtime.cpu={cpu}", *extra]
    assert main(argv) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    line = next(ln for ln in err.splitlines() if "loop.realtime.cpu" in ln)
    available = str(sorted(os.sched_getaffinity(0)))
    assert f"CPU {cpu}" in line and available in line, err


def test_a_cpu_this_process_may_run_on_is_accepted():
    cpu = min(os.sched_getaffinity(0))
    profile = load_profile(GRASP_PROFILE, [f"loop.realtime.cpu={cpu}"])
    assert profile.loop.realtime.cpu == cpu
