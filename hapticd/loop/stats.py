"""Streaming statistics for the servo loop: a log-binned histogram with exact max.

Recording a value costs a log and an integer add (no allocation). Percentiles
come from bin edges, so they are within the bin resolution (about 1%).
"""

from __future__ import annotations

import math

import numpy as np


class LogHistogram:
    """Histogram of non-negative values on log-spaced bins from ``lo`` to ``hi``.

    Values below ``lo`` go to the first bin, above ``hi`` to the last; the
    exact minimum and maximum are kept. ``per_decade`` sets the resolution.
    """

    def __init__(self, lo: float = 1e-9, hi: float = 10.0, per_decade: int = 230) -> None:
        self.lo = lo
        self._log_lo = math.log10(lo)
        self._scale = per_decade
        self.n_bins = math.ceil((math.log10(hi) - self._log_lo) * per_decade) + 1
        self.counts = [0] * self.n_bins
        self.count = 0
        self.max = 0.0
        self.total = 0.0

    def add(self, value: float) -> None:
        if value > self.lo:
            b = int((math.log10(value) - self._log_lo) * self._scale)
            if b >= self.n_bins:
                b = self.n_bins - 1
        else:
            b = 0
        self.counts[b] += 1
        self.count += 1
        self.total += value
        if value > self.max:
            self.max = value

    def _upper_edge(self, b: int) -> float:
        return 10.0 ** (self._log_lo + (b + 1) / self._scale)

    def percentile(self, q: float) -> float:
        """Value at percentile ``q`` (0-100): the upper edge of its bin, at most the max."""
        if self.count == 0:
            return math.nan
        target = q / 100.0 * self.count
        cum = np.cumsum(self.counts)
        b = int(np.searchsorted(cum, max(target, 1e-12)))
        if b == 0 and self.counts[0] and target <= self.counts[0]:
            return min(self.lo, self.max)
        return min(self._upper_edge(min(b, self.n_bins - 1)), self.max)

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else math.nan

    def nonzero(self) -> list[tuple[float, int]]:
        """(upper bin edge, count) of every non-empty bin: the histogram, sparsely."""
        return [(self._upper_edge(b), c) for b, c in enumerate(self.counts) if c]
