"""The hapticd command runs BLAS on one thread per process unless the user asks for more."""

from __future__ import annotations

import os
import subprocess
import sys

from hapticd.__main__ import BLAS_THREAD_VARIABLES
from tests.conftest import ROOT

# After the command ran: the variables, and the threads of a process whose BLAS has
# just done a large decomposition (a BLAS with a pool has one thread per core then).
PROBE = """
import os, sys
from hapticd.__main__ import main
sys.argv = ["hapticd", "--version"]
try:
    main()
except SystemExit:
    pass
import numpy as np
np.linalg.svd(np.random.default_rng(0).random((400, 400)))
print(os.environ["OPENBLAS_NUM_THREADS"], len(os.listdir("/proc/self/task")))
"""


def _probe(**env: str) -> tuple[str, int]:
    base = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    out = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=60, cwd=ROOT,
        env={**base, **env},
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    value, threads = out.stdout.split()[-2:]
    return value, int(threads)


def test_the_command_runs_blas_on_one_thread():
    assert _probe() == ("1", 1)


def test_a_users_setting_is_kept():
    value, threads = _probe(OPENBLAS_NUM_THREADS="2")
    assert value == "2"
    assert threads == 2 or os.cpu_count() == 1  # OpenBLAS starts no more threads than cores
