"""The documented report protocol: round trips, corruption, malformed layouts."""

import pytest
from hapticd_drivers.delta import load_description
from hapticd_drivers.reports import Codec, ReportError, ReportSet, sequence_gap
from hypothesis import given
from hypothesis import strategies as st

PROTO = ReportSet(load_description("delta-omega-class").reports)

i32 = st.integers(-(2**31), 2**31 - 1)
u16 = st.integers(0, 2**16 - 1)


@given(
    st.integers(0, 255),
    u16,
    st.integers(0, 2**32 - 1),
    st.lists(i32, min_size=3, max_size=3),
    u16,
    u16,
)
def test_input_report_round_trip(status, seq, t_us, enc, buttons, ack):
    values = {
        "status": status,
        "sequence": seq,
        "time_us": t_us,
        "encoder": tuple(enc),
        "buttons": buttons,
        "ack_sequence": ack,
    }
    raw = PROTO["input"].encode(values)
    assert len(raw) == 32 and raw[0] == 1
    assert PROTO["input"].decode(raw) == values


@given(st.lists(st.integers(-32768, 32767), min_size=3, max_size=3), u16)
def test_output_report_carries_currents_in_amperes(milliamps, seq):
    currents = tuple(m / 1000 for m in milliamps)
    raw = PROTO["output"].encode({"flags": 1, "sequence": seq, "current": currents})
    out = PROTO["output"].decode(raw)
    assert out["flags"] == 1 and out["sequence"] == seq
    assert out["current"] == pytest.approx(currents, abs=1e-12)


def test_feature_reports_round_trip():
    ident = PROTO["identity"].decode(
        PROTO["identity"].encode(
            {"model": "delta-omega-class", "serial": "SN-0042", "firmware": 0x0103}
        )
    )
    assert ident == {"model": "delta-omega-class"[:16], "serial": "SN-0042", "firmware": 0x0103}
    lim = PROTO["limits"].decode(
        PROTO["limits"].encode({"max_current": 3.2, "watchdog": 0.005, "counts_per_rev": 4096})
    )
    assert lim["max_current"] == pytest.approx(3.2) and lim["watchdog"] == pytest.approx(0.005)


@given(st.integers(0, 32 * 8 - 1))
def test_every_single_bit_corruption_is_detected(bit):
    raw = bytearray(PROTO["input"].encode({"sequence": 7, "encoder": (1, -2, 3)}))
    raw[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(ReportError, match=r"CRC mismatch|id "):
        PROTO["input"].decode(bytes(raw))


def test_wrong_length_id_and_out_of_range_values():
    codec = PROTO["output"]
    raw = codec.encode({"current": (0.1, 0.2, 0.3)})
    with pytest.raises(ReportError, match="15 bytes, expected 16"):
        codec.decode(raw[:-1])
    with pytest.raises(ReportError, match="id 1, expected 2"):
        codec.decode(bytes([1]) + raw[1:])
    with pytest.raises(ReportError, match=r"current .* out of range"):
        codec.encode({"current": (40.0, 0.0, 0.0)})  # 40 A does not fit 16 bits of mA
    with pytest.raises(ReportError, match="needs 3 values"):
        codec.encode({"current": (0.1, 0.2)})


def test_sequence_gaps_wrap():
    assert sequence_gap(65535, 0) == 1
    assert sequence_gap(10, 10) == 0
    assert sequence_gap(10, 13) == 3
    assert sequence_gap(10, 9) == 65535  # out of order


@pytest.mark.parametrize(
    ("layout", "match"),
    [
        (
            {
                "id": 5,
                "size": 8,
                "crc_offset": 6,
                "fields": [{"name": "a", "type": "u32", "offset": 4}],
            },
            "overlaps or overflows",
        ),
        (
            {
                "id": 5,
                "size": 8,
                "crc_offset": 6,
                "fields": [{"name": "a", "type": "f32", "offset": 1}],
            },
            "unknown type",
        ),
        ({"id": 5, "size": 8, "crc_offset": 7, "fields": []}, "bad id, size or crc_offset"),
        ({"id": 5, "size": 8, "fields": []}, "malformed layout"),
    ],
)
def test_bad_layouts_are_rejected(layout, match):
    with pytest.raises(ReportError, match=match):
        Codec("x", layout)


def test_a_description_without_the_required_reports():
    with pytest.raises(
        ReportError, match=r"reports \['output', 'identity', 'limits'\] are missing"
    ):
        ReportSet({"input": {"id": 1, "size": 4, "crc_offset": 2, "fields": []}})
