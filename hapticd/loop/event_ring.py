"""The servo loop's events on their way out: a preallocated ring, and the frame watcher.

The loop (one producer) writes fixed-size records to ``EventRing``; the control
server (one consumer, another thread of the same process) drains them in the
loop's sleep window. A push never allocates an array, formats or logs, and
never waits: when the ring is full the event is counted as lost (``lost``) and
the server reports the count. ``FrameEvents`` finds contact and button
transitions by comparing the tick frame's ``in_contact`` and ``buttons`` with
its own copies of the previous tick's (a byte comparison through memoryviews
made once: tens of nanoseconds on a tick without change). Kinds and causes are
declared in ``hapticd.events``.
"""

from __future__ import annotations

import struct

import numpy as np

from hapticd.events import CODES
from hapticd.physics.frame import Frame

# One event: its kind (index into hapticd.events.EVENTS), finger and button (-1: none),
# a value (a fault cause or parameter index; -1: none), its tick and that tick's time (s).
RECORD = np.dtype(
    [
        ("kind", "u1"),
        ("finger", "i1"),
        ("button", "i1"),
        ("value", "<i4"),
        ("tick", "<u8"),
        ("t", "<f8"),
    ]
)
# A record packed as RECORD lays it out (little-endian, no padding).
_PACK = struct.Struct("<BbbiQd").pack_into
_SIZE = RECORD.itemsize
assert struct.calcsize("<BbbiQd") == _SIZE and not RECORD.isalignedstruct
DEFAULT_CAPACITY = 8192  # events; the server drains every few ms, a tick makes a handful

CONTACT_BEGIN = CODES["contact_begin"]
CONTACT_END = CODES["contact_end"]
BUTTON_DOWN = CODES["button_down"]
BUTTON_UP = CODES["button_up"]
BUTTON_BITS = 32  # buttons is a u4 bit set per finger


class EventRing:
    """A single-producer single-consumer ring of ``capacity`` event records.

    Producer (the servo thread): ``push``. Consumer (the control thread): ``drain``.
    Both run under the GIL, which orders their plain attribute reads and writes;
    the producer publishes a record by advancing ``head`` after writing it, the
    consumer frees space by advancing ``tail`` after copying. A full ring drops
    the new event (``lost``, ``lost_tick``): the loop never waits for a reader.
    """

    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        if capacity < 1:
            raise ValueError(f"an event ring needs room for at least one event, got {capacity}")
        self.capacity = int(capacity)
        self.records = np.zeros(self.capacity, dtype=RECORD)
        self._bytes = memoryview(self.records).cast("B")  # what a push packs a record into
        self.head = 0  # events written (producer)
        self.tail = 0  # events read (consumer)
        self.lost = 0  # events dropped because the ring was full (producer)
        self.lost_tick = 0  # tick of the last event dropped
        self.lost_t = 0.0
        self._lost_reported = 0  # (consumer)

    def push(
        self, kind: int, tick: int, t: float, finger: int = -1, button: int = -1, value: int = -1
    ) -> None:
        """Append one event (from the servo thread); counted as lost when the ring is full."""
        head = self.head
        if head - self.tail >= self.capacity:
            self.lost += 1
            self.lost_tick = tick
            self.lost_t = t
            return
        # One C call for the whole record (six numpy item stores took about 0.9 us).
        _PACK(self._bytes, (head % self.capacity) * _SIZE, kind, finger, button, value, tick, t)
        self.head = head + 1  # published: the record is complete

    @property
    def pending(self) -> bool:
        """Is there anything to drain (events or a loss not yet reported)?"""
        return self.head != self.tail or self.lost != self._lost_reported

    def drain(self) -> tuple[np.ndarray, int]:
        """(the events written since the last drain, in order, as a copy; how many were lost
        since the last drain, all of them after those events). Consumer side only.

        A loss while this runs (the ring still full) is counted by the next drain, after
        the events it returns: those may have been made after that loss."""
        # The loss count first: a loss happens only on a full ring, whose head cannot move
        # until tail does, so every loss counted here came after every event copied below.
        lost = self.lost
        head, tail = self.head, self.tail
        if head == tail:
            out = self.records[:0].copy()
        else:
            idx = np.arange(tail, head) % self.capacity
            out = self.records[idx]
        self.tail = head
        new_losses = lost - self._lost_reported
        self._lost_reported = lost
        return out, new_losses


