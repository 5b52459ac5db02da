"""Safety between allocation and the devices: the last stage before a force leaves.

Every force passes ``SafetyChain.apply``: a non-finite value latches a fault and
zeroes every finger; a magnitude above the finger's limit (the smaller of the
device's and the profile's) is scaled down with its direction kept. A latched
fault keeps all forces at zero until ``reset``. A finger with a deadman button
gets force only while that button is held. Forces in N, shape (F, 3).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hapticd.params import PARAMS, ParamError
from hapticd.physics import kernels
from hapticd.physics.frame import Frame


@dataclass(frozen=True)
class Fault:
    """A latched fault: tick, time (s), a human-readable cause and its kind (a name of
    hapticd.events.FAULT_CAUSES, e.g. ``nonfinite_force``)."""

    tick: int
    t: float
    cause: str
    kind: str = "other"


@dataclass(frozen=True)
class Deadman:
    """A finger's deadman button: its force is exactly zero while button ``button`` (bit of
    the device's ``buttons``) is up, and ramps from zero to full over ``ramp_s`` (s,
    nominal clock) from the tick it is pressed."""

    button: int
    ramp_s: float = 0.25


@dataclass(frozen=True)
class SafetyParams:
    """Limits beyond the force clamp (defaults: off).

    ramp_s: after enabling, forces scale from 0 to 1 over this time (s, nominal clock).
    max_rate_n_per_s: largest change of a finger's force per second (N/s); a drop to
      exactly zero is never delayed.
    workspace_center_m, workspace_radius_m: a finger beyond this sphere latches a fault.
    watchdog_s: more wall time than this between two ticks latches a fault (a stalled loop).
    max_device_speed_m_per_s: a device reporting a faster speed (m/s, its own frame), or a
      non-finite position or velocity, latches a fault; checked where device state enters
      the frame (hapticd.loop.device_bank), which keeps the finger's last good state.
    deadman: per finger, its deadman button or None (empty: no finger has one).
    """

    ramp_s: float = 0.0
    max_rate_n_per_s: float = math.inf
    workspace_center_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    workspace_radius_m: float = math.inf
    watchdog_s: float = math.inf
    max_device_speed_m_per_s: float = math.inf
    deadman: tuple[Deadman | None, ...] = ()


class _Count:
    """A count the kernel keeps at item ``at`` of a chain's array, as an int."""

    def __init__(self, at: int) -> None:
        self.at = at

    def __get__(self, chain: Any, owner: type | None = None) -> Any:
        return self if chain is None else int(chain._view[self.at])

    def __set__(self, chain: Any, n: int) -> None:
        chain._view[self.at] = float(n)


