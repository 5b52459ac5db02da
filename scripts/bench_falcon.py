#!/usr/bin/env python3
"""The falcon backend's per-tick cost, and its parts, against the usb backend's.

Times, tick by tick (perf_counter_ns), ``--ticks`` ticks ``--rounds`` times, the
variants interleaved in each round: the Falcon's forward kinematics from the last
position, its motor values for a force, one packet encoded and decoded, a whole tick
(read_state + write_force) of the falcon backend through pyftdi, pyusb and the emulated
chip, and the same tick of the usb backend through pyusb and its emulator. The
emulators' own cost is in the two whole-tick figures: they compare backends, not
devices. Prints a Markdown table of the median and p99 per tick over all rounds and
the spread of the rounds' medians, in us, and saves a box plot (``--plot PATH``, else
in the system temp dir).

    python scripts/bench_falcon.py --rounds 5
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from hapticd_drivers import DeviceState, open_device
from hapticd_drivers import falcon_model as fm
from hapticd_drivers.delta import load_description
from hapticd_drivers.emulator import DeltaEmulator
from hapticd_drivers.falcon_emulator import EmulatedFalconBackend, FalconEmulator
from hapticd_drivers.trajectory import Trajectory
from hapticd_drivers.usb_emulator import EmulatedUsbBackend

TIMES = np.array([0.0, 1.0, 2.0])
POS = np.array([[0.0, 0.0, 0.0], [0.02, 0.01, -0.01], [-0.01, -0.02, 0.02]])
FORCE = np.array([1.0, -2.0, 3.0])


class Clock:
    t = 0.0

    def __call__(self) -> float:
        return self.t


def _path_angles(ticks: int) -> list[np.ndarray]:
    path = Trajectory(TIMES, POS, "bench")
    return [fm.inverse(np.array(path.at(k * 1e-3)[0])) for k in range(ticks)]


def _kinematics(ticks: int) -> Callable[[int], None]:
    angles = _path_angles(ticks)
    last = [np.zeros(3)]

    def tick(k: int) -> None:
        last[0] = fm.forward(angles[k], last[0])

    return tick


def _motor(ticks: int) -> Callable[[int], None]:
    path = Trajectory(TIMES, POS, "bench")
    poses = [np.array(path.at(k * 1e-3)[0]) for k in range(ticks)]

    def tick(k: int) -> None:
        fm.motor_values(poses[k], FORCE)

    return tick


def _codec(ticks: int) -> Callable[[int], None]:
    def tick(k: int) -> None:
        fm.decode_state(fm.encode_state((k, -k, 2 * k), 7, 0))
        fm.encode_command((100, -200, 300), fm.LED_GREEN, False)

    return tick


def _device(backend: str) -> Callable[[int], None]:
    clock = Clock()
    path = Trajectory(TIMES, POS, "bench")
    if backend == "falcon":
        emu = FalconEmulator(path, clock, "B-1", firmware_loaded=True, homed=True)
        seam = {"usb_backend": EmulatedFalconBackend([emu]), "clock": clock}
    else:
        delta = DeltaEmulator(load_description("delta-omega-class"), path, clock, serial="B-1")
        seam = {"usb_backend": EmulatedUsbBackend([delta])}
    dev = open_device(backend, serial_number="B-1", **seam)
    dev.open()
    dev.enable_forces(True)
    state = DeviceState()

    def tick(k: int) -> None:
        clock.t = k * 1e-3
        dev.read_state(state)
        dev.write_force(FORCE)

    return tick


VARIANTS: dict[str, Callable[[int], Callable[[int], None]]] = {
    "falcon forward kinematics": _kinematics,
    "falcon motor values": _motor,
    "falcon packet encode + decode": _codec,
    "falcon tick (backend + emulated chip)": lambda n: _device("falcon"),
    "usb tick (backend + emulator)": lambda n: _device("usb"),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ticks", type=int, default=2000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--plot", type=Path, default=None)
    args = ap.parse_args()
    samples: dict[str, list[np.ndarray]] = {name: [] for name in VARIANTS}
    for _ in range(args.rounds):
        for name, make in VARIANTS.items():
            tick = make(args.ticks)
            out = np.empty(args.ticks)
            for k in range(args.ticks):
                t0 = time.perf_counter_ns()
                tick(k)
                out[k] = (time.perf_counter_ns() - t0) * 1e-3
            samples[name].append(out)
    print(f"{args.rounds} rounds of {args.ticks} ticks; per tick, us\n")
    print("| variant | median | p99 | rounds' medians |")
    print("|---|---|---|---|")
    for name, rounds in samples.items():
        every = np.concatenate(rounds)
        meds = [float(np.median(r)) for r in rounds]
        print(
            f"| {name} | {np.median(every):.1f} | {np.percentile(every, 99):.1f} | "
            f"{min(meds):.1f}-{max(meds):.1f} |"
        )
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.boxplot([np.concatenate(r) for r in samples.values()], showfliers=False)
    ax.set_xticks(range(1, len(samples) + 1), [n.replace(" (", "\n(") for n in samples])
    ax.set_ylabel("us per tick")
    ax.tick_params(axis="x", labelsize=7)
    fig.tight_layout()
    where = args.plot or Path(tempfile.gettempdir()) / "bench_falcon.png"
    fig.savefig(where, dpi=120)
    print(f"\nplot: {where}")


if __name__ == "__main__":
    main()
