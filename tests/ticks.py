"""The tests' way into the tick's one call (hapticd.physics.kernels.tick_step) with chosen inputs: a
renderer on a scene, compiled or not, and a stage inserted into its plan that puts given
values into frame fields (the call then runs in parts around it: hapticd.physics.render.OneCall).

The compiled call is loaded from the run's numba cache (tests/conftest.py compiles it
before the workers start), never compiled here."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from hapticd.allocation.actuation import Actuation
from hapticd.physics import jit
from hapticd.physics.render import Renderer
from hapticd.physics.scene import Scene

MODES = ("uncompiled", "compiled")


def renderer(scene: Scene, radii: Sequence[float], mode: str, allocator: str = "pinv") -> Renderer:
    """A renderer of ``scene`` for fingertips of ``radii`` (m), each with one actuated
    direction (x), its one call compiled (``mode`` "compiled") or not ("uncompiled")."""
    n = len(radii)
    r = Renderer(scene, list(radii), Actuation([[(1.0, 0.0, 0.0)]] * n), allocator)
    use(r, mode)
    return r


def use(r: Renderer, mode: str) -> None:
    """Run ``r``'s one call compiled or not from its next tick on."""
    if mode not in MODES:
        raise ValueError(f"mode {mode!r}: expected one of {MODES}")
    r.use_kernels(jit.compile_kernels(r.kernel_names) if mode == "compiled" else {})


def stage(r: Renderer, name: str) -> object:
    """The stage ``name`` of ``r``'s plan."""
    return next(s for s in r.stages if s.name == name)


class Put:
    """A stage that puts ``values`` (field -> value; set them between ticks) into the frame's
    ``fields`` when it runs: inserted after their writers, it stands for what those wrote
    (a fault injector's declaration: ``corrupts``)."""

    def __init__(self, fields: Sequence[str], name: str = "put") -> None:
        self.name = name
        self.corrupts = tuple(fields)
        self.values: dict[str, object] = {}

    def run(self, frame) -> None:
        for field, value in self.values.items():
            getattr(frame, field)[...] = value


def far(n: int) -> np.ndarray:
    """Device positions (n, 3) m a metre above everything: no contact."""
    return np.tile([0.0, 0.0, 1.0], (n, 1))
