"""Real-time settings for the servo thread: SCHED_FIFO, CPU affinity, mlockall, timer slack.

Each setting is tried on its own and reported; one that is not permitted (no
CAP_SYS_NICE, RLIMIT_RTPRIO or RLIMIT_MEMLOCK too small, a CPU that does not
exist) is skipped with a message saying why and what would permit it, unless
the profile requires real time. Scheduling policy, affinity and timer slack
apply to the calling thread only (Linux), so threads started before ``apply``
(the control server) keep the normal policy; mlockall applies to the process.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
from dataclasses import dataclass, field

MCL_CURRENT, MCL_FUTURE = 1, 2
PR_SET_TIMERSLACK = 29


class RealtimeError(RuntimeError):
    """A required real-time setting could not be applied."""


def usable_cpus() -> list[int]:
    """The CPUs the calling thread may run on (its affinity mask), ascending."""
    return sorted(os.sched_getaffinity(0))


def cpu_problem(cpu: int) -> str | None:
    """Why the servo thread cannot be pinned to ``cpu`` (naming the CPUs it may use), or
    None when it can: checked when a profile is read, so a typo fails ``check``, not a run."""
    have = usable_cpus()
    if cpu in have:
        return None
    return f"CPU {cpu} is not one this process may run on; available: {have}"


@dataclass(frozen=True)
class RealtimeSettings:
    """What to ask for. priority: SCHED_FIFO priority 1-99, or 0 for the normal policy;
    cpu: the CPU to pin the servo thread to, or None; lock_memory: mlockall;
    timer_slack_ns: the thread's timer slack (ns), or None to leave it."""

    priority: int = 80
    cpu: int | None = None
    lock_memory: bool = True
    timer_slack_ns: int | None = 1
    required: bool = False


@dataclass
class RealtimeReport:
    """What was applied, and a message per setting that was not."""

    fifo_priority: int = 0
    cpu: int | None = None
    memory_locked: bool = False
    timer_slack_ns: int | None = None
    problems: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, object]:
        return {
            "fifo_priority": self.fifo_priority,
            "cpu": self.cpu,
            "memory_locked": self.memory_locked,
            "timer_slack_ns": self.timer_slack_ns,
            "problems": list(self.problems),
        }


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name, use_errno=True) if name else None
    except OSError:
        return None


def apply(settings: RealtimeSettings) -> RealtimeReport:
    """Apply ``settings`` to the calling thread (and mlockall to the process).

    RealtimeError if ``settings.required`` and any setting failed; otherwise the
    report lists the problems.
    """
    rep = RealtimeReport()
    libc = _libc()
    if settings.timer_slack_ns is not None:
        slack = int(settings.timer_slack_ns)
        if libc is not None and libc.prctl(PR_SET_TIMERSLACK, slack, 0, 0, 0) == 0:
            rep.timer_slack_ns = slack
        else:
            rep.problems.append("timer slack: prctl failed; sleeps overshoot more")
    if settings.cpu is not None:
        try:
            os.sched_setaffinity(0, {int(settings.cpu)})
            rep.cpu = int(settings.cpu)
        except (OSError, OverflowError) as exc:  # OverflowError: beyond a C long
            why = getattr(exc, "strerror", None) or str(exc)
            rep.problems.append(f"cpu affinity {settings.cpu}: {why}; available: {usable_cpus()}")
    if settings.lock_memory:
        if libc is None:
            rep.problems.append("mlockall: no C library found")
        elif libc.mlockall(MCL_CURRENT | MCL_FUTURE) == 0:
            rep.memory_locked = True
        else:
            err = ctypes.get_errno()
            rep.problems.append(
                f"mlockall: {os.strerror(err)}; page faults may stall the loop "
                "(raise RLIMIT_MEMLOCK: LimitMEMLOCK=infinity in the unit, or ulimit -l)"
            )
    if settings.priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(settings.priority)))
            rep.fifo_priority = int(settings.priority)
        except (OSError, AttributeError) as exc:
            why = getattr(exc, "strerror", None) or str(exc)
            rep.problems.append(
                f"SCHED_FIFO priority {settings.priority}: {why}; running with the normal "
                "policy (grant CAP_SYS_NICE or LimitRTPRIO=99 in the unit, or run as root)"
            )
    if settings.required and rep.problems:
        restore(rep)
        raise RealtimeError("real time is required but: " + "; ".join(rep.problems))
    return rep


def restore(rep: RealtimeReport) -> None:
    """Put the calling thread back on the normal policy (for shutdown work after the loop).

    The report keeps saying what the loop ran with."""
    if rep.fifo_priority:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    if rep.memory_locked:
        libc = _libc()
        if libc is not None:
            libc.munlockall()
