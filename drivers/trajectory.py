"""A recorded fingertip path, interpolated linearly at any time (cursor-based, O(1) per step),
and the buttons held along it (each sample's held until the next); played once, or
again and again (``repeat``) for as long as the run lasts."""

from __future__ import annotations

import numpy as np
from hapticd_drivers.base import DeviceError

Vec = tuple[float, float, float]
Items = np.ndarray | memoryview  # where ``sample`` stores three floats


def check_samples(
    times: np.ndarray, positions: np.ndarray, buttons: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(times (N,) s, positions (N, 3) m, buttons (N,) or None) as float arrays, checked:
    at least 2 samples, every time and position finite, times strictly increasing,
    buttons one 32-bit bit set per sample. DeviceError says which sample is wrong and how
    (the one check for every trajectory: the devices' and ``hapticd check``'s)."""
    t = np.asarray(times, dtype=float).reshape(-1)
    x = np.asarray(positions, dtype=float)
    if x.shape != (t.size, 3):
        raise DeviceError(f"positions {x.shape} do not match times ({t.size},)")
    b = None
    if buttons is not None:
        b = np.asarray(buttons)
        if b.shape != (t.size,) or b.dtype.kind not in "iub":
            raise DeviceError(
                f"buttons must be one integer bit set per sample ({t.size},), "
                f"got {b.dtype} {b.shape}"
            )
        if b.size and (int(b.min()) < 0 or int(b.max()) > 0xFFFFFFFF):
            raise DeviceError("buttons must be 32-bit bit sets (0 to 2**32 - 1)")
    if t.size < 2:
        raise DeviceError(f"{t.size} sample(s); a trajectory needs at least 2")
    bad_t = np.flatnonzero(~np.isfinite(t))
    if bad_t.size:
        i = int(bad_t[0])
        raise DeviceError(f"sample {i} has a non-finite time ({t[i]}); {bad_t.size} of {t.size} do")
    bad_x = np.flatnonzero(~np.all(np.isfinite(x), axis=1))
    if bad_x.size:
        i = int(bad_x[0])
        raise DeviceError(
            f"sample {i} (t = {t[i]:g} s) has a non-finite position {tuple(x[i].tolist())} m; "
            f"{bad_x.size} of {t.size} do"
        )
    step = np.diff(t)
    bad_dt = np.flatnonzero(~(step > 0))
    if bad_dt.size:
        i = int(bad_dt[0]) + 1
        what = "repeats" if t[i] == t[i - 1] else "goes back from"
        raise DeviceError(
            f"sample times must strictly increase: sample {i} (t = {t[i]:g} s) {what} "
            f"sample {i - 1} (t = {t[i - 1]:g} s); {bad_dt.size} such step(s)"
        )
    return t, x, b


# How far a repeated trajectory may end from where it starts, m: a loop that jumps would
# throw the fingertip across the gap in one tick (a glitch the device bank refuses).
REPEAT_GAP_M = 1e-4


class Trajectory:
    """Positions (N, 3) m at strictly increasing times (N,) s, shifted to start at t = 0;
    optionally the device's buttons (N,) (bit i for button i) at each sample. With
    ``repeat`` the path starts again each time it ends (time taken modulo its duration):
    it must end where it starts (within REPEAT_GAP_M)."""

    def __init__(
        self,
        times: np.ndarray,
        positions: np.ndarray,
        who: str,
        buttons: np.ndarray | None = None,
        repeat: bool = False,
    ) -> None:
        try:
            t, x, b = check_samples(times, positions, buttons)
        except DeviceError as exc:
            raise DeviceError(f"{who}: {exc}") from None
        gap = float(np.linalg.norm(x[-1] - x[0]))
        if repeat and not gap <= REPEAT_GAP_M:
            raise DeviceError(
                f"{who}: a repeated trajectory must end where it starts (within "
                f"{REPEAT_GAP_M * 1e3:g} mm); this one ends {gap * 1e3:.3g} mm away"
            )
        self.repeat = bool(repeat)
        self._buttons = None if b is None else [int(v) for v in b.tolist()]
        self._t = (t - t[0]).tolist()
        self._x = [tuple(p) for p in x.tolist()]
        self._slope = [tuple(s) for s in (np.diff(x, axis=0) / np.diff(t)[:, None]).tolist()]
        self._segments = [p + s for p, s in zip(self._x, self._slope, strict=False)]
        self._kmax = len(self._t) - 2  # the last segment's start
        self._k = 0

    @property
    def duration(self) -> float:
        return self._t[-1]

    def _wrap(self, now: float) -> float:
        """``now`` (s) on the path's own time: modulo its duration when it repeats."""
        end = self._t[-1]
        return now % end if self.repeat and now >= end else now

    def buttons_at(self, now: float) -> int:
        """The buttons of the last sample at or before ``now`` (s); 0 without buttons. Call
        after ``at(now)``: it reuses the cursor."""
        b = self._buttons
        if b is None:
            return 0
        now = self._wrap(now)
        last = len(self._t) - 1
        return b[last] if now >= self._t[last] else b[self._k] if now >= self._t[0] else b[0]

    def at(self, now: float) -> tuple[Vec, Vec]:
        """(position m, velocity m/s) at time ``now`` (s); held at the ends, zero velocity there
        (a repeated path has no end)."""
        t, last = self._t, len(self._t) - 1
        if self.repeat and now >= t[last]:
            now %= t[last]
        k = self._k
        if now < t[k]:
            k = 0  # time went back (a new run): search from the start
        while k < last - 1 and now >= t[k + 1]:
            k += 1
        self._k = k
        if now >= t[last]:
            return self._x[last], (0.0, 0.0, 0.0)
        x0 = self._x[k]
        if now < t[0]:
            return x0, (0.0, 0.0, 0.0)
        s = self._slope[k]
        dt = now - t[k]
        return (x0[0] + s[0] * dt, x0[1] + s[1] * dt, x0[2] + s[2] * dt), s

    def sample(self, now: float, position: Items, velocity: Items) -> int:
        """``at(now)`` written into ``position`` and ``velocity`` ((3,) arrays or memoryviews,
        m and m/s; the same numbers), and ``buttons_at(now)`` returned: a device's read in
        one call, with no tuple built for the sample."""
        t = self._t
        k = self._k
        # A tick's usual step: the cursor's segment [t[k], t[k + 1]) or the next one (then
        # at() finds the same segment: the time is inside the path, and no wrap).
        if now >= t[k + 1]:
            k += 1
            if k > self._kmax or now >= t[k + 1]:
                return self._sample_far(now, position, velocity)
        elif not now >= t[k]:
            return self._sample_far(now, position, velocity)
        self._k = k
        # The segment's start and slope in one tuple: the same numbers as at()'s.
        x0, x1, x2, s0, s1, s2 = self._segments[k]
        dt = now - t[k]
        position[0] = x0 + s0 * dt
        position[1] = x1 + s1 * dt
        position[2] = x2 + s2 * dt
        velocity[0] = s0
        velocity[1] = s1
        velocity[2] = s2
        b = self._buttons
        return 0 if b is None else b[k]

    def _sample_far(self, now: float, position: Items, velocity: Items) -> int:
        """``sample`` when the time is beyond the cursor's next segment, before its segment
        (a new run), or past either end: ``at`` and ``buttons_at``."""
        pos, vel = self.at(now)
        position[0], position[1], position[2] = pos
        velocity[0], velocity[1], velocity[2] = vel
        return self.buttons_at(now)
