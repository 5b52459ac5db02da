"""Lab Streaming Layer outlets: the loop's ticks and the daemon's events as two LSL streams.

``hapticd run --lsl`` (or the profile's ``lsl`` section) publishes (docs/lsl.md):

- a numeric stream named ``hapticd-<profile name>`` (type ``Haptics``): one sample per
  tick (or per ``lsl.decimation`` ticks), its channels the CSV export's columns
  (``hapticd.recording.export.csv_columns``), their units and fingers in the stream's
  description;
- a marker stream ``hapticd-<profile name>-markers`` (type ``Markers``): each of the
  daemon's events (hapticd.events: contacts, buttons, faults, prompts, answers, the
  runner's ``mark``) as its JSON line.

Every sample is stamped with its own tick's start on LSL's clock: liblsl's ``local_clock``
is ``std::chrono::steady_clock``, CLOCK_MONOTONIC on Linux, the loop's own clock, so a
tick's LSL time is the loop's origin plus its ``t_wall`` (hapticd.recording.ring
``clock_anchor``); a marker carries its tick's time, the same as that tick's sample.

Nothing of LSL runs in the daemon: the loop copies each tick's record into a second
shared-memory ring (as it does for a recording, hapticd.recording.ring) and the control
thread writes event lines to a pipe, without blocking; another process
(``python -m hapticd.daemon.lsl``) reads both and owns the outlets. A slow or absent consumer
costs the loop nothing: a full ring drops the tick from the stream (``dropped``), never
from the recording.
"""

from __future__ import annotations

import contextlib
import json
import math
import mmap
import os
import select
import socket
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hapticd import __version__
from hapticd.allocation import plugins as allocation_plugins
from hapticd.recording import ring
from hapticd.recording.export import PER_FINGER, csv_columns, flat_values
from hapticd.recording.format import Field, Recording, RecordingError, make_dtype
from hapticd.recording.recorder import Recorder

if TYPE_CHECKING:
    from hapticd.daemon.server import ControlServer
    from hapticd.daemon.session import Session

INSTALL = "pip install 'hapticd[lsl]'"
STREAM_TYPE = "Haptics"
POLL_S = 0.005  # how often the publisher looks at the ring and the marker pipe
# A marker whose tick the publisher has not seen this long after it arrived (a tick dropped
# from the stream, the run's end) is stamped with its nominal time instead.
MARKER_WAIT_S = 0.5
CLOSE_WAIT_S = 1.0  # at close, how long the publisher waits for the last marker lines


class LslUnavailableError(RuntimeError):
    """pylsl is not installed (or liblsl does not load); the message says how to install it."""


def require_pylsl(what: str) -> None:
    """LslUnavailableError naming ``what`` asked for LSL unless pylsl imports."""
    try:
        import pylsl  # noqa: F401
    except (ImportError, OSError, RuntimeError) as exc:
        raise LslUnavailableError(
            f"{what} publishes Lab Streaming Layer streams, which needs pylsl "
            f"(and the liblsl it bundles): {INSTALL} ({type(exc).__name__}: {exc})"
        ) from None


def stream_name(profile_name: str) -> str:
    """The numeric stream's name; the marker stream's is this plus ``-markers``."""
    return f"hapticd-{profile_name}"


def channels(fields: Sequence[Field], fingers: Sequence[str]) -> list[dict[str, str]]:
    """Per channel of the numeric stream, in order: label (the CSV column), unit, the
    field it is part of, and its finger ("" for a field that is not per finger)."""
    out = []
    for f in fields:
        rec = Recording(Path("-"), np.zeros(0, make_dtype([f])), [f], list(fingers), {}, 0)
        per_finger = f.name in PER_FINGER and f.shape[:1] == (len(fingers),)
        for label in csv_columns(rec):
            finger = label.split(".")[1] if per_finger else ""
            out.append({"label": label, "unit": f.unit, "field": f.name, "finger": finger})
    return out


