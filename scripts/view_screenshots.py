"""Screenshots of ``hapticd view``: the experimenter's page, the subject's, and the subject's
with a prompt's answer buttons, while the lift profile's cube is off the ground; and the
experimenter's page moving two virtual devices (configs/rehearse-virtual.yaml).

Starts ``hapticd view`` on a socket in a temp dir, opens its pages in headless Chromium
(tests/cdp.py, Debian's /usr/bin/chromium), then runs ``hapticd run
configs/lift-weight.yaml --device sim`` (paced) on that socket, waits until the cube's
centre is ``--lift-mm`` above where it started, and captures the experimenter's and the
subject's pages at that moment; then sets a prompt over the control socket and captures
the subject's page with its buttons (skipped, with a note, when the daemon has no
``prompt`` command).

The virtual devices' page (view-virtual.png): ``hapticd run configs/rehearse-virtual.yaml``
and ``hapticd view --control``; both fingers brought into the cube with the squeeze key
(s), lifted 5 mm (Shift+Up), and the thumb dragged deeper with the mouse, as a person
does it.

    python scripts/view_screenshots.py                  # into a temp dir (printed)
    python scripts/view_screenshots.py --out docs/img   # the docs' figures
    python scripts/view_screenshots.py --only virtual --out docs/img
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hapticd import protocol as proto  # noqa: E402
from hapticd.control import ControlClient  # noqa: E402
from tests import cdp  # noqa: E402

PROFILE = ROOT / "configs" / "lift-weight.yaml"
RUN = [sys.executable, "-m", "hapticd", "run", str(PROFILE), "--device", "sim"]
RUN += ["--no-realtime", "-q"]
VIRTUAL = ROOT / "configs" / "rehearse-virtual.yaml"
VIRTUAL_AT = "JSON.parse(document.querySelector('[data-testid=scene]').dataset.virtual || 'null')"
PROMPT = {
    "prompt": 1,
    "question": "Was this cube heavier than the first?",
    "choices": ["no", "yes"],
}


def wait(read, what: str, until=bool, timeout_s: float = 30.0, poll_s: float = 0.02):
    """``read()`` until ``until`` holds; RuntimeError naming ``what`` at the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = read()
        if until(value):
            return value
        if time.monotonic() > deadline:
            raise RuntimeError(f"no {what} within {timeout_s:g} s (last: {value!r})")
        time.sleep(poll_s)


def connect(sock: Path, proc: subprocess.Popen) -> ControlClient:
    def attempt():
        if proc.poll() is not None:
            raise RuntimeError(f"hapticd run ended (exit {proc.returncode}) before serving")
        try:
            return ControlClient(sock)
        except OSError:
            return None

    return wait(attempt, "control socket", until=lambda c: c is not None)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, help="folder for the PNGs (default: a new temp dir)")
    ap.add_argument(
        "--lift-mm", type=float, default=20.0, help="how high the cube must be (mm, default 20)"
    )
    ap.add_argument("--only", choices=["all", "lift", "virtual"], default="all")
    args = ap.parse_args()
    exe = cdp.find_chromium()
    if exe is None:
        print("no chromium: apt-get install chromium", file=sys.stderr)
        return 2
    out = args.out or Path(tempfile.mkdtemp(prefix="hapticd-view-shots-"))
    out.mkdir(parents=True, exist_ok=True)
    if args.only in ("all", "lift"):
        lift_shots(exe, out, args.lift_mm)
    if args.only in ("all", "virtual"):
        virtual_shot(exe, out)
    for p in sorted(out.glob("view-*.png")):
        print(p)
    return 0