class FrameEvents:
    """Pushes ``contact_begin``/``contact_end`` and ``button_down``/``button_up`` events when
    the frame's ``in_contact`` or ``buttons`` differ from the previous tick's (both start at
    zero: a finger already touching on tick 0 begins its contact there).

    It counts each finger's ticks in contact on the way (``contact_ticks``): at each
    contact's end, and for contacts still going on when asked, so a tick without a change
    counts nothing."""

    def __init__(self, ring: EventRing, n_fingers: int) -> None:
        self.ring = ring
        self.n_fingers = n_fingers
        self.tick = -1  # the last tick watched
        self._closed = [0] * n_fingers  # ticks in contacts that have ended
        self._since = [0] * n_fingers  # the first tick of each finger's current contact
        self._contact = np.zeros(n_fingers, dtype=np.uint8)
        self._buttons = np.zeros(n_fingers, dtype=np.uint32)
        self._was_contact = memoryview(self._contact)
        self._was_buttons = memoryview(self._buttons.view(np.uint8))
        self._frame: Frame | None = None
        self._now_contact = self._was_contact
        self._now_buttons = self._was_buttons

    @property
    def seen(self) -> tuple[np.ndarray, np.ndarray]:
        """What the watcher saw last: ``in_contact`` (F,) u1 and the ``buttons``' bytes (4 F,)
        (copies; the one call compares the frame against them, hapticd.loop.servo)."""
        return self._contact.copy(), self._buttons.view(np.uint8).copy()

    def _bind(self, frame: Frame) -> None:
        """Watch ``frame`` (a reload gives the loop a new one)."""
        self._frame = frame
        self._now_contact = memoryview(frame.in_contact)
        self._now_buttons = memoryview(frame.buttons.view(np.uint8))

    def after_tick(self, frame: Frame, tick: int, t: float) -> None:
        """Compare the tick's frame with the previous tick's; push what changed."""
        if frame is not self._frame:
            self._bind(frame)
        self.tick = tick
        if self._now_contact != self._was_contact:
            self._contacts(frame, tick, t)
        if self._now_buttons != self._was_buttons:
            self._button_changes(frame, tick, t)

    def _contacts(self, frame: Frame, tick: int, t: float) -> None:
        now, was = frame.in_contact, self._contact
        push = self.ring.push
        for i in range(self.n_fingers):
            a, b = int(was[i]), int(now[i])
            if a != b:
                push(CONTACT_BEGIN if b else CONTACT_END, tick, t, i)
                if b:
                    self._since[i] = tick
                else:
                    self._closed[i] += tick - self._since[i]
        was[...] = now

    def contact_ticks(self) -> list[int]:
        """Each finger's ticks in contact over the ticks watched so far."""
        out = list(self._closed)
        for i in range(self.n_fingers):
            if self._contact[i]:
                out[i] += self.tick + 1 - self._since[i]
        return out

    def _button_changes(self, frame: Frame, tick: int, t: float) -> None:
        now, was = frame.buttons, self._buttons
        push = self.ring.push
        for i in range(self.n_fingers):
            a, b = int(was[i]), int(now[i])
            changed = a ^ b
            bit = 0
            while changed and bit < BUTTON_BITS:
                if changed & 1:
                    push(BUTTON_DOWN if (b >> bit) & 1 else BUTTON_UP, tick, t, i, bit)
                changed >>= 1
                bit += 1
        was[...] = now
