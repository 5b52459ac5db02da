"""The documented USB/HID report protocol for delta haptic devices (docs/protocol.md).

Force Dimension's own protocol is not public; open hardware and firmware can
implement this one. A report layout lives in the device description (YAML), so
another device maps without code: each report has an ID (its first byte), a
size, fields (name, type u8/u16/u32/i16/i32/str, offset, optional count, scale
and string length), and the offset of a CRC-16/CCITT over the bytes before it.
Everything is little-endian. ``Codec.decode`` checks ID, length and CRC and
raises ``ReportError`` naming what is wrong; it never returns a half-read report.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass
from typing import Any

from hapticd_drivers.base import DeviceError

_TYPES = {"u8": "B", "u16": "H", "u32": "I", "i16": "h", "i32": "i"}
_CRC_INIT = 0xFFFF


class ReportError(DeviceError):
    """A report that is malformed: wrong ID or length, bad CRC, out-of-range value."""


def crc16(data: bytes) -> int:
    """CRC-16/CCITT (polynomial 0x1021, initial 0xFFFF) of ``data``."""
    return binascii.crc_hqx(data, _CRC_INIT)


@dataclass(frozen=True)
class FieldSpec:
    name: str
    type: str
    offset: int
    count: int = 1
    scale: float | None = None
    length: int = 0  # str only


class Codec:
    """Encodes and decodes one report type from its layout."""

    def __init__(self, name: str, layout: dict[str, Any]) -> None:
        try:
            self.name = name
            self.report_id = int(layout["id"])
            self.size = int(layout["size"])
            self.crc_offset = int(layout["crc_offset"])
            self.fields = [
                FieldSpec(
                    str(f["name"]),
                    str(f["type"]),
                    int(f["offset"]),
                    int(f.get("count", 1)),
                    None if f.get("scale") is None else float(f["scale"]),
                    int(f.get("length", 0)),
                )
                for f in layout["fields"]
            ]
        except (KeyError, TypeError, ValueError) as exc:
            raise ReportError(f"report {name!r}: malformed layout: {exc}") from None
        self._check_layout()

    def _check_layout(self) -> None:
        used = {0}
        if not (0 < self.report_id < 256) or self.crc_offset + 2 > self.size:
            raise ReportError(f"report {self.name!r}: bad id, size or crc_offset")
        used |= {self.crc_offset, self.crc_offset + 1}
        for f in self.fields:
            if f.type == "str":
                width = f.length
            elif f.type in _TYPES:
                width = struct.calcsize("<" + _TYPES[f.type]) * f.count
            else:
                raise ReportError(
                    f"report {self.name!r}: field {f.name!r} has unknown type {f.type!r}"
                )
            span = set(range(f.offset, f.offset + width))
            if width <= 0 or f.offset < 1 or f.offset + width > self.crc_offset or span & used:
                raise ReportError(f"report {self.name!r}: field {f.name!r} overlaps or overflows")
            used |= span

    def encode(self, values: dict[str, Any]) -> bytes:
        """The report's bytes for ``values`` (scaled fields in SI units)."""
        buf = bytearray(self.size)
        buf[0] = self.report_id
        for f in self.fields:
            v = values.get(f.name, 0 if f.type != "str" else "")
            if f.type == "str":
                raw = str(v).encode("ascii", "replace")[: f.length]
                buf[f.offset : f.offset + f.length] = raw.ljust(f.length, b"\0")
                continue
            items = list(v) if f.count > 1 else [v]
            if len(items) != f.count:
                raise ReportError(f"report {self.name!r}: {f.name} needs {f.count} values")
            if f.scale is not None:
                items = [round(float(x) / f.scale) for x in items]
            fmt = "<" + _TYPES[f.type] * f.count
            try:
                struct.pack_into(fmt, buf, f.offset, *(int(x) for x in items))
            except struct.error as exc:
                raise ReportError(
                    f"report {self.name!r}: {f.name} = {v!r} out of range: {exc}"
                ) from None
        struct.pack_into("<H", buf, self.crc_offset, crc16(bytes(buf[: self.crc_offset])))
        return bytes(buf)

    def decode(self, data: bytes) -> dict[str, Any]:
        """Field values of a received report (scaled fields in SI units)."""
        if len(data) != self.size:
            raise ReportError(f"report {self.name!r}: {len(data)} bytes, expected {self.size}")
        if data[0] != self.report_id:
            raise ReportError(f"report {self.name!r}: id {data[0]}, expected {self.report_id}")
        (crc,) = struct.unpack_from("<H", data, self.crc_offset)
        if crc != crc16(bytes(data[: self.crc_offset])):
            raise ReportError(f"report {self.name!r}: CRC mismatch (corrupted report)")
        out: dict[str, Any] = {}
        for f in self.fields:
            if f.type == "str":
                out[f.name] = (
                    bytes(data[f.offset : f.offset + f.length])
                    .rstrip(b"\0")
                    .decode("ascii", "replace")
                )
                continue
            vals = struct.unpack_from("<" + _TYPES[f.type] * f.count, data, f.offset)
            if f.scale is not None:
                vals = tuple(x * f.scale for x in vals)
            out[f.name] = vals if f.count > 1 else vals[0]
        return out


class ReportSet:
    """All report codecs of one device model, from its description's ``reports`` mapping."""

    REQUIRED = ("input", "output", "identity", "limits")

    def __init__(self, reports: dict[str, Any], where: str = "device description") -> None:
        if not isinstance(reports, dict):
            raise ReportError(f"{where}: 'reports' must be a mapping")
        missing = [r for r in self.REQUIRED if r not in reports]
        if missing:
            raise ReportError(f"{where}: reports {missing} are missing")
        self.codecs = {name: Codec(name, layout) for name, layout in reports.items()}

    def __getitem__(self, name: str) -> Codec:
        return self.codecs[name]


def sequence_gap(previous: int, current: int, bits: int = 16) -> int:
    """Reports between two sequence numbers, modulo wrap: 1 is in order, 0 a repeat,
    more than 1 some lost; a large value means out of order."""
    return (current - previous) % (1 << bits)
