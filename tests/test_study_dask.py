"""hapticd study on a real Dask cluster (a ``dask scheduler`` process and ``dask worker``
processes on loopback), and what made Dask studies slow: a full garbage collection
before every simulated interval."""

from __future__ import annotations

import gc
import os
import sqlite3
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from hapticd.daemon.session import build_session
from hapticd.experiment import cluster
from hapticd.experiment.cluster import kill_listed
from hapticd.experiment.study import dask_advice, run_study
from hapticd.profile import load_profile
from tests.conftest import GRASP_PROFILE

ROOT = Path(__file__).resolve().parent.parent
STIFFNESS = ROOT / "configs" / "experiments" / "stiffness-jnd.yaml"


def stored(db: Path) -> list[tuple]:
    con = sqlite3.connect(db)
    try:
        return con.execute(
            "SELECT subject, plan_index, condition, comparison, comparison_first, "
            "answer_second_more, seed, status, source FROM trials ORDER BY subject, plan_index"
        ).fetchall()
    finally:
        con.close()


def test_only_a_paced_loop_collects_garbage_before_it_runs(monkeypatch):
    # A full collection before each of a study's thousands of short unpaced loops cost
    # more than their ticks, and most in a Dask worker's large heap.
    calls = []
    real = gc.collect
    monkeypatch.setattr(gc, "collect", lambda *a: calls.append(a) or real(*a))
    assert gc.isenabled()
    build_session(load_profile(GRASP_PROFILE), paced=False, duration_s=0.05).run()
    assert calls == [] and gc.isenabled()
    build_session(load_profile(GRASP_PROFILE), paced=True, duration_s=0.01).run()
    assert calls and gc.isenabled()


DASK_SCRIPT = """
import sys
from distributed import Client
from hapticd.experiment import study
from hapticd.experiment.cluster import loopback_cluster


def setup(dask_worker):
    return dask_worker.state.nthreads, "profile" in dask_worker.periodic_callbacks


folder, db = sys.argv[1], sys.argv[2]
with loopback_cluster(2, folder, start_s=90) as address:
    assert address.startswith("tcp://127.0.0.1:"), address
    with Client(address, timeout="60s") as client:
        # Single-threaded, no profiler: set up as the docs advise, so no advice.
        assert set(client.run(setup).values()) == {{(1, False)}}
        assert study.dask_advice(client) == []
    study.run_study({exp!r}, 2, db, scheduler=address, seed=9, standards=[90.0], repetitions=1)
"""


def test_a_study_on_scheduler_and_worker_processes_stores_the_same_answers(tmp_path):
    pytest.importorskip(
        "distributed", reason="dask.distributed is not installed (pip install 'hapticd[dask]')"
    )
    design = dict(seed=9, standards=[90.0], repetitions=1)
    run_study(STIFFNESS, 2, tmp_path / "one.sqlite", workers=1, **design)
    one = stored(tmp_path / "one.sqlite")
    assert len(one) == 24
    # In a child process (a Client leaves threads behind in whatever process made it),
    # which starts the scheduler and two workers as programs on 127.0.0.1 (address
    # given as a string: run_study makes and closes its own Client). Bounded by the
    # timeout; the cluster's process groups are killed whatever happens.
    folder = tmp_path / "cluster"
    script = DASK_SCRIPT.format(exp=str(STIFFNESS))
    try:
        proc = subprocess.run(
            [sys.executable, "-c", script, str(folder), str(tmp_path / "dask.sqlite")],
            capture_output=True,
            text=True,
            timeout=180,
        )
    finally:
        kill_listed(folder)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (folder / "pids").read_text().split().__len__() == 3  # scheduler, 2 workers
    assert stored(tmp_path / "dask.sqlite") == one


def test_a_cluster_that_cannot_start_fails_with_its_log_and_leaves_no_process(
    tmp_path, monkeypatch
):
    pytest.importorskip(
        "distributed", reason="dask.distributed is not installed (pip install 'hapticd[dask]')"
    )
    # A "python" that exits at once with a message: the scheduler dies before its address.
    fake = tmp_path / "python"
    fake.write_text("#!/bin/sh\necho 'no scheduler here' >&2\nexit 3\n")
    fake.chmod(0o755)
    monkeypatch.setattr(cluster, "sys", SimpleNamespace(executable=str(fake)))
    with (
        pytest.raises(cluster.ClusterError, match=r"scheduler exited \(3\)") as err,
        cluster.loopback_cluster(2, tmp_path / "c", start_s=30),
    ):
        pass
    assert "no scheduler here" in str(err.value)  # the log's tail
    for pid in (tmp_path / "c" / cluster.PIDS).read_text().split():
        with pytest.raises(ProcessLookupError):
            os.killpg(int(pid), 0)


class FakeClient:
    """What dask_advice asks a Client for: each worker's (threads, profiler running)."""

    def __init__(self, setups):
        self.setups = setups

    def run(self, fn):
        if self.setups is None:
            raise RuntimeError("run() is not allowed on this cluster")
        return {f"tcp://127.0.0.1:{i}": s for i, s in enumerate(self.setups)}


def test_dask_advice_names_threaded_and_profiled_workers():
    assert dask_advice(FakeClient([(1, False), (1, False)])) == []
    assert dask_advice(FakeClient(None)) == []  # workers that cannot be asked
    threads, profiler = dask_advice(FakeClient([(2, True), (1, True), (1, False)]))
    assert threads.startswith("1 of 3 Dask workers run 2 threads") and "--nthreads 1" in threads
    assert profiler.startswith("2 of 3") and "PROFILE__ENABLED=False" in profiler