class LslOutlet(Recorder):
    """The daemon's side of the LSL outlets: a ring of tick records the loop appends to
    (``loop.tap``; a full ring drops the tick from the stream), a pipe of event lines
    (``markers``), and the publisher process that owns the outlets."""

    def __init__(
        self,
        name: str,
        fields: Sequence[Field],
        fingers: Sequence[str],
        rate_hz: float,
        *,
        decimation: int = 1,
        meta: dict[str, Any] | None = None,
        capacity: int = 4096,
    ) -> None:
        self.dtype = make_dtype(fields)
        self.path = Path(f"LSL stream {name}")  # named so in messages
        self.name = name
        self.decimation = int(decimation)
        self.markers_sent = 0
        self.markers_lost = 0  # the pipe was full, or the publisher gone
        info = {
            "name": name,
            "source_id": f"{name}@{socket.gethostname()}",
            "rate_hz": float(rate_hz),
            "decimation": self.decimation,
            "fields": [f.to_json() for f in fields],
            "channels": channels(fields, fingers),
            "fingers": list(fingers),
            "meta": {"hapticd": __version__, **(meta or {})},
        }
        r, self._marker_w = os.pipe()
        os.set_blocking(self._marker_w, False)
        try:
            self._start_ring(
                capacity,
                False,
                "hapticd.daemon.lsl",
                [str(r), str(os.getpid()), json.dumps(info)],
                (r,),
            )
        except BaseException:
            os.close(self._marker_w)
            raise
        finally:
            os.close(r)  # the publisher has its own copy

    def markers(self, lines: list[bytes]) -> None:
        """Hand event lines (JSON, one per line) to the publisher without waiting: a line
        the pipe has no room for is counted in ``markers_lost``."""
        for line in lines:
            if self._marker_w < 0 or len(line) > select.PIPE_BUF:
                self.markers_lost += 1
                continue
            try:
                os.write(self._marker_w, line)  # whole or not at all: at most PIPE_BUF
            except OSError:  # full (BlockingIOError), or the publisher gone (EPIPE)
                self.markers_lost += 1
            else:
                self.markers_sent += 1

    def status(self) -> dict[str, Any]:
        """The ring's counts (``Recorder.status``), the stream's name, decimation and
        markers sent and lost."""
        return {
            **super().status(),
            "name": self.name,
            "decimation": self.decimation,
            "markers": self.markers_sent,
            "markers_lost": self.markers_lost,
        }

    def close(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """The last markers, then every tick in the ring, out; RecordingError if the
        publisher failed or was lost."""
        self._close_markers()
        return super().close(timeout_s)

    def discard(self) -> None:
        self._close_markers()
        if not self._closed:
            self._final = {**self.status(), "error": "discarded"}
        self._shutdown()

    def _close_markers(self) -> None:
        w, self._marker_w = self._marker_w, -1
        if w >= 0:
            os.close(w)  # the publisher reads to the end, then sees it closed


def attach(session: Session, server: ControlServer | None) -> LslOutlet:
    """Start the LSL outlets of ``session`` (its profile's ``lsl`` section: decimation)
    before its run: the loop's tap and the control server's event sink. RecordingError if
    the publisher does not start (its message says why)."""
    profile, loop = session.profile, session.loop
    from hapticd.recording import loop_fields

    outlet = LslOutlet(
        stream_name(profile.name),
        loop_fields(len(profile.fingers), loop.renderer.actuation.n_actuators),
        profile.finger_names,
        loop.rate_hz,
        decimation=profile.lsl.decimation,
        meta={"profile": profile.name, "allocators": list(allocation_plugins.names())},
        capacity=max(4096, int(2.0 * loop.rate_hz)),  # 2 s of ticks
    )
    outlet.wait_running(timeout_s=10.0)
    loop.tap = outlet
    if server is not None:
        server.event_sinks.append(outlet.markers)
    return outlet


def detach(session: Session, outlet: LslOutlet) -> dict[str, Any]:
    """Close ``outlet`` after the run (and after the control server, whose last events it
    publishes); its status, with ``error`` (never raised: the run's outcome is not LSL's)."""
    if session.loop.tap is outlet:
        session.loop.tap = None
    try:
        return outlet.close()
    except RecordingError as exc:
        return {**outlet.status(), "error": str(exc)}


# -- the publisher process --------------------------------------------------------------


def _outlets(pylsl: Any, info: dict[str, Any]) -> tuple[Any, Any]:
    """The numeric and the marker outlet ``info`` describes."""
    rate = info["rate_hz"] / info["decimation"]
    chans = info["channels"]
    numeric = pylsl.StreamInfo(
        info["name"], STREAM_TYPE, len(chans), rate, pylsl.cf_double64, info["source_id"]
    )
    desc = numeric.desc()
    acq = desc.append_child("acquisition")
    acq.append_child_value("manufacturer", "hapticd")
    acq.append_child_value("model", str(info["meta"].get("profile", "")))
    node = desc.append_child("channels")
    for ch in chans:
        c = node.append_child("channel")
        c.append_child_value("label", ch["label"])
        c.append_child_value("unit", ch["unit"])
        c.append_child_value("type", ch["field"])
        if ch["finger"]:
            c.append_child_value("finger", ch["finger"])
    fingers = desc.append_child("fingers")
    for name in info["fingers"]:
        fingers.append_child_value("finger", name)
    hd = desc.append_child("hapticd")
    hd.append_child_value("version", str(info["meta"].get("hapticd", "")))
    hd.append_child_value("rate_hz", repr(info["rate_hz"]))
    hd.append_child_value("decimation", str(info["decimation"]))
    hd.append_child_value("allocators", ",".join(info["meta"].get("allocators", [])))
    hd.append_child_value(
        "clock", "a sample's time is its tick's start on CLOCK_MONOTONIC (LSL's local_clock)"
    )
    markers = pylsl.StreamInfo(
        info["name"] + "-markers",
        "Markers",
        1,
        pylsl.IRREGULAR_RATE,
        pylsl.cf_string,
        info["source_id"] + "-markers",
    )
    mdesc = markers.desc().append_child("hapticd")
    mdesc.append_child_value(
        "format", "one JSON object per marker: event, tick, t and its fields (hapticd.events)"
    )
    return pylsl.StreamOutlet(numeric), pylsl.StreamOutlet(markers)


def publish(ring_fd: int, marker_fd: int, parent_pid: int, info: dict[str, Any]) -> None:
    """Publish the ring's ticks and the pipe's event lines until the daemon closes the ring
    (or dies); failures are the ring's error text, as a recording writer's are."""
    mm = mmap.mmap(ring_fd, 0)
    if mm[:8] != ring.MAGIC:
        raise SystemExit(f"hapticd LSL publisher: fd {ring_fd} is not a tick ring")
    words = ring.Words(mm)
    view = memoryview(mm)
    try:
        # liblsl's log at warnings and above only (its info lines would fill the daemon's
        # stderr): its configuration, read when the first outlet is made, from a memory
        # file (nothing left behind).
        cfg = os.memfd_create("hapticd-lsl-config")
        os.write(cfg, b"[log]\nlevel = -1\n")
        os.environ["LSLAPICFG"] = f"/proc/self/fd/{cfg}"
        try:
            import pylsl
        except (ImportError, OSError, RuntimeError) as exc:
            ring.fail(mm, words, f"the LSL publisher cannot import pylsl: {exc}; {INSTALL}")
            return
        numeric, markers = _outlets(pylsl, info)
        words[ring.W_STATE] = ring.STATE_RUNNING
        _Publisher(words, view, marker_fd, info, numeric, markers).run(parent_pid)
        words[ring.W_STATE] = ring.STATE_DONE
    except Exception as exc:
        ring.fail(mm, words, f"the LSL publisher failed: {type(exc).__name__}: {exc}")
    finally:
        view.release()
        words.release()
        mm.close()


class _Publisher:
    """The publisher's state: the ring read so far, each recent tick's LSL time, markers
    waiting for their tick."""

    def __init__(
        self,
        words: ring.Words,
        view: memoryview,
        marker_fd: int,
        info: dict[str, Any],
        numeric: Any,
        markers: Any,
    ) -> None:
        self.words, self.view, self.marker_fd = words, view, marker_fd
        os.set_blocking(marker_fd, False)
        self.fields = [
            Field(f["name"], f["dtype"], tuple(f["shape"]), f["unit"]) for f in info["fields"]
        ]
        self.dtype = make_dtype(self.fields)
        self.decimation = int(info["decimation"])
        self.numeric, self.markers = numeric, markers
        self.size, self.cap = words[ring.W_ITEMSIZE], words[ring.W_CAPACITY]
        self.done = words[ring.W_DRAINED]
        self.times = np.zeros(self.cap)  # LSL time of tick k at k % cap
        self.ticks = np.full(self.cap, -1, np.int64)  # which tick each entry is
        self.newest = -1
        self.pending: list[tuple[float, dict[str, Any], str]] = []  # (arrived, event, line)
        self.partial = b""
        self.pipe_open = True

    def run(self, parent_pid: int) -> None:
        closed_at: float | None = None
        while True:
            closed = self.words[ring.W_CLOSED] or os.getppid() != parent_pid
            self._drain()
            self._read_markers(POLL_S if closed_at is None else 0.0)
            now = time.monotonic()
            if closed and closed_at is None:
                closed_at = now
            ending = closed_at is not None and (
                not self.pipe_open or now - closed_at > CLOSE_WAIT_S
            )
            self._push_markers(now, everything=ending)
            if ending:
                return

    def _drain(self) -> None:
        anchor = self.words.anchor()
        n = self.words[ring.W_WRITTEN]
        if anchor is None or n <= self.done:
            return
        lsl0 = anchor[0]
        while self.done < n:
            i = self.done % self.cap
            k = min(n - self.done, self.cap - i)
            start = ring.HEADER_BYTES + i * self.size
            rows = np.frombuffer(self.view[start : start + k * self.size], self.dtype)
            tick = rows["tick"].astype(np.int64)
            stamps = lsl0 + rows["t_wall"]
            self.times[tick % self.cap] = stamps
            self.ticks[tick % self.cap] = tick
            keep = tick % self.decimation == 0
            if keep.any():
                kept = rows[keep]
                self.numeric.push_chunk(
                    flat_values(kept, self.fields, len(kept)), stamps[keep].tolist()
                )
            self.newest = max(self.newest, int(tick[-1]))
            del rows
            self.done += k
            self.words[ring.W_DRAINED] = self.done  # the slots may be used again

    def _read_markers(self, wait_s: float) -> None:
        if not self.pipe_open:
            if wait_s:
                time.sleep(wait_s)
            return
        with contextlib.suppress(InterruptedError):
            select.select([self.marker_fd], [], [], wait_s)
        try:
            data = os.read(self.marker_fd, 65536)
        except BlockingIOError:
            return
        if not data:
            self.pipe_open = False  # the daemon closed its end: every line is here
            return
        *lines, self.partial = (self.partial + data).split(b"\n")
        now = time.monotonic()
        for raw in lines:
            try:
                ev = json.loads(raw)
            except ValueError:
                continue
            if isinstance(ev, dict):
                self.pending.append((now, ev, raw.decode("utf-8", "replace")))

    def _stamp(self, ev: dict[str, Any]) -> float | None:
        """The LSL time of the event's tick, once that tick was read (else None)."""
        tick = ev.get("tick")
        if not isinstance(tick, int) or tick > self.newest:
            return None
        if tick >= 0 and self.ticks[tick % self.cap] == tick:
            return float(self.times[tick % self.cap])
        return self._nominal(ev)

    def _nominal(self, ev: dict[str, Any]) -> float:
        """A marker whose tick is not in the stream: the loop's origin plus its nominal time."""
        anchor = self.words.anchor()
        t = ev.get("t")
        lsl0 = anchor[0] if anchor is not None else 0.0
        return lsl0 + (float(t) if isinstance(t, int | float) and math.isfinite(t) else 0.0)

    def _push_markers(self, now: float, *, everything: bool) -> None:
        """Push, in order, each waiting marker whose tick was read; the rest wait (up to
        MARKER_WAIT_S, or until the end: then their nominal time)."""
        while self.pending:
            arrived, ev, line = self.pending[0]
            stamp = self._stamp(ev)
            if stamp is None:
                if not (everything or now - arrived > MARKER_WAIT_S):
                    return
                stamp = self._nominal(ev)
            self.markers.push_sample([line], stamp)
            self.pending.pop(0)


def main(argv: list[str]) -> int:
    if len(argv) != 4:
        usage = "usage: python -m hapticd.daemon.lsl RING_FD MARKER_FD PARENT_PID INFO_JSON"
        print(usage, file=sys.stderr)
        return 2
    # The daemon decides when publishing ends (as for a recording's writer).
    import signal

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    publish(int(argv[0]), int(argv[1]), int(argv[2]), json.loads(argv[3]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
