"""Recordings: every servo tick as one fixed-size binary record (docs/recording.md).

``read(path)`` returns a ``Recording``: a mapping of field name to numpy array
with the tick axis first (e.g. ``device_pos`` is (ticks, fingers, 3), m).
``Recorder`` is the servo loop's side (a shared-memory ring drained by a writer
process); ``hapticd.recording.export`` writes CSV and MCAP.
"""

from hapticd.recording.format import (
    FORMAT_VERSION,
    MAGIC,
    SUFFIX,
    Field,
    Recording,
    RecordingError,
    RecordingWriter,
    loop_fields,
    make_dtype,
    read,
    trajectory_fields,
    write,
)
from hapticd.recording.recorder import Recorder

__all__ = [
    "FORMAT_VERSION",
    "MAGIC",
    "SUFFIX",
    "Field",
    "Recorder",
    "Recording",
    "RecordingError",
    "RecordingWriter",
    "loop_fields",
    "make_dtype",
    "read",
    "trajectory_fields",
    "write",
]
