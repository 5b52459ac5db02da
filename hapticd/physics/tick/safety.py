"""The safety chain's tick (hapticd.physics.safety.SafetyChain's kernel, and the one call's
last stage): the deadman gates, the finite and workspace checks, the clamp, the ramps and
the rate limit. Its declaration, its array's layout (SAFETY_*) and its kernel
(``safety_step``), split into the gates, the trips and each finger's limits.

Units: forces N, positions m, times s.
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.physics.tick.layout import Declaration

# The safety chain's array (hapticd.physics.safety.SafetyChain's, safety_step's ``params``):
# its parameters and the state it carries from tick to tick. The rate limit's largest
# change a tick (N; inf: off), the workspace's radius (m; inf: off) and centre (3, m), the
# enable ramp's length (s), when forces were enabled (s, nominal), when the ramp-down
# begins (s; inf: none) and its length (s), 1.0 while a fault is latched (forces zero, the
# deadman gates still follow their buttons), the ticks on which a force was clamped and on
# which one was rate limited, and the distance from the centre of the finger that left the
# workspace (m, written when one does); then SAFETY_COLUMNS blocks of F items, one item a
# finger: its force limit (N), its deadman button (-1: none), that deadman's ramp (s), when
# the button went down (s, nominal; inf: up) and the deadman's gate on the last tick (0 to
# 1; 1 without a deadman).
SAFETY_RATE, SAFETY_RADIUS, SAFETY_CENTRE = 0, 1, 2
SAFETY_RAMP_S, SAFETY_T_ENABLED, SAFETY_T_DOWN, SAFETY_DOWN_S = 5, 6, 7, 8
SAFETY_LATCHED, SAFETY_CLAMPED_TICKS, SAFETY_LIMITED_TICKS, SAFETY_DISTANCE = 9, 10, 11, 12
SAFETY_PARAMS = 13
SAFETY_LIMIT, SAFETY_BUTTON, SAFETY_BUTTON_RAMP, SAFETY_PRESSED, SAFETY_GATE = range(5)
SAFETY_COLUMNS = 5
# safety_step's outcome: bit flags of a tick made safe (a force clamped, a force rate
# limited), or of a trip, with the output zeroed (the chain latches the fault, with its
# message): a non-finite force, the bits from SAFETY_FINGERS on naming its fingers (bit
# SAFETY_FINGERS + i: finger i), or a finger beyond the workspace's radius, the bits from
# SAFETY_FINGERS on its index.
SAFETY_CLAMPED, SAFETY_LIMITED, SAFETY_NON_FINITE, SAFETY_WORKSPACE = 1, 2, 4, 8
SAFETY_FINGERS = 4


def _norm3(x0: float, x1: float, x2: float) -> float:
    """The length of (x0, x1, x2), scaled by its largest magnitude so that no square
    overflows or underflows (a force of 1e200 N keeps its direction when clamped); inf
    for an infinite argument, NaN for a NaN one (every comparison then fails)."""
    a0, a1, a2 = abs(x0), abs(x1), abs(x2)
    top = a1 if a1 > a0 else a0
    top = a2 if a2 > top else top
    if top == 0.0 or math.isinf(top):
        # A NaN beside zeros or an infinity: the comparisons above skipped it.
        return top if a0 == a0 and a1 == a1 and a2 == a2 else math.nan
    a0, a1, a2 = a0 / top, a1 / top, a2 / top
    return top * math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)


def ramp_down_factor(t: float, t_down: float, down_s: float) -> float:
    """The ramp-down's factor at nominal time ``t`` (s): 1 before ``t_down`` (s), then
    falling to exactly 0 after ``down_s`` (s): tick times carry rounding, and a remainder
    of 1e-15 must not leave a force of 1e-15 N. safety_step's, and the chain's
    ``ramped_down``."""
    if t < t_down:
        return 1.0
    left = 1.0 - (t - t_down) / down_s if down_s > 0.0 else 0.0
    return left if left > 1e-9 else 0.0


def _gates(buttons: np.ndarray, params: np.ndarray, n: int, t: float) -> None:
    """Each deadman's gate at nominal time ``t`` (s) from its button (the frame's button
    bytes ``buttons``): 0 while up, then rising over its ramp; written into ``params``."""
    gates = SAFETY_PARAMS + SAFETY_GATE * n
    for i in range(n):
        button = params[SAFETY_PARAMS + SAFETY_BUTTON * n + i]
        if button < 0.0:
            continue
        # The gate follows its button also while a fault holds the forces at zero.
        bit = int(button)
        pressed = SAFETY_PARAMS + SAFETY_PRESSED * n + i
        if (int(buttons[4 * i + bit // 8]) >> (bit % 8)) & 1 == 0:
            params[pressed] = math.inf
            params[gates + i] = 0.0
            continue
        if params[pressed] == math.inf:
            params[pressed] = t
        held = t - params[pressed]
        ramp_s = params[SAFETY_PARAMS + SAFETY_BUTTON_RAMP * n + i]
        params[gates + i] = 1.0 if ramp_s <= 0.0 or held >= ramp_s else held / ramp_s


def _trips(forces: np.ndarray, positions: np.ndarray, params: np.ndarray, n: int) -> int:
    """-1 while a fault is latched; else a trip's SAFETY_ outcome (a non-finite force, a
    finger beyond the workspace), or 0."""
    if params[SAFETY_LATCHED] != 0.0:
        return -1
    outcome = 0
    for i in range(n):
        f0, f1, f2 = forces[i, 0], forces[i, 1], forces[i, 2]
        if not (math.isfinite(f0) and math.isfinite(f1) and math.isfinite(f2)):
            outcome |= 1 << (SAFETY_FINGERS + i)
    if outcome != 0:
        return outcome | SAFETY_NON_FINITE
    if math.isfinite(params[SAFETY_RADIUS]):
        c0, c1, c2 = params[SAFETY_CENTRE], params[SAFETY_CENTRE + 1], params[SAFETY_CENTRE + 2]
        for i in range(n):
            r = _norm3(positions[i, 0] - c0, positions[i, 1] - c1, positions[i, 2] - c2)
            if not r <= params[SAFETY_RADIUS]:
                params[SAFETY_DISTANCE] = r
                return SAFETY_WORKSPACE | (i << SAFETY_FINGERS)
    return outcome


def _ramp(params: np.ndarray, t: float) -> float:
    """The smaller of the enable ramp's and the ramp-down's factors at ``t`` (s), 0 to 1."""
    ramp = 1.0
    ramp_s = params[SAFETY_RAMP_S]
    if ramp_s > 0.0:
        ramp = (t - params[SAFETY_T_ENABLED]) / ramp_s
        if not ramp > 0.0:
            ramp = 0.0
        elif not ramp < 1.0:
            ramp = 1.0
    down = ramp_down_factor(t, params[SAFETY_T_DOWN], params[SAFETY_DOWN_S])
    return down if down < ramp else ramp


def _limited(
    forces: np.ndarray, params: np.ndarray, out_prev: np.ndarray, i: int, n: int, ramp: float
) -> int:
    """Finger i's force clamped (direction kept), scaled by the smaller of ``ramp`` and its
    gate, rate limited from the last tick's, into out_prev[0, i] and out_prev[1, i]; the
    SAFETY_CLAMPED and SAFETY_LIMITED flags of what it did."""
    flags = 0
    f0, f1, f2 = forces[i, 0], forces[i, 1], forces[i, 2]
    mag = _norm3(f0, f1, f2)
    limit = params[SAFETY_PARAMS + SAFETY_LIMIT * n + i]
    if mag > limit:
        s = limit / mag
        f0, f1, f2 = f0 * s, f1 * s, f2 * s
        flags |= SAFETY_CLAMPED
    g = params[SAFETY_PARAMS + SAFETY_GATE * n + i]
    scale_i = ramp if ramp <= g else g
    if scale_i <= 0.0:
        # Exactly zero, never -0.0; the rate limit never delays a drop to zero.
        f0, f1, f2 = 0.0, 0.0, 0.0
    elif scale_i < 1.0:
        f0, f1, f2 = f0 * scale_i, f1 * scale_i, f2 * scale_i
    step = params[SAFETY_RATE]
    if step < math.inf and (f0 != 0.0 or f1 != 0.0 or f2 != 0.0):
        p0, p1, p2 = out_prev[1, i, 0], out_prev[1, i, 1], out_prev[1, i, 2]
        d0, d1, d2 = f0 - p0, f1 - p1, f2 - p2
        change = _norm3(d0, d1, d2)
        if change > step:
            k = step / change
            f0, f1, f2 = p0 + k * d0, p1 + k * d1, p2 + k * d2
            flags |= SAFETY_LIMITED
    out_prev[0, i, 0], out_prev[0, i, 1], out_prev[0, i, 2] = f0, f1, f2
    out_prev[1, i, 0], out_prev[1, i, 1], out_prev[1, i, 2] = f0, f1, f2
    return flags


def safety_step(
    forces: np.ndarray,
    positions: np.ndarray,
    buttons: np.ndarray,
    params: np.ndarray,
    out_prev: np.ndarray,
    t: float,
) -> int:
    """The safety chain's tick for F fingers at nominal time ``t`` (s): the deadman gates;
    then, with no fault latched, the finite and workspace checks (a trip zeroes the
    output), the clamp (direction kept), the smallest of the ramps and the gate, the rate
    limit, the counters. Returns the SAFETY_ outcome.

    ``forces`` (F, 3) N, ``positions`` (F, 3) m, ``buttons`` the frame's button bytes
    (4 F: each finger's little-endian uint32), ``params`` the chain's array (SAFETY_*),
    ``out_prev`` (2, F, 3) N: this tick's output, then last tick's.
    """
    n = forces.shape[0]
    _gates(buttons, params, n, t)
    outcome = _trips(forces, positions, params, n)
    if outcome != 0:  # a latched fault or a trip: zero force, and nothing to limit from
        for i in range(n):
            for j in range(3):
                out_prev[0, i, j] = 0.0
                out_prev[1, i, j] = 0.0
        return 0 if outcome < 0 else outcome
    ramp = _ramp(params, t)
    flags = 0
    for i in range(n):
        flags |= _limited(forces, params, out_prev, i, n, ramp)
    if flags & SAFETY_CLAMPED:
        params[SAFETY_CLAMPED_TICKS] += 1.0
    if flags & SAFETY_LIMITED:
        params[SAFETY_LIMITED_TICKS] += 1.0
    return flags


DECLARATION = Declaration(
    "safety",
    fields=("rendered_force", "device_force", "t"),
    flag="safety",
    helpers=("_norm3", "ramp_down_factor", "_gates", "_trips", "_ramp", "_limited", "safety_step"),
)
