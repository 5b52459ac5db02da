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
from hapticd.physics.kernels import SAFETY_CLAMPED, SAFETY_DEFER, SAFETY_LIMITED, SAFETY_PARAMS


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


class SafetyChain:
    """The last stage before a device, for F fingers, in this order: fault latch, NaN/inf
    guard, watchdog, workspace, magnitude clamp (direction kept), enable ramp and deadman
    gate, rate limit.

    Every stage only scales a force down or moves it between two forces within the
    limit, so the output never exceeds the limit and is never NaN. ``rated_n`` are the
    devices' own limits (N, per finger), which a new ``force_limit_n`` never exceeds;
    without them, the starting ``limits_n``.

    The clamp, ramp, gate and rate limit are hapticd.physics.kernels.safety_step, compiled
    (``use_kernels``) or not; whatever may trip (a non-finite force, the watchdog, a
    finger at the workspace's edge) is checked by the code below, with its messages,
    before that step runs.
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
        # The kernel's inputs in one array (each argument of a compiled call costs a type
        # check): SAFETY_PARAMS parameters, then the F limits, then the F gates.
        self._step_params = np.zeros(SAFETY_PARAMS + 2 * F)
        self._limits_a = self._step_params[SAFETY_PARAMS : SAFETY_PARAMS + F]
        # Its per-tick items stored through a memoryview: a float stored through one is
        # that float, for a fraction of a numpy item assignment.
        self._step_view = memoryview(self._step_params)
        self.limits = [float(v) for v in limits_n]
        self.rated = [float(v) for v in (rated_n if rated_n is not None else limits_n)]
        if len(self.rated) != len(self.limits):
            raise ValueError(f"one rated force per finger is needed, got {rated_n}")
        self.params = params or SafetyParams()
        F = len(self.limits)
        if self.params.deadman and len(self.params.deadman) != F:
            raise ValueError(f"one deadman entry (or None) per finger is needed, got {F} fingers")
        self._deadman = [
            (d.button, d.ramp_s) if d is not None else None
            for d in (self.params.deadman or (None,) * F)
        ]
        for dm in self._deadman:
            if dm is not None and not (0 <= dm[0] < 32 and dm[1] >= 0 and math.isfinite(dm[1])):
                raise ValueError(f"a deadman needs a button in 0-31 and a ramp >= 0 s, got {dm}")
        self._has_deadman = any(d is not None for d in self._deadman)
        # Per finger: nominal time its deadman button went down (inf: up) and the factor
        # the gate applied on the last tick (1 without a deadman).
        self._held_since = [math.inf] * F
        self.gate = [0.0 if d is not None else 1.0 for d in self._deadman]
        self.dt = float(dt)
        # safety_step, compiled or not (use_kernels), and its preallocated inputs.
        self._step: Callable[..., int] = kernels.uncompiled("safety_step")
        # The params (and whether with the workspace check) _step_params holds; ``dt`` is
        # fixed for the chain's life.
        self._inputs_for: SafetyParams | None = None
        self._inputs_workspace = False
        self._gate_a = self._step_params[SAFETY_PARAMS + F :]
        self._gate_a[:] = self.gate
        self.fault: Fault | None = None
        self.clamped_ticks = 0
        self.rate_limited_ticks = 0
        # Ticks the kernel deferred to the chain's own checks (something might trip: a
        # non-finite force, the watchdog, the workspace's edge); ordinary ticks never are.
        self.checked_ticks = 0
        # This tick's output and the last one's, in one array for the compiled path.
        self._out_prev = np.zeros((2, F, 3))
        self.output = self._out_prev[0]
        self._prev = self._out_prev[1]
        self._t_enabled = 0.0
        self._t_down = math.inf
        self._down_s = 0.0
        self._last_wall: float | None = None

    @property
    def latched(self) -> bool:
        return self.fault is not None

    @property
    def limits(self) -> list[float]:
        """Per-finger force limits, N (a copy: ``set_limits`` changes them, so that the
        kernel's copy follows)."""
        return list(self._limits)

    @limits.setter
    def limits(self, limits_n: list[float]) -> None:
        self._limits = [float(v) for v in limits_n]
        self._limits_a[:] = self._limits  # the kernel's copy

    def use_kernels(self, compiled: dict[str, Callable[..., int]]) -> None:
        """Run ``compiled["safety_step"]`` (compiled by hapticd.physics.jit) from the next tick on;
        without it (an empty dict), the same function uncompiled."""
        self._step = compiled.get("safety_step") or kernels.uncompiled("safety_step")

    def start(self, t: float) -> None:
        """Forces were (re-)enabled at nominal time ``t`` (s): begin the ramp."""
        self._t_enabled = float(t)
        self._t_down = math.inf
        self._prev[:] = 0.0
        self._last_wall = None

    def set_limits(self, limits_n: list[float]) -> None:
        """New per-finger force limits, N (positive, finite); the next tick obeys them."""
        if len(limits_n) != len(self.limits) or any(
            not (math.isfinite(v) and v > 0) for v in limits_n
        ):
            raise ValueError(f"force limits must be {len(self.limits)} positive numbers")
        self.limits = [float(v) for v in limits_n]

    def param(self, name: str) -> Any:
        """The current value of a safety parameter (hapticd.params, owner ``safety``)."""
        return _GETTERS[_own(name)](self)

    def set_param(self, name: str, value: Any) -> None:
        """Change a safety parameter (already checked against its spec) from the next tick."""
        _SETTERS[_own(name)](self, value)

    def ramp_down(self, t: float, duration_s: float) -> None:
        """Scale forces by a factor falling from 1 at ``t`` (s) to 0 after ``duration_s``."""
        self._t_down = float(t)
        self._down_s = max(float(duration_s), 0.0)

    def _down_factor(self, t: float) -> float:
        """The ramp-down's scale at ``t``: 1 before it, falling to exactly 0 at its end
        (tick times carry rounding: a remainder of 1e-15 must not leave a force of 1e-15 N)."""
        if t < self._t_down:
            return 1.0
        left = 1.0 - (t - self._t_down) / self._down_s if self._down_s > 0 else 0.0
        return left if left > 1e-9 else 0.0

    def ramped_down(self, t: float) -> bool:
        """True once a ramp-down begun before ``t`` has reached zero."""
        return self._down_factor(t) == 0.0

    def trip(self, tick: int, t: float, cause: str, kind: str = "other") -> None:
        """Latch a fault (the first cause is kept) and zero the output; ``kind`` names the
        cause's kind (hapticd.events.FAULT_CAUSES)."""
        if self.fault is None:
            self.fault = Fault(tick, t, cause, kind)
        self.output[:] = 0.0
        self._prev[:] = 0.0

    def reset(self, t: float = 0.0) -> None:
        """Clear a latched fault; forces ramp up again from ``t``."""
        self.fault = None
        self.output[:] = 0.0
        self.start(t)

    def run(self, frame: Frame, t_wall: float) -> None:
        """The safety stage: ``device_force`` from the frame's ``rendered_force``, checked
        against its tick, nominal time and device positions; ``t_wall`` (monotonic s)
        feeds the watchdog."""
        buttons = frame.buttons if self._has_deadman else None
        out = self.apply(
            frame.rendered_force, int(frame.tick), float(frame.t), frame.device_pos, t_wall, buttons
        )
        frame.device_force[...] = out

    def ready(self, t: float) -> bool:
        """Whether this tick (nominal time ``t``, s) may be the normal one, made by
        ``safety_step`` outside the chain (the renderer's one call, with ``kernel_arrays``;
        then ``done``): no deadman, no latched fault. Sets the kernel's parameters for ``t``
        when it may."""
        if self._has_deadman or self.fault is not None:
            return False
        self._step_inputs(t, True)
        return True

    @property
    def kernel_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """safety_step's ``params`` and ``out_prev`` (this tick's output and the last)."""
        return self._step_params, self._out_prev

    def done(self, flags: int, t_wall: float | None) -> bool:
        """After ``safety_step`` made this tick's output with the parameters ``ready`` set,
        at monotonic time ``t_wall`` (s; None: no watchdog): its ``flags`` counted; False
        when the watchdog must trip (the caller then runs the chain: ``run``)."""
        if t_wall is not None:
            if self._stalled(t_wall):
                return False
            self._last_wall = t_wall
        if flags:  # most ticks neither clamp nor limit
            self.clamped_ticks += (flags & SAFETY_CLAMPED) != 0
            self.rate_limited_ticks += (flags & SAFETY_LIMITED) != 0
        return True

    def deadman_status(self) -> list[dict[str, Any] | None]:
        """Per finger: its deadman button, whether it is held and the gate's factor (0 to 1)
        on the last tick; None for a finger without one."""
        return [
            None
            if d is None
            else {"button": d[0], "held": self._held_since[i] < math.inf, "gate": self.gate[i]}
            for i, d in enumerate(self._deadman)
        ]

    def _update_deadman(self, buttons: Any, t: float) -> None:
        """Each deadman finger's gate at nominal time ``t`` (s) from its device's ``buttons``
        (F,) bit sets (None: every button up): 0 while its button is up, then (t - press)
        / ramp_s up to 1."""
        bits = [0] * len(self._deadman) if buttons is None else np.asarray(buttons).tolist()
        for i, d in enumerate(self._deadman):
            if d is None:
                continue
            button, ramp_s = d
            if not (int(bits[i]) >> button) & 1:
                self._held_since[i] = math.inf
                self.gate[i] = 0.0
                continue
            if self._held_since[i] == math.inf:
                self._held_since[i] = t
            held = t - self._held_since[i]
            self.gate[i] = 1.0 if ramp_s <= 0.0 or held >= ramp_s else held / ramp_s

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

        ``positions`` (F, 3) m feed the workspace check, ``t_wall`` (s, monotonic)
        the watchdog, ``buttons`` (F,) bit sets the deadman gates (None: every button up);
        ``t`` is the nominal tick time for the ramps.
        """
        out = self.output
        if self._has_deadman:
            # Before the fault latch: the gate follows the button also while forces are off.
            self._update_deadman(buttons, t)
        if self.fault is not None:
            out[:] = 0.0
            return out
        if self._normal(forces, t, positions, t_wall):
            return out
        self.checked_ticks += 1
        return self._apply(forces, tick, t, positions, t_wall)

    def _ramp(self, t: float) -> float:
        """The factor of the enable ramp and the ramp-down at nominal time ``t`` (s), 0 to 1."""
        prm = self.params
        ramp = 1.0
        if prm.ramp_s > 0.0:
            ramp = min(1.0, max(0.0, (t - self._t_enabled) / prm.ramp_s))
        if t >= self._t_down:
            ramp = min(ramp, self._down_factor(t))
        return ramp

    def _normal(self, forces: Any, t: float, positions: Any, t_wall: float | None) -> bool:
        """The normal tick by ``safety_step``; False (nothing changed) when ``_apply`` must
        run this tick: something may trip."""
        if t_wall is not None and self._stalled(t_wall):
            return False
        flags = self._step_now(forces, t, positions)
        return not flags & SAFETY_DEFER and self.done(flags, t_wall)

    def _stalled(self, t_wall: float) -> bool:
        """Whether more wall time than the watchdog's limit passed since the last tick."""
        last = self._last_wall
        return last is not None and t_wall - last > self.params.watchdog_s

    def _step_now(self, forces: Any, t: float, positions: Any) -> int:
        """``safety_step``'s flags on this tick's ``forces`` (F, 3) N (and ``positions`` (F, 3)
        m, None: no workspace check): SAFETY_DEFER, nothing written, when something may
        trip. Either given in another form than the kernel's (a list, another dtype, a
        strided view) is copied."""
        p = self._step_inputs(t, positions is not None)
        if positions is None or not math.isfinite(p[2]):
            positions = self.output  # never read
        forces = np.ascontiguousarray(forces, dtype=float)
        positions = np.ascontiguousarray(positions, dtype=float)
        for a in (forces, positions):
            if a.shape != self.output.shape:
                raise ValueError(
                    f"forces and positions must be {self.output.shape} arrays, not {a.shape}"
                )
        if self._has_deadman:
            self._gate_a[:] = self.gate
        return self._step(forces, positions, p, self._out_prev)

    def _step_inputs(self, t: float, workspace: bool) -> np.ndarray:
        """safety_step's parameters for nominal time ``t`` (s), with the workspace check
        (when the params have a finite radius) or without."""
        prm = self.params
        v = self._step_view
        if prm is not self._inputs_for or workspace is not self._inputs_workspace:
            # The parameters' part, stored again only when they (or the check) change.
            self._inputs_for, self._inputs_workspace = prm, workspace
            self._step_params[3:6] = prm.workspace_center_m
            v[2] = prm.workspace_radius_m if workspace else math.inf  # inf: no check
            v[1] = prm.max_rate_n_per_s * self.dt
        # Past the enable ramp and before any ramp-down the factor is exactly 1 (the
        # division in ``_ramp`` cannot fall below 1 there); otherwise ``_ramp`` says.
        if t < self._t_down and (prm.ramp_s <= 0.0 or t - self._t_enabled >= prm.ramp_s):
            v[0] = 1.0
        else:
            v[0] = self._ramp(t)
        return self._step_params

    def _apply(
        self,
        forces: Any,
        tick: int,
        t: float,
        positions: Any,
        t_wall: float | None,
    ) -> np.ndarray:
        """``apply`` from the finite check on, for a tick that may trip: the checks with their
        messages, then (nothing tripped) the normal step."""
        out = self.output
        prm = self.params
        # Plain floats: per-element numpy access would cost more than the checks themselves.
        rows = np.asarray(forces, dtype=float).tolist()
        finite = math.isfinite
        if not all(finite(x) for row in rows for x in row):
            bad = [i for i, row in enumerate(rows) if not all(finite(x) for x in row)]
            self.trip(tick, t, f"non-finite force for finger(s) {bad}", "nonfinite_force")
            return out
        if t_wall is not None:
            last, self._last_wall = self._last_wall, t_wall
            if last is not None and t_wall - last > prm.watchdog_s:
                gap = (t_wall - last) * 1e3
                self.trip(
                    tick,
                    t,
                    f"watchdog: {gap:.1f} ms between ticks (limit {prm.watchdog_s * 1e3:g} ms)",
                    "watchdog",
                )
                return out
        if positions is not None and math.isfinite(prm.workspace_radius_m):
            c = prm.workspace_center_m
            for i, p in enumerate(np.asarray(positions, dtype=float).tolist()):
                r = math.sqrt((p[0] - c[0]) ** 2 + (p[1] - c[1]) ** 2 + (p[2] - c[2]) ** 2)
                if not r <= prm.workspace_radius_m:
                    self.trip(
                        tick,
                        t,
                        f"finger {i} left the workspace: {r:.4f} m from its centre "
                        f"(limit {prm.workspace_radius_m:g} m)",
                        "workspace",
                    )
                    return out
        # Nothing trips: the normal step, its workspace check done above.
        self.done(self._step_now(forces, t, None), None)
        return out


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
