"""What hostile control traffic costs the servo loop: overruns and p99 period error.

Each case runs a paced 1 kHz grasp run with its control server in a process of its
own, first quiet and then with ``--clients`` connections (200 by default, from one
separate process) each sending ``status`` requests as fast as they are answered,
reconnecting whenever the daemon turns them away (``busy``) or closes them. The server
variants (its connection cap, and whether its thread runs at a lower priority) run in
the same invocation, interleaved over ``--rounds``; the table gives, per case, the
median over rounds of the overruns per 10,000 ticks and of the p99 period error, and
the requests answered a second.

    python scripts/bench_hostile.py --rounds 3 --seconds 4
    python scripts/bench_hostile.py --quick        # one round of 2 s a case

Prints a Markdown table. The machines are shared and noisy: compare within one run.
"""

from __future__ import annotations

import argparse
import json
import os
import selectors
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "configs" / "grasp-stiffness.yaml"
# name: (connection cap, subscribers' places, nice of the server thread, bounded): bounded
# is the server as it is; unbounded, as it was before its I/O waited for the loop's sleep
# and its accepts and busy warnings were bounded per round (patched in the child).
VARIANTS = {
    "cap 64, nice 0": (64, 32, 0, 1),
    "cap 64, nice 0, unbounded": (64, 32, 0, 0),
    "cap 32, nice 0": (32, 16, 0, 1),
    "cap 64, nice 10": (64, 32, 10, 1),
}


def child(sock: str, seconds: float, cap: int, subs: int, nice: int, bounded: int) -> None:
    """The daemon under test: a paced run serving ``sock``; prints its timing as JSON."""
    sys.path.insert(0, str(ROOT))
    from hapticd.daemon import server as server_module
    from hapticd.daemon.server import ControlServer
    from hapticd.daemon.session import build_session
    from hapticd.loop.stats import LogHistogram
    from hapticd.profile import load_profile

    session = build_session(load_profile(PROFILE), paced=True, duration_s=seconds + 60.0)
    session.loop.realtime_settings = None  # the same for every case, root or not
    if not bounded:
        server_module.ACCEPTS_PER_ROUND = 1 << 30
        server_module.BUSY_LOG_PERIOD_S = 0.0
        ControlServer._await_io_window = lambda self: None
    server = ControlServer(session, sock, max_clients=cap, max_subscribers=subs)
    server.start()
    if nice and server._thread is not None:
        os.setpriority(os.PRIO_PROCESS, server._thread.native_id, nice)
    runner = threading.Thread(target=session.run)
    runner.start()
    time.sleep(1.0)  # the loop's start
    stats = session.loop.stats
    print("ready", flush=True)
    sys.stdin.readline()  # the load has started (or not)
    ticks0, over0 = stats.ticks, stats.overruns
    before = list(stats.period_error.counts)
    time.sleep(seconds)
    # The window's own histogram: the counts since it began (its max is the run's).
    window = LogHistogram()
    window.counts = [a - b for a, b in zip(stats.period_error.counts, before, strict=True)]
    window.count = sum(window.counts)
    window.max = stats.period_error.max
    out = {
        "ticks": stats.ticks - ticks0,
        "overruns": stats.overruns - over0,
        "p99_us": window.percentile(99.0) * 1e6,
    }
    session.loop.request_stop("bench over", ramp=False)
    runner.join(10)
    server.close()
    print(json.dumps(out), flush=True)


def load(sock: str, clients: int, seconds: float) -> None:
    """``clients`` connections sending status requests as fast as they are answered;
    prints how many replies came."""
    sel = selectors.DefaultSelector()
    replies = 0

    def connect() -> None:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.connect(sock)
        except OSError:
            s.close()
            return
        s.setblocking(False)
        s.send(b'{"cmd": "status"}\n')
        sel.register(s, selectors.EVENT_READ)

    for _ in range(clients):
        connect()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for key, _ in sel.select(0.05):
            s = key.fileobj
            try:
                data = s.recv(1 << 20)
            except OSError:
                data = b""
            if not data or b'"busy"' in data or b'"idle"' in data:
                sel.unregister(s)
                s.close()
                connect()
                continue
            n = data.count(b'"ok":true')
            replies += n
            if n:
                s.send(b'{"cmd": "status"}\n' * n)
        while len(sel.get_map()) < clients and time.monotonic() < end:
            connect()
    print(json.dumps({"replies": replies}), flush=True)


def one(variant: str, clients: int, seconds: float) -> dict:
    cap, subs, nice, bounded = VARIANTS[variant]
    with tempfile.TemporaryDirectory() as tmp:
        sock = str(Path(tmp) / "b.sock")
        me = [sys.executable, __file__]
        daemon = subprocess.Popen(
            [*me, "--child", sock, str(seconds), str(cap), str(subs), str(nice), str(bounded)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert daemon.stdout.readline().strip() == "ready"
            loader = None
            if clients:
                loader = subprocess.Popen(
                    [*me, "--load", sock, str(clients), str(seconds)],
                    stdout=subprocess.PIPE,
                    text=True,
                )
                time.sleep(0.3)  # every connection made
            daemon.stdin.write("go\n")
            daemon.stdin.flush()
            result = json.loads(daemon.stdout.readline())
            if loader is not None:
                result.update(json.loads(loader.communicate(timeout=seconds + 30)[0]))
            daemon.communicate(timeout=30)
        finally:
            for p in (daemon, locals().get("loader")):
                if p is not None and p.poll() is None:
                    p.kill()
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--clients", type=int, default=200)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--child", nargs=6, help=argparse.SUPPRESS)
    ap.add_argument("--load", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        s, sec, cap, subs, nice, bounded = args.child
        child(s, float(sec), int(cap), int(subs), int(nice), int(bounded))
        return
    if args.load:
        s, n, sec = args.load
        load(s, int(n), float(sec))
        return
    if args.quick:
        args.rounds, args.seconds = 1, 2.0
    cases = [("idle", next(iter(VARIANTS)), 0)] + [
        (f"{args.clients} clients", v, args.clients) for v in VARIANTS
    ]
    results: dict[tuple[str, str], list[dict]] = {}
    for _ in range(args.rounds):
        for load_name, variant, n in cases:
            results.setdefault((load_name, variant), []).append(one(variant, n, args.seconds))
    print(
        f"| load | server | overruns / 10k ticks | p99 period error (us) | "
        f"replies/s |  (median of {args.rounds} rounds of {args.seconds:g} s)"
    )
    print("|---|---|---|---|---|")
    for (load_name, variant), rs in results.items():

        def med(f, rs=rs):
            return statistics.median(f(r) for r in rs)

        over = med(lambda r: 1e4 * r["overruns"] / max(r["ticks"], 1))
        rate = med(lambda r: r.get("replies", 0) / args.seconds)
        print(
            f"| {load_name} | {variant} | {over:.1f} | {med(lambda r: r['p99_us']):.1f} | "
            f"{rate:.0f} |"
        )


if __name__ == "__main__":
    main()
