#!/usr/bin/env python3
"""The dhd backend's per-tick device cost (read_state + write_force) on the fake SDK.

Builds the fake SDK (tests/fakes/fake_dhd.c), opens one device and times
``--ticks`` reads and writes, ``--rounds`` times, interleaving the variants in each
round: this tree's backend against the SDK as documented (velocity window, error
codes) and with the fake's older behaviours; with ``--before REV``, the backend of
git revision REV too (on the older behaviours, the only ones it survives). Each tick
is timed on its own (perf_counter_ns): prints a Markdown table of the median and p99
per tick over all rounds and the spread of the rounds' medians, in us, and saves a
box plot of the ticks (``--plot PATH``, else in the system temp dir). The fake's own
cost is in every figure: this compares backends, not devices.

    python scripts/bench_dhd.py --before 93e3008 --rounds 7
"""

from __future__ import annotations

import argparse
import ctypes
import importlib.util
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


def _time(
    module: ModuleType, lib_path: str, lib: ctypes.CDLL, legacy: int, ticks: int
) -> np.ndarray:
    """Each tick's read_state + write_force, us: (ticks,)."""
    lib.fake_set_legacy(legacy)
    lib.fake_reset(1)
    dhd_backend._HELD.clear()
    dev = module.DhdDevice(index=0, library=lib_path)
    dev.open()
    dev.enable_forces(True)
    st, f = DeviceState(), np.array([0.1, 0.2, 0.3])
    out = np.empty(ticks)
    clock = time.perf_counter_ns
    for k in range(ticks):
        t0 = clock()
        dev.read_state(st)
        dev.write_force(f)
        out[k] = clock() - t0
    dev.close()
    return out / 1e3


def _plot(times: dict[str, list[np.ndarray]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.0))
    names = list(times)
    ax.boxplot(
        [np.concatenate(times[n]) for n in names], orientation="horizontal", showfliers=False
    )
    ax.set_yticks(range(1, len(names) + 1), names)
    ax.set_xlabel("read_state + write_force per tick, us (whiskers 1.5 IQR, no outliers)")
    ax.set_title("dhd backend on the fake SDK")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ticks", type=int, default=20000)
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--before", metavar="REV", help="also time the backend of this revision")
    p.add_argument(
        "--plot",
        type=Path,
        default=Path(tempfile.gettempdir()) / "hapticd-bench-dhd.png",
        help="where to save the plot",
    )
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
            before = _backend_at(args.before, Path(tmp))
            variants.append((f"{args.before}, older behaviours", before, LEGACY_ALL))
        times: dict[str, list[np.ndarray]] = {name: [] for name, _, _ in variants}
        for _ in range(args.rounds):
            for name, module, legacy in variants:
                times[name].append(_time(module, lib_path, lib, legacy, args.ticks))
    runs_of = f"{args.rounds} rounds x {args.ticks} ticks"
    print(f"| backend and fake ({runs_of}) | median us | p99 us | rounds' medians us |")
    print("|---|---|---|---|")
    for name, runs in times.items():
        every = np.concatenate(runs)
        medians = [float(np.median(r)) for r in runs]
        print(
            f"| {name} | {np.median(every):.2f} | {np.percentile(every, 99):.2f} | "
            f"{min(medians):.2f}-{max(medians):.2f} |"
        )
    _plot(times, args.plot)
    print(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
