"""The tick frame: one declaration that the recording, the docs and the loop derive from."""

from __future__ import annotations

import numpy as np
import pytest

from hapticd import recording
from hapticd.physics.frame import FIELDS, Frame, markdown_table
from hapticd.recording import Recorder
from tests.conftest import ROOT


def test_each_field_is_a_view_of_one_record():
    frame = Frame(2, 3)
    assert frame.device_pos.shape == (2, 3) and frame.lam_a.shape == (3,)
    assert frame.object_rot.shape == (3, 3) and frame.alpha.shape == ()
    frame.device_pos[1, 2] = 0.25
    frame.alpha[()] = 0.5
    assert frame.record["device_pos"][1, 2] == 0.25 and frame.record["alpha"] == 0.5
    copy = frame.copy()
    frame.alpha[()] = 0.0
    assert float(copy.alpha) == 0.5
    with pytest.raises(AttributeError, match="no field 'devise_pos'"):
        _ = frame.devise_pos


def test_the_recorded_bytes_are_the_recorded_fields_in_file_order():
    frame = Frame(2, 2)
    rng = np.random.default_rng(1)
    for f in FIELDS:
        view = frame.get(f.name)
        view[...] = (
            rng.integers(0, 200, view.shape) if view.dtype.kind == "u" else rng.random(view.shape)
        )
    rows = frame.recorded.view(frame.recorded_dtype)
    names = [f.name for f in FIELDS if f.recorded]
    assert list(frame.recorded_dtype.names) == names
    assert [f.name for f in recording.loop_fields(2, 2)] == names
    assert recording.make_dtype(recording.loop_fields(2, 2)) == frame.recorded_dtype
    for name in names:
        np.testing.assert_array_equal(rows[name][0], frame.get(name), err_msg=name)
    assert "surface_point" not in names


@pytest.mark.parametrize("n_fingers", [1, 2, 3, 5])
@pytest.mark.parametrize("n_actuators", [1, 2, 3, 7])
def test_every_field_is_aligned_in_the_record(n_fingers, n_actuators):
    # A compiled kernel types an aligned float64 array at numba's fast door; an unaligned
    # one (a record packed with a 1-byte field before it) costs far more per call.
    frame = Frame(n_fingers, n_actuators)
    for f in FIELDS:
        view = frame.get(f.name)
        assert view.flags.aligned, f.name
        assert frame.record.dtype.fields[f.name][1] % view.dtype.itemsize == 0, f.name
    assert len(frame.recorded) == frame.recorded_dtype.itemsize


def test_same_shaped_fields_land_in_their_own_columns(tmp_path):
    # Recording copies the frame's bytes: a field can only be read back under its own name.
    frame = Frame(2, 2)
    fields = recording.loop_fields(2, 2)
    rec = Recorder(tmp_path / "r.hrec", fields, ["a", "b"], block_when_full=True)
    try:
        rec.wait_running()
        for k in range(5):
            frame.tick[()] = k
            frame.device_pos[:] = k
            frame.proxy_pos[:] = -k
            frame.contact_force[:] = 10 * k
            frame.rendered_force[:] = 100 * k
            rec.append(frame.recorded)
    finally:
        rec.close()
    got = recording.read(tmp_path / "r.hrec")
    ks = np.arange(5.0)[:, None, None]
    np.testing.assert_array_equal(got["tick"], np.arange(5))
    np.testing.assert_array_equal(got["device_pos"], np.broadcast_to(ks, (5, 2, 3)))
    np.testing.assert_array_equal(got["proxy_pos"], np.broadcast_to(-ks, (5, 2, 3)))
    np.testing.assert_array_equal(got["contact_force"], np.broadcast_to(10 * ks, (5, 2, 3)))
    np.testing.assert_array_equal(got["rendered_force"], np.broadcast_to(100 * ks, (5, 2, 3)))
    assert got.units()["device_pos"] == "m" and got.units()["contact_force"] == "N"


def test_every_field_names_its_unit_and_meaning():
    for f in FIELDS:
        assert f.doc, f.name
        if f.name.endswith(("_pos", "_point", "_proxy")):
            assert f.unit == "m", f.name
        if f.name.endswith("_force"):
            assert f.unit == "N", f.name


def test_the_docs_table_is_the_declaration():
    text = (ROOT / "docs" / "recording.md").read_text()
    assert markdown_table() in text, "docs/recording.md: regenerate with markdown_table()"


@pytest.mark.parametrize(("n_fingers", "n_actuators"), [(1, 1), (2, 2), (5, 15)])
def test_the_fields_the_call_reads_as_one_run_are_adjacent_float64(n_fingers, n_actuators):
    # kernels.tick_step reads each of these runs from its first field's offset on.
    fields = Frame(n_fingers, n_actuators).dtype.fields
    for run in (
        ("residual_internal", "residual_external", "residual_total", "amplification", "alpha"),
        ("object_pos", "object_vel", "object_omega", "object_rot"),
    ):
        at = fields[run[0]][1]
        for name in run:
            dtype, offset = fields[name][:2]
            assert (offset, dtype.base) == (at, np.float64), name
            at += dtype.itemsize
