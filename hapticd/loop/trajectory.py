"""Motion model for synthetic fingertip trajectories (the bundled replay files).

A trajectory is a sequence of segments per finger, each ``duration_s`` long:
``minjerk`` moves from the current point to ``target`` along the minimum-jerk
profile (Flash & Hogan 1985: zero velocity and acceleration at both ends);
``hold`` stays put; ``squeeze`` oscillates ``amplitude_m`` along ``axis`` at
``freq_hz`` under a sin^2 envelope (``ramp_s``) so velocity stays continuous.
Sampled at ``rate_hz``. Pure: numpy in, numpy out. See docs/trajectories.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MinJerk:
    duration_s: float
    target: tuple[float, float, float]


@dataclass(frozen=True)
class Hold:
    duration_s: float


@dataclass(frozen=True)
class Squeeze:
    duration_s: float
    axis: tuple[float, float, float]
    amplitude_m: float
    freq_hz: float
    ramp_s: float = 0.3


Segment = MinJerk | Hold | Squeeze


def minjerk_profile(s: np.ndarray) -> np.ndarray:
    """Normalised minimum-jerk position 10 s^3 - 15 s^4 + 6 s^5 for s in [0, 1]."""
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s)


def _envelope(tau: np.ndarray, duration: float, ramp: float) -> np.ndarray:
    ramp = min(ramp, 0.5 * duration)
    if ramp <= 0:
        return np.ones_like(tau)
    up = np.sin(0.5 * np.pi * np.clip(tau / ramp, 0, 1)) ** 2
    down = np.sin(0.5 * np.pi * np.clip((duration - tau) / ramp, 0, 1)) ** 2
    return np.minimum(up, down)


def sample(
    start: np.ndarray, segments: list[Segment], rate_hz: float
) -> tuple[np.ndarray, np.ndarray]:
    """Times (N,) s and positions (N, 3) m of one finger starting at ``start`` (3,) m."""
    total = sum(seg.duration_s for seg in segments)
    n = round(total * rate_hz) + 1
    t = np.arange(n) / rate_hz
    x = np.repeat(np.asarray(start, dtype=float).reshape(1, 3), n, axis=0)
    here = np.asarray(start, dtype=float).reshape(3)
    t_seg = 0.0
    for seg in segments:
        if seg.duration_s <= 0:
            raise ValueError("segment durations must be positive")
        mask = t >= t_seg - 1e-12
        tau = t[mask] - t_seg
        if isinstance(seg, MinJerk):
            goal = np.asarray(seg.target, dtype=float)
            prof = minjerk_profile(tau / seg.duration_s)[:, None]
            x[mask] = here + prof * (goal - here)
            here = goal
        elif isinstance(seg, Hold):
            x[mask] = here
        else:
            axis = np.asarray(seg.axis, dtype=float)
            axis = axis / np.linalg.norm(axis)
            inside = tau <= seg.duration_s
            env = _envelope(np.minimum(tau, seg.duration_s), seg.duration_s, seg.ramp_s)
            wave = seg.amplitude_m * env * np.sin(2 * np.pi * seg.freq_hz * tau)
            x[mask] = here + np.where(inside, wave, 0.0)[:, None] * axis
        t_seg += seg.duration_s
    return t, x


def two_finger(
    starts: list[np.ndarray], plans: list[list[Segment]], rate_hz: float
) -> tuple[np.ndarray, np.ndarray]:
    """Times (N,) and positions (N, F, 3) for F fingers with plans of equal total length."""
    totals = {round(sum(s.duration_s for s in p), 9) for p in plans}
    if len(totals) != 1:
        raise ValueError(f"finger plans must last equally long, got {sorted(totals)}")
    samples = [sample(s, p, rate_hz) for s, p in zip(starts, plans, strict=True)]
    t = samples[0][0]
    return t, np.stack([x for _, x in samples], axis=1)
