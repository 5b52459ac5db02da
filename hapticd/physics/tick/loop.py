"""The servo loop's part of the one call: the check of the devices' samples the loop left
waiting in the frame, the events watcher's question (did in_contact or the buttons change),
and each finger's largest force. Their block of the carried state (LOOP_*), its
declaration and kernels.

Units: positions m, velocities m/s, forces N.
"""

from __future__ import annotations

import numpy as np

from hapticd.physics.tick.layout import Declaration
from hapticd.physics.tick.safety import _norm3

# The loop's block: 1.0 while the devices' samples wait in the frame's device_sample for
# the call's check (the device bank's deferred read; the call clears it), the fastest
# plausible device speed (m/s) and farthest position (m), 1.0 while the loop watches the
# ticks, then (written by the call when it does) 1.0 when in_contact or buttons differ
# from the last tick's; then each finger's largest device force (F, N), its value before
# this tick (F, N), and the last tick's in_contact (F) and buttons (4 F, their bytes).
LOOP_SAMPLES, LOOP_MAX_SPEED, LOOP_MAX_DISTANCE, LOOP_WATCH, LOOP_CHANGED = range(5)
LOOP_HEAD = 5


def plausible(
    p0: float, p1: float, p2: float, v0: float, v1: float, v2: float, speed: float, far: float
) -> bool:
    """Whether a device's sample, position (p0, p1, p2) m and velocity (v0, v1, v2) m/s, is
    one a hand makes: no faster than ``speed`` m/s, no farther than ``far`` m from the
    device's origin, finite (NaN fails every comparison). The one check of a sample: the
    tick's one call runs it compiled, the device bank (hapticd.loop.device_bank) on floats."""
    return _norm3(v0, v1, v2) <= speed and _norm3(p0, p1, p2) <= far


def take_samples(
    record: np.ndarray, state: np.ndarray, lp: int, sp: int, at_pos: int, at_vel: int, n: int
) -> bool:
    """The device bank's check of the samples it read (hapticd.loop.device_bank), compiled:
    the n samples at float ``sp`` of ``record`` (positions, then velocities) copied to
    device_pos (``at_pos``) and device_vel (``at_vel``) when every one is plausible; False,
    nothing written, when one is not. The loop's block at ``lp`` of ``state``."""
    state[lp + LOOP_SAMPLES] = 0.0
    sv = sp + 3 * n
    speed, far = state[lp + LOOP_MAX_SPEED], state[lp + LOOP_MAX_DISTANCE]
    for i in range(n):
        p, v = sp + 3 * i, sv + 3 * i
        if not plausible(
            record[p], record[p + 1], record[p + 2], record[v], record[v + 1], record[v + 2],
            speed, far,
        ):  # fmt: skip
            return False
    for j in range(3 * n):
        record[at_pos + j] = record[sp + j]
        record[at_vel + j] = record[sv + j]
    return True


def watch_changes(raw: np.ndarray, state: np.ndarray, lp: int, ic: int, bt: int, n: int) -> None:
    """Whether in_contact (the record's bytes ``raw`` from ``ic``) or the buttons (from
    ``bt``) changed since the last tick, for the loop's events watcher
    (hapticd.loop.event_ring.FrameEvents), kept for the next."""
    was = lp + LOOP_HEAD + 2 * n
    changed = 0.0
    for j in range(5 * n):  # in_contact's n bytes, then the buttons' 4 n
        b = raw[ic + j] if j < n else raw[bt + j - n]
        if state[was + j] != b:
            state[was + j] = b
            changed = 1.0
    state[lp + LOOP_CHANGED] = changed


def send(
    out_prev: np.ndarray, out: np.ndarray, state: np.ndarray, lp: int, watch: bool, n: int
) -> None:
    """The safety chain's output (out_prev[0]) into the frame's device_force ``out`` (F, 3)
    N; with ``watch``, the loop's statistics: each finger's largest force, and the last."""
    for i in range(n):
        f0, f1, f2 = out_prev[0, i, 0], out_prev[0, i, 1], out_prev[0, i, 2]
        out[i, 0], out[i, 1], out[i, 2] = f0, f1, f2
        if watch:
            top = lp + LOOP_HEAD + i
            was = state[top]
            state[top + n] = was
            mag = _norm3(f0, f1, f2)
            if mag > was:
                state[top] = mag


DECLARATION = Declaration(
    "loop",
    fields=("device_sample",),
    state=(("loop", lambda n, d: (LOOP_HEAD + 8 * n,)),),
    helpers=("plausible", "take_samples", "watch_changes", "send"),
)
