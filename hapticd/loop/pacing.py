"""Pacing of a fixed-rate loop: the deadline grid, the sleep gate, overruns, re-anchoring.

Ticks run on a grid of absolute deadlines on the monotonic clock (no drift):
the loop sleeps until ``SPIN_MARGIN_S`` before a deadline and spins the rest.
Just before it sleeps it writes a byte to the *sleep gate*, a pipe another
thread may wait on to do its Python work while the loop sleeps (so the loop
never waits for the GIL; docs/daemon.md). An unpaced pacer never waits: ticks
run as fast as they can on the nominal clock. Times in s.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

from hapticd.loop.stats import LogHistogram

OVERRUN_FACTOR = 1.1
# Sleep until this long before a deadline, then spin: measured in docs/daemon.md. The
# default of the profile's loop.spin_s.
SPIN_MARGIN_S = 200e-6
# If the loop falls this many periods behind, it re-anchors instead of bursting.
REANCHOR_PERIODS = 10
# Paced runs start this long after ``start``: the first deadline is not already late.
START_DELAY_S = 2e-3


@dataclass
class LoopStats:
    """Timing gathered while the loop runs (s), and per-finger force and contact counts
    (``contact_ticks`` brought up to date when the loop stops)."""

    period_error: LogHistogram = field(default_factory=LogHistogram)
    compute: LogHistogram = field(default_factory=LogHistogram)
    ticks: int = 0
    overruns: int = 0
    reanchors: int = 0
    first_start: float = 0.0
    last_start: float = 0.0
    max_force: list[float] = field(default_factory=list)
    contact_ticks: list[int] = field(default_factory=list)


def wait_until(deadline: float, margin: float) -> None:
    """Sleep until ``margin`` s before ``deadline`` (monotonic s), then spin to it."""
    remaining = deadline - time.monotonic()
    if remaining > margin:
        time.sleep(remaining - margin)
    while time.monotonic() < deadline:
        pass


class Pacer:
    """Deadlines for ticks at ``rate_hz``; ``paced`` False runs them back to back. A paced
    loop spins the last ``spin_s`` s before each deadline (at most half the period).

    ``max_consecutive_overruns`` periods in a row longer than ``OVERRUN_FACTOR`` x
    the period make ``begin`` report sustained lateness (0: never).
    """

    def __init__(
        self,
        rate_hz: float,
        paced: bool,
        max_consecutive_overruns: int = 0,
        spin_s: float = SPIN_MARGIN_S,
    ) -> None:
        self.rate_hz = float(rate_hz)
        self.period = 1.0 / self.rate_hz
        self.paced = paced
        self.max_consecutive_overruns = max_consecutive_overruns if paced else 0
        self.margin = min(max(float(spin_s), 0.0), 0.5 * self.period)
        self.stats = LoopStats()
        self.t0 = 0.0
        # Tick 0's due time (monotonic s): where ``t_wall`` counts from; unlike ``t0`` it is
        # never moved by ``catch_up``, so ``origin + t_wall`` is a tick's monotonic start.
        self.origin = 0.0
        self.sleep_until = 0.0  # when the loop's current sleep ends, less the spin
        self._prev = 0.0
        self._period_error = 0.0  # tick k's (k > 0), from ``begin`` to ``end`` (s)
        self._late = 0
        self._gate_w = -1

    # -- the sleep gate ---------------------------------------------------------------------

    def open_sleep_gate(self) -> int:
        """A pipe the loop writes a byte to just before each sleep; returns its read end."""
        r, w = os.pipe()
        os.set_blocking(r, False)
        os.set_blocking(w, False)
        self._gate_w = w
        return r

    def close_sleep_gate(self) -> None:
        w, self._gate_w = self._gate_w, -1
        if w >= 0:
            os.close(w)

    # -- ticks -------------------------------------------------------------------------------

    def start(self) -> None:
        """Anchor the grid: tick 0 is due now (paced: a moment from now)."""
        self.t0 = self.origin = time.monotonic() + (START_DELAY_S if self.paced else 0.0)
        self._late = 0

    def begin(self, k: int) -> tuple[float, str | None]:
        """Wait for tick ``k``'s deadline; (its start, monotonic s; a lateness fault or None)."""
        st = self.stats
        if self.paced:
            deadline = self.t0 + k * self.period
            if self._gate_w >= 0:
                # The loop is about to sleep: the other thread's window to take the GIL.
                self.sleep_until = deadline - self.margin
                try:  # noqa: SIM105 - suppress() would allocate every tick
                    os.write(self._gate_w, b"\0")
                except BlockingIOError:
                    pass  # nobody is waiting; the pipe is full of old news
            wait_until(deadline, self.margin)
        start = time.monotonic()
        fault = None
        if k == 0:
            st.first_start = start
        else:
            period = start - self._prev
            # Added to its histogram in ``end``, once the tick's forces are out.
            self._period_error = abs(period - self.period)
            if period > OVERRUN_FACTOR * self.period:
                st.overruns += 1
                self._late += 1
                if self._late == self.max_consecutive_overruns:
                    fault = (
                        f"overrun: {self._late} consecutive ticks longer than "
                        f"{OVERRUN_FACTOR:g}x the period"
                    )
            else:
                self._late = 0
        self._prev = start
        return start, fault

    def end(self, k: int, start: float) -> float:
        """Tick ``k`` that began at ``start`` is done; returns its compute time (s)."""
        compute = time.monotonic() - start
        st = self.stats
        if k:
            st.period_error.add(self._period_error)  # this tick's, measured in ``begin``
        st.compute.add(compute)
        st.ticks = k + 1
        st.last_start = start
        return compute

    def catch_up(self, k: int) -> None:
        """Before tick ``k``: re-anchor the grid if the loop fell far behind."""
        if self.paced and time.monotonic() - (self.t0 + k * self.period) > (
            REANCHOR_PERIODS * self.period
        ):
            self.t0 = time.monotonic() - k * self.period
            self.stats.reanchors += 1
