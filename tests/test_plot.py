"""hapticd plot: the figure of a recording or a run summary, its panels, and clear errors."""

from __future__ import annotations

import json
import re
import sys
import tempfile

import numpy as np
import pytest

from hapticd import plot, recording
from hapticd.cli import main
from tests.conftest import GRASP_PROFILE, ROOT

pytest.importorskip("matplotlib", reason="hapticd plot needs matplotlib (the plot extra)")

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
RATE = 1000.0
ALL_TITLES = [
    "thumb: force magnitude",
    "thumb: force components",
    "index: force magnitude",
    "index: force components",
    "contact",
    "allocation residuals",
    "object position",
    "loop period error",
    "tick compute time",
]


def synthetic(path, ticks=400, *, late_ticks=(), fields=None, meta=None):
    """A loop recording of two fingers with known forces, contact and timing: each tick
    1 ms after the last, except ``late_ticks`` which start 0.5 ms late."""
    fields = fields or recording.loop_fields(2, 2)
    k = np.arange(ticks)
    t = k / RATE
    wall = t.copy()
    for j in late_ticks:
        wall[j:] += 0.0005
    full = np.zeros((ticks, 2, 3))
    full[:, 0, 0] = np.sin(k / 50.0) * 3.0  # thumb: x only
    full[:, 1, 2] = 2.0  # index: a constant 2 N along z
    arrays = {f.name: np.zeros((ticks, *f.shape), dtype=f.dtype) for f in fields}
    arrays.update(
        t=t,
        t_wall=wall,
        compute_s=np.full(ticks, 50e-6),
        contact_force=full,
        rendered_force=0.5 * full,
        device_force=0.5 * full,
        in_contact=(np.abs(full).sum(axis=2) > 0).astype("u1"),
        residual_internal=np.linspace(0, 1, ticks),
        residual_external=np.linspace(1, 0, ticks),
        object_pos=np.tile([0.0, 0.0, 0.01], (ticks, 1)),
        control_seq=(k >= ticks // 2).astype("<u4"),
    )
    arrays = {f.name: arrays[f.name] for f in fields}
    recording.write(
        path,
        arrays,
        fields,
        ["thumb", "index"],
        meta or {"rate_hz": RATE, "paced": True, "profile": "synthetic", "allocator": "if"},
    )
    return recording.read(path)


def axes_by_title(fig):
    return {ax.get_title(): ax for ax in fig.axes if ax.get_title()}


def test_a_recording_gets_every_panel_with_its_data(tmp_path):
    rec = synthetic(tmp_path / "r.hrec", late_ticks=(100, 300))
    fig = plot.recording_figure(rec)
    axes = axes_by_title(fig)
    assert list(axes) == ALL_TITLES
    # The thumb's magnitude panel draws |contact_force| and |rendered_force| of the thumb.
    mags = {ln.get_label(): ln.get_ydata() for ln in axes["thumb: force magnitude"].get_lines()}
    full = mags["full |contact_force|"]
    np.testing.assert_allclose(full, np.abs(np.sin(np.arange(400) / 50.0) * 3.0))
    np.testing.assert_allclose(mags["rendered |rendered_force|"], 0.5 * full)
    # The index's components: full z is 2 N, rendered z 1 N, x and y zero.
    comps = {ln.get_label(): ln.get_ydata() for ln in axes["index: force components"].get_lines()}
    np.testing.assert_allclose(comps["full z"], 2.0)
    np.testing.assert_allclose(comps["rendered z"], 1.0)
    np.testing.assert_allclose(comps["full x"], 0.0)
    # Object position in mm.
    z = next(ln for ln in axes["object position"].get_lines() if ln.get_label() == "z")
    np.testing.assert_allclose(z.get_ydata(), 10.0)
    # One control change, at the middle tick, is a vertical line on the time panels.
    marks = [ln for ln in axes["contact"].get_lines() if ln.get_linestyle() == ":"]
    assert [float(m.get_xdata()[0]) for m in marks] == [pytest.approx(0.2)]
    # The period error histogram counts every tick after the first; two came 500 us late.
    counts = [p.get_height() for p in axes["loop period error"].patches]
    assert sum(counts) == 399
    assert "max 500 us" in axes["loop period error"].get_xlabel()
    assert "p50 50 us" in axes["tick compute time"].get_xlabel()


def test_fields_choose_the_panels_by_name_or_by_field(tmp_path):
    rec = synthetic(tmp_path / "r.hrec")
    panels = plot.parse_panels("contact,residual_external,compute_s")
    assert panels == ["contact", "residuals", "timing"]
    titles = list(axes_by_title(plot.recording_figure(rec, panels)))
    assert titles == ["contact", "allocation residuals", "loop period error", "tick compute time"]
    with pytest.raises(plot.PlotError, match="unknown panel or field 'forces'"):
        plot.parse_panels("forces")


def test_an_unpaced_recording_has_no_period_error(tmp_path):
    rec = synthetic(tmp_path / "r.hrec", meta={"rate_hz": RATE, "paced": False})
    axes = axes_by_title(plot.recording_figure(rec, ["timing"]))
    assert "unpaced run: no period error" in [t.get_text() for t in axes["loop period error"].texts]


def test_long_recordings_are_drawn_as_an_envelope_that_keeps_spikes():
    t = np.arange(1_000_003) / RATE
    y = np.zeros_like(t)
    y[777_777] = 9.0  # a one-tick spike
    tt, yy = plot._envelope(t, y)
    assert len(tt) <= plot.MAX_POINTS + 2 and len(tt) == len(yy)
    assert yy.max() == 9.0 and yy.min() == 0.0


def test_the_cli_writes_a_png_of_a_run_and_of_its_summary(tmp_path, capsys):
    rec_path, summary = tmp_path / "run.hrec", tmp_path / "s.json"
    out = tmp_path / "run.png"
    rc = main(
        [
            "run",
            str(GRASP_PROFILE),
            "--unpaced",
            "--duration",
            "0.3",
            "--no-socket",
            "-q",
            "--record",
            str(rec_path),
            "--summary-json",
            str(summary),
            "--plot",
            str(out),
        ]
    )
    assert rc == 0
    assert out.read_bytes()[:8] == PNG_MAGIC
    assert f"plot: {out}" in capsys.readouterr().out
    out2 = tmp_path / "again.png"
    assert main(["plot", str(rec_path), "--out", str(out2), "--fields", "contact"]) == 0
    assert out2.read_bytes()[:8] == PNG_MAGIC
    # A summary: its period error histogram (an unpaced run has none: said in the figure).
    fig = plot.figure_for(summary)
    assert [ax.get_title() for ax in fig.axes] == ["loop period error"]
    assert main(["plot", str(summary), "--out", str(tmp_path / "s.png")]) == 0
    assert (tmp_path / "s.png").read_bytes()[:8] == PNG_MAGIC


def test_run_plot_without_record_leaves_no_recording_behind(tmp_path, monkeypatch):
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", None)  # re-read TMPDIR
    out = tmp_path / "run.png"
    args = ["run", str(GRASP_PROFILE), "--unpaced", "--duration", "0.2", "--no-socket", "-q"]
    assert main([*args, "--plot", str(out)]) == 0
    assert out.read_bytes()[:8] == PNG_MAGIC
    assert list((tmp_path / "tmp").iterdir()) == []


def test_run_plot_without_record_names_no_removed_recording(tmp_path, monkeypatch, capsys):
    """The summary (printed and JSON) does not name the temporary recording the plot was
    made from and then removed (before: it named a file already deleted)."""
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", None)  # re-read TMPDIR
    summary = tmp_path / "s.json"
    args = ["run", str(GRASP_PROFILE), "--unpaced", "--duration", "0.2", "--no-socket"]
    assert main([*args, "--plot", str(tmp_path / "run.png"), "--summary-json", str(summary)]) == 0
    out = capsys.readouterr().out
    rec = json.loads(summary.read_text())["recording"]
    assert rec["path"] is None and rec["temporary"] is True and rec["written"] > 0
    assert str(tmp_path / "tmp") not in out + summary.read_text()
    assert "temporary, for the plot; removed" in out


def test_a_summary_histogram_is_drawn_bin_by_bin(tmp_path):
    s = {
        "ticks": 100,
        "rate_hz": {"target": 1000.0, "achieved": 999.0},
        "period_error_hist_us": [[1.0, 60], [10.0, 30], [200.0, 9]],
        "period_error_us": {"p50": 1.0, "p99": 200.0, "max": 200.0},
        "overruns": 9,
    }
    path = tmp_path / "s.json"
    path.write_text(json.dumps(s))
    ax = plot.figure_for(path).axes[0]
    assert sorted(p.get_height() for p in ax.patches) == [9, 30, 60]
    assert any("overruns 9" in t.get_text() for t in ax.texts)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"hello", "neither a hapticd recording"),
        (recording.MAGIC + b"\xff\xff\xff\x00", "header length"),
        (b"{not json", "not a run summary (JSON)"),
        (b'{"ticks": 3}', "'period_error_hist_us' must be a list of [error_us, count] pairs"),
        (b'{"period_error_hist_us": [[1, "x"]]}', "'period_error_hist_us' must be a list"),
    ],
)
def test_bad_files_get_a_clear_error_naming_the_file(tmp_path, capsys, content, message):
    path = tmp_path / "bad.hrec"
    path.write_bytes(content)
    with pytest.raises(plot.PlotError, match=re.escape(message)) as exc:
        plot.figure_for(path)
    assert str(path) in str(exc.value)
    assert main(["plot", str(path), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and message in err
    assert not (tmp_path / "x.png").exists()


def test_recordings_that_cannot_fill_a_panel_say_which_field_is_missing(tmp_path):
    empty = synthetic(tmp_path / "empty.hrec", ticks=0)
    with pytest.raises(plot.PlotError, match="holds no ticks"):
        plot.recording_figure(empty)
    few = [f for f in recording.loop_fields(2, 2) if not f.name.startswith("residual")]
    rec = synthetic(tmp_path / "few.hrec", fields=few)
    assert "allocation residuals" not in axes_by_title(plot.recording_figure(rec))
    with pytest.raises(plot.PlotError, match="panel 'residuals' needs the field"):
        plot.recording_figure(rec, ["residuals"])
    traj = recording.read(ROOT / "hapticd/data/trajectories/grasp-stiffness.hrec")
    with pytest.raises(plot.PlotError, match="nothing to plot: its fields are t, device_pos"):
        plot.recording_figure(traj)


def test_a_missing_file_and_an_unwritable_output(tmp_path, capsys):
    assert main(["plot", str(tmp_path / "nope.hrec")]) == 2
    assert "nope.hrec: cannot read" in capsys.readouterr().err
    synthetic(tmp_path / "r.hrec")
    assert main(["plot", str(tmp_path / "r.hrec"), "--out", str(tmp_path / "no/dir/x.png")]) == 1
    assert "cannot write the plot" in capsys.readouterr().err


def test_without_matplotlib_the_message_names_the_extra(tmp_path, monkeypatch, capsys):
    synthetic(tmp_path / "r.hrec")
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # import fails
    assert main(["plot", str(tmp_path / "r.hrec"), "--out", str(tmp_path / "x.png")]) == 1
    assert "pip install 'hapticd[plot]'" in capsys.readouterr().err
