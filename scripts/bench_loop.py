"""Servo-loop timing benchmark: what rate, load, recording and real time do to the period.

Each case runs ``hapticd run`` as its own process (as the service runs) on the
grasp profile at 1, 2, 4 or 8 kHz, on the replay device or on hid devices over
the emulator, optionally with control load (another process sending status
requests as fast as it can plus a 100 Hz telemetry subscriber) and with every
tick recorded, with or without real-time settings (SCHED_FIFO, mlockall, timer
slack; needs root or LimitRTPRIO), beside a bare deadline wait with no work
(the machine's floor), and at 1 kHz with ``hapticd view`` open and two pages
reading its stream (the experimenter's and the subject's: by default a process
holding both pages' WebSockets and parsing every message, as the page's script does;
with ``--browser chromium`` two headless Chromium pages, which also parse and
draw every frame). Every case runs ``--rounds`` times,
interleaved, and the table gives the median over rounds of each figure and the
p99 ratio to the idle real-time replay case at the same rate (the machines are
shared and noisy: compare within one run).

    python scripts/bench_loop.py --rounds 3 --seconds 5
    python scripts/bench_loop.py --quick          # 1 and 4 kHz, replay only
    python scripts/bench_loop.py --view --rounds 2 --seconds 4   # the view's cost alone
    python scripts/bench_loop.py --kernels --rounds 3   # rendering.kernels python vs compiled
    python scripts/bench_loop.py --storm --rounds 2 --seconds 4   # request storms vs quiet

Prints a Markdown table and saves a histogram plot, in the system temp dir unless
--plot PATH names a file (the docs' figure: --plot docs/img/bench-loop.png).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
# Outside the repository: a run never overwrites the docs' figure unless asked to.
DEFAULT_PLOT = Path(tempfile.gettempdir()) / "hapticd-bench-loop.png"

LOAD_SCRIPT = r"""
import signal, sys, threading
from hapticd.control import ControlClient
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *a: stop.set())
sock = sys.argv[1]
n = 0
try:
    with ControlClient(sock) as watcher, ControlClient(sock) as c:
        watcher.subscribe(100.0)
        while not stop.is_set():
            c.status()
            n += 1
except (OSError, ValueError):
    pass  # the daemon's run ended first
print(n)
"""

# A storm of requests that change the loop or rebuild it: four clients, each sending
# ``cmd`` (reload, or a set of the stiffness) as fast as the daemon answers, as the
# adversarial run did. Prints the requests answered (any reply, ok or not).
STORM_SCRIPT = r"""
import signal, sys, threading
from hapticd.control import ControlClient
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *a: stop.set())
sock, cmd = sys.argv[1], sys.argv[2]
counts = [0] * 4
def storm(i):
    try:
        with ControlClient(sock, timeout_s=30.0) as c:
            k = 0
            while not stop.is_set():
                k += 1
                if cmd == "reload":
                    c.request("reload")
                else:
                    c.request("set", param="stiffness_n_per_m", value=60.0 + k % 2)
                counts[i] += 1
    except (OSError, ValueError):
        pass  # the daemon's run ended first
threads = [threading.Thread(target=storm, args=(i,), daemon=True) for i in range(4)]
for t in threads:
    t.start()
stop.wait()
print(sum(counts))
"""
STORMS = {"reload storm": "reload", "set storm": "set"}

# Two pages on ``hapticd view``: each holds the page's WebSocket and parses every message
# as JSON, as the page's script does. Prints the telemetry frames read.
PAGES_SCRIPT = r"""
import json, signal, sys, threading
from websockets.sync.client import connect
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *a: stop.set())
counts = []
def page(url, i):
    try:
        with connect(url, proxy=None, open_timeout=10) as ws:
            while not stop.is_set():
                try:
                    msg = json.loads(ws.recv(timeout=0.2))
                except TimeoutError:
                    continue
                if msg["type"] == "telemetry":
                    counts[i] += 1
    except Exception:
        pass  # the view ended first (ConnectionClosed, OSError)
urls = sys.argv[1:]
counts.extend([0] * len(urls))
threads = [threading.Thread(target=page, args=(u, i), daemon=True) for i, u in enumerate(urls)]
for t in threads:
    t.start()
stop.wait()
print(sum(counts))
"""


# The machine's floor: the same deadline wait (sleep, then spin the last 200 us or half a
# period) with no work at all, under SCHED_FIFO when permitted.
BARE_SCRIPT = r"""
import gc, json, os, sys, time
rate, seconds = float(sys.argv[1]), float(sys.argv[2])
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
except OSError:
    pass
