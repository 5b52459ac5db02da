"""Every generated hostile profile (tests/hostile.py) gives a clear error from
``hapticd check``: exit 2, the file named, the key or the line named, no traceback;
never a crash, a hang or a silent acceptance of a value invalid by construction."""

from __future__ import annotations

import functools
import json
import os
import select
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

from tests.hostile import ROOT, Case, generate

CASE_DEADLINE_S = 10.0  # a hang; the slowest case takes milliseconds


class _Worker:
    """``python -m tests.hostile`` in a subprocess: one check per line, killed on a hang."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tests.hostile"],
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        if self._line(60.0) is None:
            self.close()
            raise RuntimeError("the hostile-profile worker did not start")

    def _line(self, timeout_s: float) -> dict | None:
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout_s)
        if not ready:
            return None
        line = self.proc.stdout.readline()
        return json.loads(line) if line else None

    def check(self, path: Path) -> dict | None:
        """The worker's answer for ``path``, or None if it hung (or died)."""
        self.proc.stdin.write(f"{path}\n")
        self.proc.stdin.flush()
        return self._line(CASE_DEADLINE_S)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.communicate()


def _judge(case: Case, path: Path, res: dict | None) -> tuple[str, str]:
    """(outcome, detail): outcome is clear error, accepted, crash, hang or unclear error."""
    if res is None:
        return "hang", f"no answer within {CASE_DEADLINE_S} s"
    if res["crash"] is not None:
        return "crash", res["crash"][-1500:]
    err = res["err"]
    if res["rc"] == 0:
        if res["run_crash"] is not None or res["run_rc"] != 0:
            detail = res["run_crash"] or res["run_err"]
            return "check accepted what run rejects", f"run exit {res['run_rc']}: {detail}"
        return "accepted", ""
    problems = []
    if res["rc"] != 2:
        problems.append(f"exit {res['rc']}, not 2")
    if not err.startswith(f"hapticd: {path}"):
        problems.append("the message does not start with the file")
    if "Traceback" in err:
        problems.append("a traceback")
    # A value that may be valid can fail elsewhere (a finger's name is the recording's
    # finger it plays): the key is required where the value is invalid by construction.
    if case.must_fail and case.key is not None and case.key not in err and "line " not in err:
        problems.append(f"names neither the key {case.key!r} nor a line")
    if len(err) > 6000:  # a path may be 4096 characters
        problems.append(f"a message of {len(err)} characters")
    if problems:
        return "unclear error", "; ".join(problems) + "\n" + err[:1500]
    return "clear error", ""


# The cases in interleaved shards: separate tests, so the suite's workers share them.
SHARDS = 4


@functools.cache
def _cases() -> list[Case]:
    """Every generated case, made once per process (the shards share them)."""
    return list(generate())


@pytest.mark.parametrize("shard", range(SHARDS))
def test_hostile_profiles_give_clear_errors(tmp_path, shard):
    every = _cases()
    assert len(every) > 2000  # generated at every key: a schema walk that finds nothing fails
    cases = every[shard::SHARDS]
    worker = _Worker()
    outcomes: Counter[str] = Counter()
    failures: list[str] = []
    slowest = 0.0
    t0 = time.monotonic()
    try:
        for n, case in enumerate(cases):
            path = tmp_path / f"case-{n}.yaml"
            path.write_bytes(case.data)
            for name, blob in case.files:
                (tmp_path / name).write_bytes(blob)
            res = worker.check(path)
            outcome, detail = _judge(case, path, res)
            if res is None:  # hung or died: a fresh worker for the rest
                worker.close()
                worker = _Worker()
            else:
                slowest = max(slowest, res["s"])
            if outcome == "accepted" and not case.must_fail:
                outcome = "accepted (valid)"
            outcomes[outcome] += 1
            if outcome not in ("clear error", "accepted (valid)"):
                failures.append(f"{case.name}: {outcome}: {detail}")
            os.unlink(path)
    finally:
        worker.close()
    summary = (
        f"hostile profiles, shard {shard + 1} of {SHARDS}: {len(cases)} tried in "
        f"{time.monotonic() - t0:.1f} s "
        f"(slowest check {slowest * 1e3:.0f} ms): "
        + ", ".join(f"{k} {v}" for k, v in sorted(outcomes.items()))
    )
    print(summary)
    assert not failures, summary + "\n" + "\n\n".join(failures[:30])