def stop(*procs: subprocess.Popen | None) -> None:
    """SIGTERM each process still running; kill it after 15 s."""
    for proc in procs:
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=15)
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def virtual_shot(exe: str, out: Path) -> None:
    """view-virtual.png: two virtual devices moved from the page, both fingers on the cube."""
    with tempfile.TemporaryDirectory(prefix="hapticd-shots-") as tmp:
        work = Path(tmp)
        sock = work / "d.sock"
        hapticd = [sys.executable, "-m", "hapticd"]
        run = subprocess.Popen(
            [*hapticd, "run", str(VIRTUAL), "--no-realtime", "-q", "--socket", str(sock)],
            cwd=ROOT,
        )
        view = None
        try:
            connect(sock, run).close()
            view = subprocess.Popen(
                [*hapticd, "view", "--socket", str(sock), "--control", "-q"],
                cwd=ROOT,
                stdout=subprocess.PIPE,
                text=True,
            )
            url = view.stdout.readline().strip()
            with cdp.Browser(exe, work / "c1") as page, ControlClient(sock) as c:
                page.open(url)
                at = wait(
                    lambda: page.evaluate(VIRTUAL_AT),
                    "the virtual fingertips drawn",
                    until=lambda a: a and a["fingers"].get("0") and a["object"],
                )
                for _ in range(15):  # both fingers in, 2 mm a press: 2 mm into the cube
                    page.press("s")
                wait(lambda: all(c.status()["in_contact"]), "both fingers on the cube")
                page.key("ArrowUp", shift=True)  # both up 5 mm
                # And the thumb dragged a tenth of the way to the drawn cube's middle: deeper.
                at = page.evaluate(VIRTUAL_AT)
                (x0, y0), (x1, y1) = at["fingers"]["0"], at["object"]
                page.drag((x0, y0), (x0 + (x1 - x0) / 10, y0 + (y1 - y0) / 10), steps=6)
                time.sleep(1.0)  # the fingers there, the traces drawn
                page.screenshot(out / "view-virtual.png")
                print(f"view-virtual.png at tick {c.status()['tick']}")
        finally:
            stop(view, run)


def lift_shots(exe: str, out: Path, lift_mm: float) -> None:
    """view-experimenter.png, view-subject.png, view-subject-prompt.png: the lift."""
    with tempfile.TemporaryDirectory(prefix="hapticd-shots-") as tmp:
        work = Path(tmp)
        sock = work / "d.sock"
        # The view and the browsers first (their start is the machine's busiest moment),
        # then the run: the pages wait for the daemon and follow it when it comes.
        view = subprocess.Popen(
            [sys.executable, "-m", "hapticd", "view", "--socket", str(sock), "-q"],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            text=True,
        )
        run = None
        try:
            url = view.stdout.readline().strip()
            subject_url = view.stdout.readline().strip()
            with (
                cdp.Browser(exe, work / "c1") as experimenter,
                cdp.Browser(exe, work / "c2") as subject,
            ):
                experimenter.open(url)
                subject.open(subject_url)
                run = subprocess.Popen(
                    [*RUN, "--socket", str(sock)],
                    cwd=ROOT,
                )
                client = connect(sock, run)
                client.subscribe(30)
                z0 = client.next_telemetry()["object_pos"][2]
                sample = wait(
                    client.next_telemetry,
                    f"lift of {lift_mm:g} mm",
                    until=lambda s: s["object_pos"][2] - z0 >= lift_mm * 1e-3,
                )
                time.sleep(0.1)  # the pages' next frames
                experimenter.screenshot(out / "view-experimenter.png")
                subject.screenshot(out / "view-subject.png")
                lift = (sample["object_pos"][2] - z0) * 1e3
                print(f"tick {sample['tick']}: the cube {lift:.1f} mm up")
                client.close()
                with ControlClient(sock) as c:
                    try:
                        c.call("prompt", **PROMPT)
                    except proto.ProtocolError as exc:
                        if exc.code != "unknown_command":
                            raise
                        print("this daemon has no prompt command: no view-subject-prompt.png")
                    else:
                        wait(
                            lambda: subject.evaluate(
                                "!document.querySelector('[data-testid=prompt]').hidden"
                            ),
                            "answer buttons",
                        )
                        time.sleep(0.1)
                        subject.screenshot(out / "view-subject-prompt.png")
        finally:
            stop(view, run)


if __name__ == "__main__":
    sys.exit(main())
