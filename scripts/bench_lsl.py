"""What LSL costs the servo loop: the tick, and a paced 1 kHz run, with and without it.

Each case runs ``hapticd run`` on the grasp profile as its own process (as the service
runs), with real-time settings off (they need root), in three variants:

- ``off``: no LSL;
- ``lsl``: ``--lsl``, nobody reading the streams;
- ``lsl + inlet``: ``--lsl`` and another process holding an inlet on each stream, pulling
  every sample (as LabRecorder does).

The unpaced case gives a whole tick's cost (wall time per tick, us, the loop's copy into
the LSL ring included; the summary's ``tick compute`` stops before it); the paced case the
period error (p50, p99, us) and overruns at 1 kHz. Every case runs ``--rounds`` times,
the variants interleaved in each round, and the table gives the median over rounds (the
machines are shared and noisy: compare within one run).

    python scripts/bench_lsl.py --rounds 5 --seconds 5
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROFILE = ROOT / "configs" / "grasp-stiffness.yaml"
HAPTICD = [sys.executable, "-m", "hapticd"]
VARIANTS = ("off", "lsl", "lsl + inlet")

INLET_SCRIPT = r"""
import signal, sys, threading, pylsl
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *a: stop.set())
name = sys.argv[1]
inlets = []
for n in (name, name + "-markers"):
    found = []
    while not found and not stop.is_set():
        found = pylsl.resolve_byprop("name", n, timeout=0.2)
    if found:
        inlets.append(pylsl.StreamInlet(found[0]))
got = 0
while not stop.is_set():
    for inlet in inlets:
        _, ts = inlet.pull_chunk(timeout=0.01)
        got += len(ts)
print(got)
"""


def run_case(variant: str, paced: bool, seconds: float, tmp: Path) -> dict:
    """One ``hapticd run``; its summary (plus ``inlet_samples`` with an inlet)."""
    out = tmp / "summary.json"
    # A name of its own: another run of the same profile on this machine is another stream.
    name = f"bench-lsl-{uuid.uuid4().hex[:8]}"
    cmd = [*HAPTICD, "run", str(PROFILE), "--duration", str(seconds), "--no-socket", "-q"]
    cmd += ["--set", f"name={name}"]
    cmd += ["--no-realtime", "--summary-json", str(out)]
    # A paced run's wall-clock faults are not what this measures: it runs to its end.
    cmd += ["--set", "safety.watchdog_s=null", "--set", "loop.max_consecutive_overruns=0"]
    if not paced:
        cmd.append("--unpaced")
    if variant != "off":
        cmd.append("--lsl")
    inlet = None
    if variant == "lsl + inlet":
        inlet = subprocess.Popen(
            [sys.executable, "-c", INLET_SCRIPT, f"hapticd-{name}"],
            stdout=subprocess.PIPE,
            text=True,
        )
    try:
        subprocess.run(cmd, check=True, cwd=ROOT, timeout=seconds * 20 + 120)
    finally:
        if inlet is not None:
            time.sleep(0.5)  # the last samples' way to the inlet
            inlet.send_signal(signal.SIGTERM)
            try:
                got, _ = inlet.communicate(timeout=30)
            except subprocess.TimeoutExpired:  # liblsl has hung an inlet past SIGTERM
                inlet.kill()
                got = inlet.communicate()[0] or ""
    summary = json.loads(out.read_text())
    if inlet is not None:
        summary["inlet_samples"] = int(got.strip() or 0)
    return summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args()
    results: dict[tuple[str, bool], list[dict]] = {}
    with tempfile.TemporaryDirectory(prefix="hapticd-bench-lsl-") as tmp:
        for r in range(args.rounds):
            for paced in (False, True):
                for variant in VARIANTS:
                    s = run_case(variant, paced, args.seconds, Path(tmp))
                    results.setdefault((variant, paced), []).append(s)
                    print(
                        f"round {r + 1}: {variant:<12} {'paced' if paced else 'unpaced'}",
                        file=sys.stderr,
                    )

    def med(values: list[float]) -> str:
        return f"{statistics.median(values):.1f}"

    print(
        f"\n{args.rounds} rounds of {args.seconds:g} s, median over rounds "
        f"({os.cpu_count()} cores)\n"
    )
    print(
        "| variant | unpaced tick, us | paced 1 kHz period error p50 / p99, us | overruns "
        "| ticks published (inlet's samples) |"
    )
    print("|---|---|---|---|---|")
    for variant in VARIANTS:
        un, pa = results[(variant, False)], results[(variant, True)]
        tick = [1e6 / s["rate_hz"]["achieved"] for s in un]
        p50 = [s["period_error_us"]["p50"] for s in pa]
        p99 = [s["period_error_us"]["p99"] for s in pa]
        over = [s["overruns"] for s in pa]
        lsl = [s["lsl"]["written"] for s in pa if "lsl" in s]
        inlet = [s["inlet_samples"] for s in pa if "inlet_samples" in s]
        pub = "-" if not lsl else med(lsl) + (f" ({med(inlet)})" if inlet else "")
        print(f"| {variant} | {med(tick)} | {med(p50)} / {med(p99)} | {med(over)} | {pub} |")


if __name__ == "__main__":
    main()
