"""The safety chain: the last stage before a force (F, 3) N leaves for the devices.

Its checks, their order and its faults: docs/daemon.md ("The safety chain's tick"), the
``safety.*`` keys of docs/profiles.md and the fault causes of docs/control.md.
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
from hapticd.physics.live import Change


@dataclass(frozen=True)
class Fault:
    """A latched fault: tick, time (s), the message and its kind (a name of
    hapticd.events.FAULT_CAUSES)."""

    tick: int
    t: float
    cause: str
    kind: str = "other"


@dataclass(frozen=True)
class Deadman:
    """A finger's deadman: ``button`` (0-31, a bit of the device's ``buttons``) and the ramp
    from zero to full force after a press, ``ramp_s`` (s, nominal clock)."""

    button: int
    ramp_s: float = 0.25


@dataclass(frozen=True)
class SafetyParams:
    """Limits beyond the force clamp (defaults: off), as the ``safety.*`` keys of
    docs/profiles.md: ramp_s (s), max_rate_n_per_s (N/s), workspace_center_m (m),
    workspace_radius_m (m), watchdog_s (s), max_device_speed_m_per_s (m/s; checked by
    hapticd.loop.device_bank, not the chain); deadman: per finger a Deadman or None (empty:
    none)."""

    ramp_s: float = 0.0
    max_rate_n_per_s: float = math.inf
    workspace_center_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    workspace_radius_m: float = math.inf
    watchdog_s: float = math.inf
    max_device_speed_m_per_s: float = math.inf
    deadman: tuple[Deadman | None, ...] = ()


class _Count:
    """A count the kernel keeps at item ``at`` of the chain's array, as an int."""

    def __init__(self, at: int) -> None:
        self.at = at

    def __get__(self, chain: Any, owner: type | None = None) -> Any:
        return self if chain is None else int(chain._view[self.at])

    def __set__(self, chain: Any, n: int) -> None:
        chain._view[self.at] = float(n)