T = 1.0 / rate
margin = min(200e-6, 0.5 * T)
n = int(seconds * rate)
errs = [0.0] * (n - 1)
gc.freeze(); gc.disable()
t0 = time.monotonic() + 2e-3
prev = None
for k in range(n):
    d = t0 + k * T
    r = d - time.monotonic()
    if r > margin:
        time.sleep(r - margin)
    while time.monotonic() < d:
        pass
    s = time.monotonic()
    if prev is not None:
        errs[k - 1] = abs(s - prev - T)
    prev = s
errs.sort()
q = lambda p: errs[min(len(errs) - 1, int(p / 100 * len(errs)))] * 1e6
print(json.dumps({
    "period_error_us": {"p50": q(50), "p99": q(99), "p99.9": q(99.9), "max": errs[-1] * 1e6},
    "overruns_per_10k": 1e4 * sum(e > 0.1 * T for e in errs) / len(errs),
    "tick_compute_us": {"p50": 0.0, "p99": 0.0},
    "period_error_hist_us": [],
}))
"""


VIEW_LOAD = "view + 2 pages"


@dataclass(frozen=True)
class Case:
    rate_hz: int
    device: str  # "replay", "emulated" or "bare"
    load: str  # "idle", "recording", "control + recording", VIEW_LOAD or one of STORMS
    realtime: bool
    profile: str = "grasp-stiffness"  # a bundled profile (configs/NAME.yaml)
    kernels: str | None = None  # rendering.kernels; None: the profile's

    @property
    def label(self) -> str:
        if self.device == "bare":
            return f"{self.rate_hz // 1000} kHz | bare wait, no work | idle | FIFO"
        device = self.device
        if self.kernels is not None:
            device = f"{self.device}, {self.profile}, kernels {self.kernels}"
        return (
            f"{self.rate_hz // 1000} kHz | {device} | {self.load} | "
            f"{'FIFO' if self.realtime else 'normal'}"
        )


def _wait_socket(path: Path, proc: subprocess.Popen, timeout_s: float = 20.0) -> bool:
    from hapticd.control import ControlClient

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        with contextlib.suppress(OSError):
            ControlClient(path).close()
            return True
        time.sleep(0.02)
    return False


class ViewLoad:
    """``hapticd view`` on the daemon's socket and two pages on it (the experimenter's and
    the subject's): WebSocket readers, or headless Chromium pages (``browser``)."""

    def __init__(self, sock: Path, work: Path, browser: str) -> None:
        self.view = subprocess.Popen(
            [sys.executable, "-m", "hapticd", "view", "--socket", str(sock), "-q"],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        self.pages: subprocess.Popen | None = None
        self.chromium = None
        url = self.view.stdout.readline().strip()  # the URL comes first, flushed at once
        if not url.startswith("http://"):
            self.close()
            raise RuntimeError(f"hapticd view printed no URL: {url!r}")
        base, _, query = url.partition("/?")
        if browser == "chromium":
            sys.path.insert(0, str(ROOT))
            from tests import cdp

            exe = cdp.find_chromium()
            if exe is None:
                self.close()
                raise RuntimeError("--browser chromium: no chromium found")
            self.chromium = cdp.Browser(exe, work / "chromium")
            self.chromium.open(url)
            self.chromium.open(url + "&mode=subject")
        else:
            ws = base.replace("http://", "ws://", 1)
            streams = [f"{ws}/ws?{query}", f"{ws}/ws?{query}&mode=subject"]
            self.pages = subprocess.Popen(
                [sys.executable, "-c", PAGES_SCRIPT, *streams],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
            )

    def close(self) -> int | None:
        """Stop the pages and the view; the telemetry frames the stream readers read."""
        frames = None
        if self.pages is not None:
            self.pages.send_signal(signal.SIGTERM)
            out, _ = self.pages.communicate(timeout=10)
            with contextlib.suppress(ValueError):
                frames = int(out.strip() or 0)
        if self.chromium is not None:
            self.chromium.close()
        self.view.send_signal(signal.SIGTERM)
        try:
            self.view.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            self.view.kill()
            self.view.communicate(timeout=10)
        return frames


def run_case(case: Case, seconds: float, work: Path, browser: str = "ws") -> dict:
    if case.device == "bare":
        out = subprocess.run(
            [sys.executable, "-c", BARE_SCRIPT, str(case.rate_hz), str(seconds)],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        return {**json.loads(out), "requests_per_s": None, "page_frames_per_s": None}
    source = ROOT / "configs" / f"{case.profile}.yaml"
    data = yaml.safe_load(source.read_text())
    data["loop"] = {**data.get("loop", {}), "rate_hz": float(case.rate_hz)}
    if case.kernels is not None:
        data["rendering"] = {**data.get("rendering", {}), "kernels": case.kernels}
    profile = work / f"bench-{case.rate_hz}.yaml"
    # (the bundled profiles name builtin trajectories: no relative path to rewrite)
    profile.write_text(yaml.safe_dump(data, sort_keys=False))
    sock = work / "bench.sock"
    summary = work / "summary.json"
    cmd = [
        sys.executable,
        "-m",
        "hapticd",
        "run",
        str(profile),
        "--duration",
        str(seconds),
        "--socket",
        str(sock),
        "--summary-json",
        str(summary),
        "-q",
    ]
    if case.device == "emulated":
        cmd += ["--device", "hid", "--emulate"]
    if not case.realtime:
        cmd.append("--no-realtime")
    if case.load in ("recording", "control + recording"):
        cmd += ["--record", str(work / "bench.hrec")]
    proc = subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.PIPE, text=True)
    load = None
    view = None
    if case.load == VIEW_LOAD and _wait_socket(sock, proc):
        view = ViewLoad(sock, work, browser)
    if case.load in STORMS and _wait_socket(sock, proc):
        load = subprocess.Popen(
            [sys.executable, "-c", STORM_SCRIPT, str(sock), STORMS[case.load]],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
    if case.load == "control + recording" and _wait_socket(sock, proc):
        load = subprocess.Popen(
            [sys.executable, "-c", LOAD_SCRIPT, str(sock)],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
    _, err = proc.communicate(timeout=seconds + 60)
    requests = None
    if load is not None:
        load.send_signal(signal.SIGTERM)
        out, _ = load.communicate(timeout=10)
        with contextlib.suppress(ValueError):
            requests = int(out.strip() or 0)
    frames = None if view is None else view.close()
    if proc.returncode not in (0, 3) or not summary.exists():
        raise RuntimeError(f"{case.label}: hapticd exited {proc.returncode}: {err[-2000:]}")
    s = json.loads(summary.read_text())
    summary.unlink()
    s["requests_per_s"] = None if requests is None else requests / seconds
    s["page_frames_per_s"] = None if frames is None else frames / seconds
    return s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=5.0, help="length of each run, s (<= 7.8)")
    ap.add_argument("--quick", action="store_true", help="1 and 4 kHz, replay only")
    ap.add_argument(
        "--view",
        action="store_true",
        help=f"only 1 kHz: the bare wait, replay idle and replay with {VIEW_LOAD}",
    )
    ap.add_argument(
        "--kernels",
        action="store_true",
        help="1, 4 and 8 kHz, both bundled profiles on replay devices under SCHED_FIFO, "
        "rendering.kernels python against compiled, beside the bare wait",
    )
    ap.add_argument(
        "--storm",
        action="store_true",
        help="only 1 kHz: replay idle against four clients storming it with reload requests, "
        "and with set requests, as fast as it answers",
    )
    ap.add_argument(
        "--browser",
        choices=("ws", "chromium"),
        default="ws",
        help="the view's two pages: WebSocket readers (default) or headless Chromium",
    )
    ap.add_argument(
        "--plot",
        type=Path,
        default=DEFAULT_PLOT,
        metavar="PATH",
        help=f"save the plot here (default {DEFAULT_PLOT})",
    )
    args = ap.parse_args()
    rates = (
        [1000]
        if args.view or args.storm
        else [1000, 4000]
        if args.quick
        else [1000, 2000, 4000, 8000]
    )
    if args.kernels:
        rates = [1000, 4000, 8000]
    devices = ["replay"] if args.quick else ["replay", "emulated"]
    cases = []
    for r in rates:
        cases.append(Case(r, "bare", "idle", True))
        if args.kernels:
            for profile in ("grasp-stiffness", "lift-weight"):
                for kernels in ("python", "compiled"):
                    cases.append(Case(r, "replay", "idle", True, profile, kernels))
            continue
        if args.storm:
            cases.append(Case(r, "replay", "idle", True))
            cases.extend(Case(r, "replay", load, True) for load in STORMS)
            continue
        if args.view:
            cases.append(Case(r, "replay", "idle", True))
            cases.append(Case(r, "replay", VIEW_LOAD, True))
            continue
        for rt in (True, False):
            cases.append(Case(r, "replay", "idle", rt))
        if r == 1000:
            cases.append(Case(r, "replay", VIEW_LOAD, True))
        cases.append(Case(r, "replay", "recording", True))
        for rt in (True, False):
            cases.append(Case(r, "replay", "control + recording", rt))
        if "emulated" in devices:
            cases.append(Case(r, "emulated", "idle", True))
            cases.append(Case(r, "emulated", "control + recording", True))
    results: dict[Case, list[dict]] = {c: [] for c in cases}
    with tempfile.TemporaryDirectory(prefix="hapticd-bench-") as tmp:
        work = Path(tmp)
        for rnd in range(args.rounds):
            for case in cases:
                results[case].append(run_case(case, args.seconds, work, args.browser))
                print(f"round {rnd + 1}/{args.rounds}: {case.label}", file=sys.stderr)
    fifo = any(
        r["realtime"]["fifo_priority"] for rs in results.values() for r in rs if r.get("realtime")
    )
    if not fifo:
        print("note: SCHED_FIFO was not granted; the FIFO rows ran on the normal policy.")

    def med(rs: list[dict], *keys: str) -> float:
        vals = []
        for r in rs:
            v = r
            for k in keys:
                v = v[k]
            vals.append(float("nan") if v is None else float(v))
        return statistics.median(vals)

    cols = [
        "rate", "device", "load", "policy", "period error p50 us", "p99 us", "p99.9 us",
        "max us", "overruns /10k", "compute p50 us", "compute p99 us", "p99 x idle FIFO",
        "requests/s", "page frames/s",
    ]  # fmt: skip
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for case in cases:
        rs = results[case]
        base = results.get(Case(case.rate_hz, "replay", "idle", True))
        p99 = med(rs, "period_error_us", "p99")
        ratio = p99 / med(base, "period_error_us", "p99") if base else float("nan")
        req = [r["requests_per_s"] for r in rs if r["requests_per_s"] is not None]
        pf = [r["page_frames_per_s"] for r in rs if r["page_frames_per_s"] is not None]
        cells = [
            case.label,
            f"{med(rs, 'period_error_us', 'p50'):.2f}",
            f"{p99:.1f}",
            f"{med(rs, 'period_error_us', 'p99.9'):.1f}",
            f"{med(rs, 'period_error_us', 'max'):.0f}",
            f"{med(rs, 'overruns_per_10k'):.1f}",
            f"{med(rs, 'tick_compute_us', 'p50'):.1f}",
            f"{med(rs, 'tick_compute_us', 'p99'):.1f}",
            f"{ratio:.2f}" if base else "-",
            f"{statistics.median(req):.0f}" if req else "-",
            f"{statistics.median(pf):.0f}" if pf else "-",
        ]
        print("| " + " | ".join(cells) + " |")
    if any(c.load == VIEW_LOAD for c in cases):
        pages = (
            "two headless Chromium pages (page frames/s not counted)"
            if args.browser == "chromium"
            else "two WebSocket readers (page frames/s: telemetry frames both read)"
        )
        print(f"\n{VIEW_LOAD}: hapticd view at its default 60 Hz telemetry, {pages}")
    plot(results, rates, args.plot)


def plot(results: dict[Case, list[dict]], rates: list[int], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("(matplotlib not installed: no plot; pip install 'hapticd[bench]')")
        return
    shown = [r for r in rates if r in (1000, 4000)] or rates[:2]
    fig, axes = plt.subplots(1, len(shown), figsize=(6 * len(shown), 4), squeeze=False)
    for ax, rate in zip(axes[0], shown, strict=True):
        for case, rs in results.items():
            if case.rate_hz != rate or case.device != "replay":
                continue
            hist = rs[0]["period_error_hist_us"]
            if not hist:
                continue
            edges = [max(e, 1e-3) for e, _ in hist]
            counts = [c for _, c in hist]
            total = sum(counts)
            # Survival curve: the fraction of periods whose error exceeds x.
            surv, left = [], total
            for c in counts:
                left -= c
                surv.append(max(left / total, 1e-7))
            ax.step(edges, surv, where="post", label=case.label.split(" | ", 2)[2])
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("period error, us")
        ax.set_ylabel("fraction of periods with a larger error")
        ax.set_title(f"{rate // 1000} kHz, replay device")
        ax.axvline(10, color="grey", lw=0.8, ls="--")
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"plot: {path}")


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
