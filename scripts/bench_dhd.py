#!/usr/bin/env python3
"""The dhd backend's per-tick device cost (read_state + write_force) on the fake SDK.

Builds the fake SDK (tests/fakes/fake_dhd.c), opens one device and times
``--ticks`` reads and writes, ``--rounds`` times, interleaving the variants in each
round: this tree's backend against the SDK as documented (velocity window, error
codes) and with the fake's older behaviours; with ``--before REV``, the backend of
git revision REV too (on the older behaviours, the only ones it survives). Prints a
Markdown table of the medians and maxima over rounds, in us per tick. The fake's own
cost is in every figure: this compares backends, not devices.

    python scripts/bench_dhd.py --before 93e3008 --rounds 7
"""

from __future__ import annotations

import argparse
import ctypes
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import numpy as np
from hapticd_drivers import DeviceState, dhd_backend

ROOT = Path(__file__).resolve().parent.parent
LEGACY_ALL = 15  # every FAKE_LEGACY_* flag


def _backend_at(rev: str, where: Path) -> ModuleType:
    text = subprocess.run(
        ["git", "show", f"{rev}:drivers/dhd_backend.py"],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    path = where / "dhd_backend_before.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("dhd_backend_before", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _time(module: ModuleType, lib_path: str, lib: ctypes.CDLL, legacy: int, ticks: int) -> float:
    lib.fake_set_legacy(legacy)
    lib.fake_reset(1)
    dhd_backend._HELD.clear()
    dev = module.DhdDevice(index=0, library=lib_path)
    dev.open()
    dev.enable_forces(True)
    st, f = DeviceState(), np.array([0.1, 0.2, 0.3])
    t0 = time.perf_counter()
    for _ in range(ticks):
        dev.read_state(st)
        dev.write_force(f)
    us = (time.perf_counter() - t0) / ticks * 1e6
    dev.close()
    return us


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ticks", type=int, default=20000)
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--before", metavar="REV", help="also time the backend of this revision")
    args = p.parse_args()
    sys.path.insert(0, str(ROOT))
    from tests.fakes.fake_sdk import build

    with tempfile.TemporaryDirectory(prefix="bench-dhd-") as tmp:
        lib_path = str(build(Path(tmp), True))
        lib = ctypes.CDLL(lib_path)
        variants = [
            ("this tree, SDK as documented", dhd_backend, 0),
            ("this tree, older behaviours", dhd_backend, LEGACY_ALL),
        ]
        if args.before:
            variants.append(
                (
                    f"{args.before}, older behaviours",
                    _backend_at(args.before, Path(tmp)),
                    LEGACY_ALL,
                )
            )
        times: dict[str, list[float]] = {name: [] for name, _, _ in variants}
        for _ in range(args.rounds):
            for name, module, legacy in variants:
                times[name].append(_time(module, lib_path, lib, legacy, args.ticks))
    print(
        f"| backend and fake ({args.rounds} rounds x {args.ticks} ticks) | median us/tick | max |"
    )
    print("|---|---|---|")
    for name, runs in times.items():
        print(f"| {name} | {statistics.median(runs):.2f} | {max(runs):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
