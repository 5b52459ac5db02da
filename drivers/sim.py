"""A simulated finger: closes the haptic loop without hardware.

The fingertip (mass m, kg) is held by the hand, modelled as a spring-damper
(k_h N/m, b_h N s/m) pulling it along a recorded path; the device's rendered
force acts on it too:

    m x'' = k_h (path(t) - x) - b_h x' + F_rendered

integrated in fine steps (at most ``max_step_s``) between reads, with the
force held as a device's amplifier holds it. Unlike replay, the finger *feels*
the rendering: a stiff virtual wall pushes it back, and a wall that is not
passive (Colgate & Schenkel: b_h > K T / 2) makes it chatter. Time comes from
``clock``, the servo loop's nominal tick time.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from hapticd_drivers.base import DeviceError, DeviceInfo, DeviceState
from hapticd_drivers.replay import ReplayDevice


class Hand:
    """A fingertip (mass, kg) pulled along ``path`` by a spring-damper (N/m, N s/m); external
    forces (N) act on it too. Integrated in steps of at most ``max_step`` s."""

    def __init__(self, path: Any, mass: float, k: float, b: float, max_step: float = 1e-4) -> None:
        self.path, self.mass, self.k, self.b, self.max_step = path, mass, k, b, max_step
        self.reset()

    def reset(self) -> None:
        start, _ = self.path.at(0.0)
        self.x, self.v, self.t = list(start), [0.0, 0.0, 0.0], 0.0

    def advance(self, until: float, force: tuple[float, float, float]) -> None:
        span = until - self.t
        if span <= 0.0:
            return
        n = max(1, math.ceil(span / self.max_step))
        h = span / n
        m, kh, bh = self.mass, self.k, self.b
        x, v, t = self.x, self.v, self.t
        for _ in range(n):
            t += h
            goal, _ = self.path.at(t)
            for i in range(3):
                a = (kh * (goal[i] - x[i]) - bh * v[i] + force[i]) / m
                v[i] += h * a
                x[i] += h * v[i]
        self.t = until


class SimulatedFinger(ReplayDevice):
    """A fingertip of mass ``mass_kg`` pulled along a path by the hand, feeling the device."""

    def __init__(
        self,
        times: np.ndarray,
        positions: np.ndarray,
        clock: Callable[[], float] | None = None,
        max_force_n: float = 12.0,
        serial: str = "sim",
        hold_s: float = 0.0,
        workspace_radius_m: float = 0.075,
        mass_kg: float = 0.05,
        hand_stiffness_n_per_m: float = 300.0,
        hand_damping_n_s_per_m: float = 3.0,
        max_step_s: float = 1e-4,
        buttons: np.ndarray | None = None,
        repeat: bool = False,
    ) -> None:
        super().__init__(
            times,
            positions,
            clock,
            max_force_n,
            serial,
            hold_s,
            workspace_radius_m,
            buttons,
            repeat,
        )
        if not (mass_kg > 0 and hand_stiffness_n_per_m >= 0 and hand_damping_n_s_per_m >= 0):
            raise DeviceError(
                f"sim {serial}: mass must be positive, hand stiffness and damping >= 0"
            )
        self.info = DeviceInfo("sim", serial, float(max_force_n), workspace_radius_m)
        self._who = f"sim {serial}"  # names it in a refusal
        self.hand = Hand(
            self.path,
            float(mass_kg),
            float(hand_stiffness_n_per_m),
            float(hand_damping_n_s_per_m),
            float(max_step_s),
        )
        self._applied = (0.0, 0.0, 0.0)

    @property
    def x(self) -> list[float]:
        return self.hand.x

    def open(self) -> None:
        super().open()
        self.hand.reset()
        self._applied = (0.0, 0.0, 0.0)

    def read_state(self, state: DeviceState) -> None:
        if not self._open:
            self._require_open("read from")
        now = self._time()
        self._now = now
        self.hand.advance(now, self._applied)
        # Item by item through the state's memoryviews: a fraction of a numpy item store.
        p, v = state.pos_view, state.vel_view
        x0, x1, x2 = self.hand.x
        p[0], p[1], p[2] = x0, x1, x2
        v[0], v[1], v[2] = self.hand.v
        state.timestamp = now
        state.buttons = self.path.buttons_at(now)
        isfinite = math.isfinite
        if not (isfinite(x0) and isfinite(x1) and isfinite(x2)):
            raise DeviceError(f"sim {self.info.serial}: the simulated finger diverged")

    def write_force(self, force: np.ndarray) -> None:
        super().write_force(force)
        # The force just kept is the one applied: the accepted one, zero while disabled.
        f, i = self._forces_mv, 3 * self._n_forces - 3
        self._applied = (f[i], f[i + 1], f[i + 2])