class SafetyChain:
    """The last stage before a device, for F fingers, in this order: fault latch, NaN/inf
    guard, watchdog, workspace, magnitude clamp (direction kept), enable ramp, ramp-down
    and deadman gate, rate limit.

    Every stage only scales a force down or moves it between two forces within the
    limit, so the output never exceeds the limit and is never NaN. ``rated_n`` are the
    devices' own limits (N, per finger), which a new ``force_limit_n`` never exceeds;
    without them, the starting ``limits_n``.

    The tick is hapticd.physics.kernels.safety_step, compiled (``use_kernels``) or not, on
    the chain's array (its parameters, ramps, deadman state and counters): it decides
    every trip but the watchdog's and zeroes the force; the chain latches the fault with
    its message. The watchdog is the chain's: the wall clock is read after the force is
    made, before it is sent.
    """

    kernel_names = ("safety_step",)

    def __init__(
        self,
        limits_n: list[float],
        params: SafetyParams | None = None,
        dt: float = 1e-3,
        *,
        rated_n: list[float] | None = None,
    ) -> None:
        if not limits_n or any(not (math.isfinite(v) and v > 0) for v in limits_n):
            raise ValueError(f"force limits must be positive and finite, got {limits_n}")
        F = len(limits_n)
        prm = params or SafetyParams()
        if prm.deadman and len(prm.deadman) != F:
            raise ValueError(f"one deadman entry (or None) per finger is needed, got {F} fingers")
        deadman = prm.deadman or (None,) * F
        for d in deadman:
            if d is not None and not (
                0 <= d.button < 32 and d.ramp_s >= 0 and math.isfinite(d.ramp_s)
            ):
                got = (d.button, d.ramp_s)
                raise ValueError(f"a deadman needs a button in 0-31 and a ramp >= 0 s, got {got}")
        # safety_step's array (hapticd.physics.kernels.SAFETY_*): parameters and state.
        self._array = a = np.zeros(kernels.SAFETY_PARAMS + kernels.SAFETY_COLUMNS * F)

        def column(k: int) -> np.ndarray:  # the per-finger block k (F,)
            return a[kernels.SAFETY_PARAMS + k * F : kernels.SAFETY_PARAMS + (k + 1) * F]

        self._limits_a, self._buttons_a = (
            column(kernels.SAFETY_LIMIT),
            column(kernels.SAFETY_BUTTON),
        )
        self._ramps_a, self._pressed_a = (
            column(kernels.SAFETY_BUTTON_RAMP),
            column(kernels.SAFETY_PRESSED),
        )
        self._gate_a = column(kernels.SAFETY_GATE)
        # Its items stored and read through a memoryview: a float stored through one is
        # that float, for a fraction of a numpy item assignment.
        self._view = memoryview(a)
        self.dt = float(dt)
        self._params = prm
        self._watchdog_s = prm.watchdog_s
        a[kernels.SAFETY_RATE] = prm.max_rate_n_per_s * self.dt
        a[kernels.SAFETY_RADIUS] = prm.workspace_radius_m
        a[kernels.SAFETY_CENTRE : kernels.SAFETY_CENTRE + 3] = prm.workspace_center_m
        a[kernels.SAFETY_RAMP_S] = prm.ramp_s
        self._buttons_a[:] = [-1.0 if d is None else d.button for d in deadman]
        self._ramps_a[:] = [0.0 if d is None else d.ramp_s for d in deadman]
        self._pressed_a[:] = math.inf
        self._gate_a[:] = [1.0 if d is None else 0.0 for d in deadman]
        self._has_deadman = any(d is not None for d in deadman)
        self.limits = [float(v) for v in limits_n]
        self.rated = [float(v) for v in (rated_n if rated_n is not None else limits_n)]
        if len(self.rated) != F:
            raise ValueError(f"one rated force per finger is needed, got {rated_n}")
        # safety_step, compiled or not (use_kernels), and its other preallocated inputs:
        # the buttons (as the frame holds them) and positions at the workspace's centre
        # (``apply`` without positions: no workspace check).
        self._step: Callable[..., int] = kernels.uncompiled("safety_step")
        self._buttons = np.zeros(F, dtype="<u4")
        self._button_bytes = self._buttons.view(np.uint8)
        self._centre = np.tile(np.asarray(prm.workspace_center_m, dtype=float), (F, 1))
        self.fault = None
        # This tick's output and the last one's, in one array for the kernel.
        self._out_prev = np.zeros((2, F, 3))
        self.output = self._out_prev[0]
        self._prev = self._out_prev[1]
        self._last_wall: float | None = None
        self.start(0.0)

    @property
    def params(self) -> SafetyParams:
        """The chain's parameters (fixed for its life: a new profile builds a new chain)."""
        return self._params

    @property
    def fault(self) -> Fault | None:
        """The latched fault (None: forces may flow); the kernel holds the forces at zero
        while one is."""
        return self._fault

    @fault.setter
    def fault(self, fault: Fault | None) -> None:
        self._fault = fault
        self._view[kernels.SAFETY_LATCHED] = 0.0 if fault is None else 1.0

    @property
    def latched(self) -> bool:
        return self._fault is not None

    @property
    def limits(self) -> list[float]:
        """Per-finger force limits, N (a copy: ``set_limits`` changes them, so that the
        kernel's copy follows)."""
        return self._limits_a.tolist()

    @limits.setter
    def limits(self, limits_n: list[float]) -> None:
        self._limits_a[:] = [float(v) for v in limits_n]

    # The ticks on which a force was clamped to its limit, and on which a force's change
    # was rate limited: counted by the kernel (a reload carries them over).
    clamped_ticks = _Count(kernels.SAFETY_CLAMPED_TICKS)
    rate_limited_ticks = _Count(kernels.SAFETY_LIMITED_TICKS)

    @property
    def gate(self) -> list[float]:
        """Each finger's deadman gate on the last tick, 0 to 1 (1 without a deadman)."""
        return self._gate_a.tolist()

    def use_kernels(self, compiled: dict[str, Callable[..., int]]) -> None:
        """Run ``compiled["safety_step"]`` (compiled by hapticd.physics.jit) from the next tick on;
        without it (an empty dict), the same function uncompiled."""
        self._step = compiled.get("safety_step") or kernels.uncompiled("safety_step")

    def start(self, t: float) -> None:
        """Forces were (re-)enabled at nominal time ``t`` (s): begin the ramp."""
        v = self._view
        v[kernels.SAFETY_T_ENABLED] = float(t)
        v[kernels.SAFETY_T_DOWN] = math.inf
        v[kernels.SAFETY_DOWN_S] = 0.0
        self._prev[:] = 0.0
        self._last_wall = None

    def set_limits(self, limits_n: list[float]) -> None:
        """New per-finger force limits, N (positive, finite); the next tick obeys them."""
        if len(limits_n) != len(self._limits_a) or any(
            not (math.isfinite(v) and v > 0) for v in limits_n
        ):
            raise ValueError(f"force limits must be {len(self._limits_a)} positive numbers")
        self.limits = [float(v) for v in limits_n]

    def param(self, name: str) -> Any:
        """The current value of a safety parameter (hapticd.params, owner ``safety``)."""
        return _GETTERS[_own(name)](self)

    def set_param(self, name: str, value: Any) -> None:
        """Change a safety parameter (already checked against its spec) from the next tick."""
        _SETTERS[_own(name)](self, value)

    def ramp_down(self, t: float, duration_s: float) -> None:
        """Scale forces by a factor falling from 1 at ``t`` (s) to exactly 0 after
        ``duration_s`` (hapticd.physics.kernels.ramp_down_factor)."""
        self._view[kernels.SAFETY_T_DOWN] = float(t)
        self._view[kernels.SAFETY_DOWN_S] = max(float(duration_s), 0.0)

    def ramped_down(self, t: float) -> bool:
        """True once a ramp-down begun before ``t`` has reached zero."""
        v = self._view
        return (
            kernels.ramp_down_factor(t, v[kernels.SAFETY_T_DOWN], v[kernels.SAFETY_DOWN_S]) == 0.0
        )

    def trip(self, tick: int, t: float, cause: str, kind: str = "other") -> None:
        """Latch a fault (the first cause is kept) and zero the output; ``kind`` names the
        cause's kind (hapticd.events.FAULT_CAUSES)."""
        if self._fault is None:
            self.fault = Fault(tick, t, cause, kind)
        self._out_prev[:] = 0.0

    def reset(self, t: float = 0.0) -> None:
        """Clear a latched fault; forces ramp up again from ``t``."""
        self.fault = None
        self.output[:] = 0.0
        self.start(t)

    def run(self, frame: Frame, t_wall: float) -> None:
        """The safety stage: ``device_force`` from the frame's ``rendered_force``, checked
        against its tick, nominal time, device positions and buttons; ``t_wall``
        (monotonic s) feeds the watchdog."""
        out = self.apply(
            frame.rendered_force,
            int(frame.tick),
            float(frame.t),
            frame.device_pos,
            t_wall,
            frame.buttons,
        )
        frame.device_force[...] = out

    def ready(self) -> bool:
        """Whether the renderer's one call may make this tick (with ``kernel_arrays``, the
        frame's nominal time and buttons; then ``done``): no fault latched."""
        return self._fault is None

    @property
    def kernel_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """safety_step's ``params`` (the chain's array) and ``out_prev`` (this tick's output
        and the last)."""
        return self._array, self._out_prev

    def done(self, outcome: int, tick: int, t: float, t_wall: float | None) -> bool:
        """After ``safety_step`` made tick ``tick`` (nominal time ``t``, s) with outcome
        ``outcome``: the watchdog at monotonic time ``t_wall`` (s; None: none), and any
        trip latched with its message. False when a fault latched (the caller then sends
        zero force: ``run``)."""
        last = self._last_wall
        if t_wall is not None:
            self._last_wall = t_wall
            if last is not None and not t_wall - last <= self._watchdog_s:
                self._latch(outcome, tick, t, t_wall - last)
                return False
        if outcome < _TRIPPED:  # most ticks
            return True
        self._latch(outcome, tick, t, None)
        return False

    def _latch(self, outcome: int, tick: int, t: float, gap: float | None) -> None:
        """Latch the faults of a tick, in the chain's order (the first is kept): a non-finite
        force, the watchdog (``gap``: s between ticks, None: no stall), the workspace."""
        if outcome & kernels.SAFETY_NON_FINITE:
            bad = [
                i for i in range(len(self.output)) if outcome >> (kernels.SAFETY_FINGERS + i) & 1
            ]
            self.trip(tick, t, f"non-finite force for finger(s) {bad}", "nonfinite_force")
        if gap is not None:
            limit = self._watchdog_s
            self.trip(
                tick,
                t,
                f"watchdog: {gap * 1e3:.1f} ms between ticks (limit {limit * 1e3:g} ms)",
                "watchdog",
            )
        if outcome & kernels.SAFETY_WORKSPACE:
            i, r = outcome >> kernels.SAFETY_FINGERS, self._view[kernels.SAFETY_DISTANCE]
            self.trip(
                tick,
                t,
                f"finger {i} left the workspace: {r:.4f} m from its centre "
                f"(limit {self._params.workspace_radius_m:g} m)",
                "workspace",
            )

    def deadman_status(self) -> list[dict[str, Any] | None]:
        """Per finger: its deadman button, whether it is held and the gate's factor (0 to 1)
        on the last tick; None for a finger without one."""
        return [
            None if b < 0 else {"button": int(b), "held": p < math.inf, "gate": g}
            for b, p, g in zip(
                self._buttons_a.tolist(),
                self._pressed_a.tolist(),
                self._gate_a.tolist(),
                strict=True,
            )
        ]

    def apply(
        self,
        forces: np.ndarray,
        tick: int,
        t: float,
        positions: np.ndarray | None = None,
        t_wall: float | None = None,
        buttons: np.ndarray | None = None,
    ) -> np.ndarray:
        """Safe forces (F, 3) N for ``forces`` (F, 3) N; returns an internal buffer.

        ``positions`` (F, 3) m feed the workspace check (None: none), ``t_wall`` (s,
        monotonic) the watchdog, ``buttons`` (F,) bit sets the deadman gates (None: every
        button up); ``t`` is the nominal tick time for the ramps. Arrays in another form
        than the kernel's (a list, another dtype, a strided view) are copied.
        """
        forces = np.ascontiguousarray(forces, dtype=float)
        positions = (
            self._centre if positions is None else np.ascontiguousarray(positions, dtype=float)
        )
        for a in (forces, positions):
            if a.shape != self.output.shape:
                raise ValueError(
                    f"forces and positions must be {self.output.shape} arrays, not {a.shape}"
                )
        if self._has_deadman:
            self._buttons[:] = 0 if buttons is None else buttons
        outcome = self._step(
            forces, positions, self._button_bytes, self._array, self._out_prev, float(t)
        )
        if self._fault is None:
            self.done(outcome, tick, t, t_wall)
        return self.output


# safety_step's outcomes from this one on are trips (below it: flags of a tick made safe).
_TRIPPED = kernels.SAFETY_NON_FINITE


def _own(name: str) -> str:
    spec = PARAMS.get(name)
    if spec is None or spec.owner != "safety":
        known = list(_SETTERS)
        raise ParamError(
            "unknown_param", f"unknown parameter {name!r} for the safety chain; known: {known}"
        )
    return name


_SETTERS: dict[str, Callable[[SafetyChain, Any], None]] = {
    "force_limit_n": lambda s, v: s.set_limits([min(r, float(v)) for r in s.rated]),
}

_GETTERS: dict[str, Callable[[SafetyChain], Any]] = {
    "force_limit_n": lambda s: list(s.limits),
}