class SafetyChain:
    """The safety chain of F fingers: ``limits_n`` (F,) N, ``rated_n`` (F,) N the devices'
    own limits, which ``force_limit_n`` never exceeds (default: ``limits_n``), ``max_n``
    (N) the profile's limit, above which ``force_limit_n`` is refused, ``dt`` (s).
    ValueError for limits that are not positive and finite, or a deadman or rated force
    list of another length.

    Every check only scales a force down or moves it between two forces within the limit,
    so the output never exceeds the limit and is never NaN. The kernel (``safety_step``)
    decides every trip but the watchdog's; the chain words and latches them, and runs the
    watchdog, whose wall clock is read after the force is made, before it is sent.
    """

    kernel_names = ("safety_step",)

    def __init__(
        self,
        limits_n: list[float],
        params: SafetyParams | None = None,
        dt: float = 1e-3,
        *,
        rated_n: list[float] | None = None,
        max_n: float = math.inf,
    ) -> None:
        if not limits_n or not _positive(limits_n):
            raise ValueError(f"force limits must be positive and finite, got {limits_n}")
        F = len(limits_n)
        prm = params or SafetyParams()
        if prm.deadman and len(prm.deadman) != F:
            raise ValueError(f"one deadman entry (or None) per finger is needed, got {F} fingers")
        deadman = prm.deadman or (None,) * F
        for d in filter(None, deadman):
            if not (0 <= d.button < 32 and d.ramp_s >= 0 and math.isfinite(d.ramp_s)):
                got = (d.button, d.ramp_s)
                raise ValueError(f"a deadman needs a button in 0-31 and a ramp >= 0 s, got {got}")
        # safety_step's array (kernels.SAFETY_*): parameters and state, then per-finger columns.
        self._array = a = np.zeros(kernels.SAFETY_PARAMS + kernels.SAFETY_COLUMNS * F)
        columns = a[kernels.SAFETY_PARAMS :].reshape(kernels.SAFETY_COLUMNS, F)
        self._limits_a = columns[kernels.SAFETY_LIMIT]
        self._buttons_a = columns[kernels.SAFETY_BUTTON]
        self._pressed_a = columns[kernels.SAFETY_PRESSED]
        self._gate_a = columns[kernels.SAFETY_GATE]
        # Scalars go through a memoryview: a fraction of a numpy item assignment's cost.
        self._view = memoryview(a)
        self.dt = float(dt)
        self._params = prm
        self._watchdog_s = prm.watchdog_s
        a[kernels.SAFETY_RATE] = prm.max_rate_n_per_s * self.dt
        a[kernels.SAFETY_RADIUS] = prm.workspace_radius_m
        a[kernels.SAFETY_CENTRE : kernels.SAFETY_CENTRE + 3] = prm.workspace_center_m
        a[kernels.SAFETY_RAMP_S] = prm.ramp_s
        self._buttons_a[:] = [-1.0 if d is None else d.button for d in deadman]
        columns[kernels.SAFETY_BUTTON_RAMP] = [0.0 if d is None else d.ramp_s for d in deadman]
        self._pressed_a[:] = math.inf
        self._gate_a[:] = [1.0 if d is None else 0.0 for d in deadman]
        self._has_deadman = any(d is not None for d in deadman)
        self.limits = limits_n
        self.rated = [float(v) for v in (rated_n if rated_n is not None else limits_n)]
        self.max_n = float(max_n)
        if len(self.rated) != F:
            raise ValueError(f"one rated force per finger is needed, got {rated_n}")
        # safety_step's other inputs, preallocated: the buttons as the frame holds them, and
        # positions at the workspace's centre for ``apply`` without positions (no check).
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
        """The chain's parameters (fixed: a new profile builds a new chain)."""
        return self._params

    @property
    def fault(self) -> Fault | None:
        """The latched fault (None: forces may flow)."""
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
        """Per-finger force limits (F,) N, a copy (``set_limits`` changes them)."""
        return self._limits_a.tolist()

    @limits.setter
    def limits(self, limits_n: list[float]) -> None:
        self._limits_a[:] = [float(v) for v in limits_n]

    # Ticks on which a force was clamped, and on which one was rate limited (settable: a
    # reload carries them over).
    clamped_ticks = _Count(kernels.SAFETY_CLAMPED_TICKS)
    rate_limited_ticks = _Count(kernels.SAFETY_LIMITED_TICKS)

    @property
    def gate(self) -> list[float]:
        """Each finger's deadman gate on the last tick, 0 to 1 (1 without a deadman)."""
        return self._gate_a.tolist()

    def use_kernels(self, compiled: dict[str, Callable[..., int]]) -> None:
        """Run ``compiled["safety_step"]`` from the next tick on; without it, the same
        function uncompiled."""
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
        if len(limits_n) != len(self._limits_a) or not _positive(limits_n):
            raise ValueError(f"force limits must be {len(self._limits_a)} positive numbers")
        self.limits = limits_n

    def param(self, name: str) -> Any:
        """The current value of a safety parameter (hapticd.params, owner ``safety``)."""
        return _GETTERS[_own(name)](self)

    def set_param(self, name: str, value: Any) -> None:
        """Change a safety parameter (checked against its spec already) from the next tick:
        ``prepare_set`` and apply it."""
        self.prepare_set(name, value).apply()

    def prepare_set(self, name: str, value: Any) -> Change:
        """Check a new value of a safety parameter and prepare its change (in the caller's
        thread): item stores into the chain's array, which the servo thread makes.
        ValueError, nothing changed, for a value the chain refuses."""
        return _SETTERS[_own(name)](self, value)

    def ramp_down(self, t: float, duration_s: float) -> None:
        """Scale forces by a factor falling from 1 at ``t`` (s) to exactly 0 after
        ``duration_s`` (s)."""
        self._view[kernels.SAFETY_T_DOWN] = float(t)
        self._view[kernels.SAFETY_DOWN_S] = max(float(duration_s), 0.0)

    def ramped_down(self, t: float) -> bool:
        """True once a ramp-down begun before ``t`` has reached zero."""
        v = self._view
        down = kernels.ramp_down_factor(t, v[kernels.SAFETY_T_DOWN], v[kernels.SAFETY_DOWN_S])
        return down == 0.0

    def trip(self, tick: int, t: float, cause: str, kind: str = "other") -> None:
        """Latch a fault (the first is kept) and zero the output; ``kind``: a name of
        hapticd.events.FAULT_CAUSES."""
        if self._fault is None:
            self.fault = Fault(tick, t, cause, kind)
        self._out_prev[:] = 0.0

    def reset(self, t: float = 0.0) -> None:
        """Clear a latched fault; forces ramp up again from ``t``."""
        self.fault = None
        self.output[:] = 0.0
        self.start(t)

    def run(self, frame: Frame, t_wall: float) -> None:
        """The frame's ``device_force`` from its ``rendered_force`` (``apply``); ``t_wall``
        (monotonic s) feeds the watchdog."""
        frame.device_force[...] = self.apply(
            frame.rendered_force,
            int(frame.tick),
            float(frame.t),
            frame.device_pos,
            t_wall,
            frame.buttons,
        )

    def ready(self) -> bool:
        """Whether the renderer's one call may make this tick (then ``done``): no fault
        latched."""
        return self._fault is None

    @property
    def kernel_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """safety_step's ``params`` (the chain's array) and ``out_prev`` (this tick's output
        and the last)."""
        return self._array, self._out_prev

    def done(self, outcome: int, tick: int, t: float, t_wall: float | None) -> bool:
        """After ``safety_step`` made tick ``tick`` (nominal ``t``, s) with ``outcome``: the
        watchdog at ``t_wall`` (monotonic s; None: none), and any trip latched. False when a
        fault latched (the caller then sends zero force: ``run``)."""
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
        """Latch a tick's faults in the chain's order (the first is kept): a non-finite force,
        the watchdog (``gap``: s between ticks, None: no stall), the workspace."""
        fingers = outcome >> kernels.SAFETY_FINGERS
        if outcome & kernels.SAFETY_NON_FINITE:
            bad = [i for i in range(len(self.output)) if fingers >> i & 1]
            self.trip(tick, t, f"non-finite force for finger(s) {bad}", "nonfinite_force")
        if gap is not None:
            limit_ms = self._watchdog_s * 1e3
            cause = f"watchdog: {gap * 1e3:.1f} ms between ticks (limit {limit_ms:g} ms)"
            self.trip(tick, t, cause, "watchdog")
        if outcome & kernels.SAFETY_WORKSPACE:
            r, limit = self._view[kernels.SAFETY_DISTANCE], self._params.workspace_radius_m
            cause = f"finger {fingers} left the workspace: {r:.4f} m from its centre "
            cause += f"(limit {limit:g} m)"
            self.trip(tick, t, cause, "workspace")

    def deadman_status(self) -> list[dict[str, Any] | None]:
        """Per finger: its deadman button, whether it is held and the gate (0 to 1) on the
        last tick; None for a finger without one."""
        buttons, pressed = self._buttons_a.tolist(), self._pressed_a.tolist()
        return [
            None if b < 0 else {"button": int(b), "held": p < math.inf, "gate": g}
            for b, p, g in zip(buttons, pressed, self.gate, strict=True)
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
        """Safe forces (F, 3) N for ``forces`` (F, 3) N, in an internal buffer; ValueError for
        another shape. ``t``: nominal time (s); ``positions`` (F, 3) m: the workspace check
        (None: none); ``t_wall`` (monotonic s): the watchdog; ``buttons`` (F,) bit sets: the
        deadman gates (None: all up). Arrays not in the kernel's form are copied.
        """
        shape = self.output.shape
        forces = np.ascontiguousarray(forces, dtype=float)
        positions = (
            self._centre if positions is None else np.ascontiguousarray(positions, dtype=float)
        )
        for a in (forces, positions):
            if a.shape != shape:
                raise ValueError(f"forces and positions must be {shape} arrays, not {a.shape}")
        if self._has_deadman:
            self._buttons[:] = 0 if buttons is None else buttons
        outcome = self._step(
            forces, positions, self._button_bytes, self._array, self._out_prev, float(t)
        )
        if self._fault is None:
            self.done(outcome, tick, t, t_wall)
        return self.output


# safety_step's outcomes from this one on are trips (below: flags of a tick made safe).
_TRIPPED = kernels.SAFETY_NON_FINITE


def _positive(values: list[float]) -> bool:
    return all(math.isfinite(v) and v > 0 for v in values)


def _own(name: str) -> str:
    spec = PARAMS.get(name)
    if spec is None or spec.owner != "safety":
        why = f"unknown parameter {name!r} for the safety chain; known: {list(_SETTERS)}"
        raise ParamError("unknown_param", why)
    return name


def _set_force_limit(s: SafetyChain, value: Any) -> Change:
    v = float(value)
    if not (v > 0.0 and math.isfinite(v)):
        raise ValueError(f"force_limit_n must be positive and finite, got {v:g}")
    if v > s.max_n:  # a live change may lower the profile's limit, never raise it past it
        raise ValueError(
            f"force_limit_n {v:g} N is above the profile's safety.max_force_n {s.max_n:g} N: "
            "refused (raise safety.max_force_n in the profile and reload)"
        )
    # Each finger's limit: its slot in the chain's array (the limits' row, finger by finger).
    at = kernels.SAFETY_PARAMS + kernels.SAFETY_LIMIT * len(s.rated)
    change = Change("force_limit_n", value, guards=[(s, "_view", s._view)])
    change.stores += [(s._view, at + i, min(r, v)) for i, r in enumerate(s.rated)]
    return change


# How the chain changes and reads each parameter it owns (hapticd.params, owner "safety").
_SETTERS: dict[str, Callable[[SafetyChain, Any], Change]] = {
    "force_limit_n": _set_force_limit,
}

_GETTERS: dict[str, Callable[[SafetyChain], Any]] = {
    "force_limit_n": lambda s: s.limits,
}
