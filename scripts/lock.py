#!/usr/bin/env python3
"""Write the dependency locks (requirements/run.txt, dev.txt, uv.txt) and test them.

The locks pin every package the README's two install commands install, with the hashes of
their wheels, for every platform and Python version hapticd supports (a universal
resolution by uv: one file serves Python 3.11 to the newest). ``pyproject.toml`` keeps its
ranges for people who install hapticd as a library; the README, ``.ci/run`` and a lab's rig
install from the locks, so the same install works next month.

  python scripts/lock.py             # bring the locks in line with pyproject.toml, keeping
                                     # every pin that still fits (no upgrades); no test run
  python scripts/lock.py --upgrade   # move every pin to today's releases, then install them
                                     # in a fresh venv and run the test suite there

After ``--upgrade``, keep the new locks if the suite passed (commit requirements/), or go
back with ``git checkout requirements/``. uv comes with the dev install (requirements/dev.txt).
``requirements/uv.txt`` is the dev lock's own pin of uv, with its hashes, alone: the README's
test command installs it with pip first, then the dev lock with uv (which installs it in under
half of pip's time, its downloads and bytecode in parallel).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LOCKS = ROOT / "requirements"
PYPROJECT = ROOT / "pyproject.toml"
# The oldest Python hapticd supports (pyproject's requires-python); the resolution covers it
# and every newer one.
OLDEST_PYTHON = "3.11"
COMMAND = "python scripts/lock.py"


def build_requirements() -> list[str]:
    """pyproject's build-system requirements: the dev install builds hapticd from the lock's
    setuptools (``--no-build-isolation``), so they are locked too."""
    data = tomllib.loads(PYPROJECT.read_text())
    return list(data["build-system"]["requires"])


def find_uv() -> str:
    """The uv executable: beside this Python (the dev venv carries it) or on PATH."""
    here = Path(sys.executable).parent / "uv"
    found = str(here) if here.exists() else shutil.which("uv")
    if found is None:
        sys.exit(
            "lock: uv not found; install the development tools first "
            "(pip install -r requirements/dev.txt) or put uv on PATH"
        )
    return found


def compile_lock(uv: str, out: Path, extras: list[str], upgrade: bool) -> None:
    """Resolve pyproject (with ``extras``) and the build requirements into ``out``."""
    with tempfile.TemporaryDirectory() as tmp:
        build_in = Path(tmp) / "build.in"
        build_in.write_text("\n".join(build_requirements()) + "\n")
        cmd = [uv, "pip", "compile", str(PYPROJECT), str(build_in)]
        for extra in extras:
            cmd += ["--extra", extra]
        cmd += [
            "--universal",
            "--python-version",
            OLDEST_PYTHON,
            "--generate-hashes",
            # Wheels only: a platform without one fails at once with pip's error, instead of
            # compiling numba or llvmlite from source for half an hour.
            "--only-binary",
            ":all:",
            "--emit-build-options",
            "--no-emit-index-url",
            "--custom-compile-command",
            COMMAND + (" --upgrade" if upgrade else ""),
            "--quiet",
            "-o",
            str(out.relative_to(ROOT)),
        ]
        if upgrade:
            cmd.append("--upgrade")
        env = {**os.environ, "UV_NO_CONFIG": "1"}
        res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    if res.returncode != 0:
        sys.stderr.write(res.stdout + res.stderr)
        sys.exit(
            f"lock: could not resolve {out.relative_to(ROOT)}: uv's explanation above names "
            "the package and the versions it tried; the lock on disk is unchanged"
        )
    # uv writes the temporary build.in's path into the annotations; name it for a reader.
    text = out.read_text().replace(str(build_in), "pyproject.toml [build-system]")
    out.write_text(text)


BOOTSTRAP = "uv"


def write_bootstrap(dev: Path, out: Path) -> None:
    """``out``: the dev lock's pin of uv (its line, hashes and notes) and its build options,
    alone; pip installs it, and uv the rest of the dev lock."""
    lines = dev.read_text().splitlines()
    options = [ln for ln in lines if ln.startswith("--")]
    start = next(i for i, ln in enumerate(lines) if ln.startswith(f"{BOOTSTRAP}=="))
    end = start + 1
    while end < len(lines) and lines[end].startswith(" "):
        end += 1
    header = [
        f"# {BOOTSTRAP} as {dev.relative_to(ROOT)} pins it, alone (written by {COMMAND}):",
        f"# the README's test command installs it with pip, then {dev.name} with it.",
    ]
    out.write_text("\n".join([*header, *options, "", *lines[start:end]]) + "\n")


def readme_test_command() -> str:
    """The README's test command (quick start, step 2), as .ci/run reads it."""
    readme = (ROOT / "README.md").read_text().splitlines()
    return next(
        ln
        for ln in readme
        if ln.startswith("python3 -m venv .venv && ") and ln.endswith("python -m pytest")
    )


def run(cmd: list[str], **kw) -> None:
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, **kw)


def test_locks() -> int:
    """The README's test command on the new lock, in a fresh venv in a clean copy of the tree
    (tracked files plus the new locks) in a folder named ``hapticd``, as a user's clone is
    named; the suite's exit code."""
    with tempfile.TemporaryDirectory(prefix="hapticd-lock-") as tmp:
        tree = Path(tmp) / "hapticd"
        files = subprocess.run(
            ["git", "ls-files", "-z"], cwd=ROOT, check=True, capture_output=True
        ).stdout.split(b"\0")
        for name in filter(None, (f.decode() for f in files)):
            src = ROOT / name
            if src.is_file():
                (tree / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, tree / name)
        t0 = time.monotonic()
        cmd = readme_test_command()
        print("+", cmd, flush=True)
        code = subprocess.run(["bash", "-c", cmd], cwd=tree).returncode
        print(f"lock: the suite on the new lock exited {code} in {time.monotonic() - t0:.0f} s")
        return code


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--upgrade", action="store_true", help="move every pin to today's releases")
    ap.add_argument(
        "--no-test", action="store_true", help="with --upgrade: write the locks, run no tests"
    )
    args = ap.parse_args()
    uv = find_uv()
    LOCKS.mkdir(exist_ok=True)
    compile_lock(uv, LOCKS / "run.txt", [], args.upgrade)
    compile_lock(uv, LOCKS / "dev.txt", ["dev"], args.upgrade)
    write_bootstrap(LOCKS / "dev.txt", LOCKS / "uv.txt")
    print(f"lock: wrote {LOCKS / 'run.txt'}, {LOCKS / 'dev.txt'} and {LOCKS / 'uv.txt'}")
    if not args.upgrade or args.no_test:
        return 0
    code = test_locks()
    if code != 0:
        print(
            "lock: the suite FAILED on the new releases; fix what broke, or go back with "
            "`git checkout requirements/`"
        )
    else:
        print("lock: the suite passed on the new releases; commit requirements/ to keep them")
    return code


if __name__ == "__main__":
    sys.exit(main())
