"""A real Dask cluster on this machine's loopback: a ``dask scheduler`` process and
``dask worker`` processes, as a lab would start them by hand, for ``hapticd study
--scheduler`` benchmarks and tests (``scripts/bench_study.py``). Not a LocalCluster:
the scheduler and every worker are separate programs that talk over TCP on 127.0.0.1
(unauthenticated, as Dask is by default: any local user can reach them while they run,
so for a machine whose users you trust).

Every wait has a deadline that fails (``ClusterError`` with the process's log tail), and
every process is ended when the block ends, however it ends: each runs in its own
process group, which gets SIGTERM, then SIGKILL after ``stop_s``. The groups' ids are
listed in the folder's ``pids`` file (``kill_listed``: for a caller that was killed)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

# The file in the cluster's folder listing its process groups' ids, one a line.
PIDS = "pids"
# Dask's setting (as an environment variable) that turns a worker's profiler off.
PROFILER_OFF = "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED"
Popen = subprocess.Popen[bytes]


class ClusterError(RuntimeError):
    """The loopback cluster did not come up in time; the message holds the logs' tails."""


def _tail(path: Path, n: int = 1500) -> str:
    with contextlib.suppress(OSError):
        return path.read_text(errors="replace")[-n:]
    return ""


def _stop(procs: list[Popen], stop_s: float) -> None:
    """SIGTERM each process's group (a worker's nanny and its worker), then SIGKILL the
    groups after ``stop_s`` (a group may outlive its leader), and reap the leaders."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for p in procs:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, sig)
        deadline = time.monotonic() + stop_s
        for p in procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(max(0.0, deadline - time.monotonic()))


@contextlib.contextmanager
def loopback_cluster(
    n_workers: int,
    folder: str | Path,
    *,
    threads: int = 1,
    profiler: bool = False,
    start_s: float = 60.0,
    stop_s: float = 10.0,
) -> Iterator[str]:
    """Start ``dask scheduler`` and ``n_workers`` ``dask worker`` processes (``threads``
    threads each) bound to 127.0.0.1, their files and logs in ``folder``; yield the
    scheduler's address once every worker has joined (within ``start_s`` s, else
    ClusterError). The processes inherit this one's environment and niceness; the
    workers run without Dask's statistical profiler unless ``profiler`` (sampling a
    study's deep Python stacks 100 times a second cost about 7 % of a worker's CPU:
    docs/experiments.md)."""
    try:
        from distributed import Client
    except ImportError:
        raise ClusterError(
            "a Dask cluster needs dask.distributed: pip install 'hapticd[dask]'"
        ) from None
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    sched_file = folder / "scheduler.json"
    sched_file.unlink(missing_ok=True)
    (folder / PIDS).unlink(missing_ok=True)
    procs: list[Popen] = []
    logs: list[Path] = []

    def spawn(name: str, args: list[str], env: dict[str, str] | None = None) -> Popen:
        log = folder / f"{name}.log"
        logs.append(log)
        with open(log, "wb") as out:
            p = subprocess.Popen(
                [sys.executable, "-m", *args],
                env=None if env is None else {**os.environ, **env},
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # its own group: ended with its children
            )
        procs.append(p)
        # Every process group, for whoever must clean up after a killed caller.
        with open(folder / PIDS, "a") as f:
            f.write(f"{p.pid}\n")
        return p

    def fail(what: str) -> ClusterError:
        tails = "\n".join(f"--- {log.name}:\n{_tail(log)}" for log in logs)
        return ClusterError(f"loopback Dask cluster: {what}\n{tails}")

    try:
        sched = spawn(
            "scheduler",
            ["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
             "--no-dashboard", "--scheduler-file", str(sched_file)],
        )  # fmt: skip
        deadline = time.monotonic() + start_s
        address = None
        while address is None:
            if sched.poll() is not None:
                raise fail(f"the scheduler exited ({sched.returncode})")
            if time.monotonic() > deadline:
                raise fail(f"no scheduler address within {start_s:g} s")
            with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
                address = str(json.loads(sched_file.read_text())["address"])
            if address is None:
                time.sleep(0.05)
        for i in range(n_workers):
            spawn(
                f"worker{i}",
                ["distributed.cli.dask_worker", address, "--host", "127.0.0.1",
                 "--nthreads", str(threads), "--nworkers", "1", "--no-dashboard",
                 "--local-directory", str(folder / f"worker{i}")],
                None if profiler else {PROFILER_OFF: "False"},
            )  # fmt: skip
        left = max(1.0, deadline - time.monotonic())
        try:
            client = Client(address, timeout=f"{left:.0f}s")
        except (OSError, TimeoutError) as exc:
            raise fail(f"cannot reach the scheduler at {address}: {exc}") from None
        with client:
            try:
                client.wait_for_workers(n_workers, timeout=max(1.0, deadline - time.monotonic()))
            except TimeoutError:
                raise fail(
                    f"{len(client.scheduler_info()['workers'])} of {n_workers} workers "
                    f"joined within {start_s:g} s"
                ) from None
        for p in procs:
            if p.poll() is not None:
                raise fail(f"{p.args[2]} exited ({p.returncode})")
        yield address
    finally:
        _stop(procs, stop_s)


def kill_listed(folder: str | Path) -> None:
    """SIGKILL every process group listed in ``folder``'s ``pids`` file (a loopback
    cluster whose caller was killed before it could end them); none left is fine."""
    with contextlib.suppress(OSError):
        for line in (Path(folder) / PIDS).read_text().split():
            with contextlib.suppress(ProcessLookupError, PermissionError, ValueError):
                os.killpg(int(line), signal.SIGKILL)
