"""The conformance suite every allocator passes: finite, bounded and continuous through
rank changes, coincident and collinear contacts, forces from 1e-9 to 1e3 N, linear where
it claims to be, and NaN input refused (docs/allocation.md, "Checking an allocator").

An allocator here is ``f(G, M_a, lam) -> lam_a``: G (6, 3p), M_a (3p, r), lam (3p,) N in,
lam_a (r,) N out. Pure: numpy in, a list of failures out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hapticd.allocation.cases import SWEEPS, block_actuation
from hapticd.allocation.grasp import grasp_matrix
from hapticd.allocation.kernels import PLUGIN_GAIN

Allocator = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]

# The largest |M_a lam_a| / |lam| a robust allocator may render: the built-ins' documented
# bounds (docs/allocation.md) at the default threshold stay below 1e3 on every case here;
# a force 1e4 times what the contact asked for is absurd on any rig (the tick latches a
# plugin's fault beyond it too: hapticd.allocation.kernels.PLUGIN_GAIN).
AMPLIFICATION = PLUGIN_GAIN
SCALES = (1e-9, 1e-6, 1e-3, 1.0, 1e3)  # N: the forces a linear allocator scales through
SWEEP_POINTS = 201  # t in [-50, 50] mm through the singular point
ZOOM, REFINE = 32, 5  # the largest step's interval cut into 32, five times (3e7 x finer)
JUMP_N = 1e-6  # N, for forces of about 1 N: a step left this large once zoomed in is a jump

LINEAR_RTOL = 1e-9


@dataclass(frozen=True)
class Claims:
    """What an allocator promises: ``robust`` (finite, bounded and continuous where the
    grasp or the actuation loses rank), ``linear`` (lam_a linear in lam)."""

    robust: bool = True
    linear: bool = True


@dataclass(frozen=True)
class Outcome:
    """One case: its name, passed or not, and what was seen (the reason when failed)."""

    case: str
    passed: bool
    detail: str = ""


def _collinear(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # Three contacts along one line (x), the middle one moving off it by t.
    pts = np.array([[-0.03, 0.0, 0.0], [0.0, t, 0.0], [0.03, 0.0, 0.0]])
    M = block_actuation([[(1, 0, 0.3)], [(0, 0.2, 1)], [(-1, 0, 0.3)]])
    lam = np.array([1.0, 0, 0.3, 0, 0.1, 0.5, -1.0, 0, 0.3])
    return grasp_matrix(pts, np.zeros(3)), M, lam


SINGULAR = {**{name: make for name, (make, _) in SWEEPS.items()}, "collinear contacts": _collinear}
# The cases every allocator runs, after SINGULAR's (linearity only when claimed).
CASES_ALWAYS = ("forces from 1e-9 to 1e3 N", "linear in lam", "NaN and inf input")


def _call(f: Allocator, G: np.ndarray, M: np.ndarray, lam: np.ndarray) -> np.ndarray:
    out = np.asarray(f(G.copy(), M.copy(), lam.copy()), dtype=float)
    if out.shape != (M.shape[1],):
        raise ValueError(f"returned shape {out.shape}, not (r,) = ({M.shape[1]},)")
    return out


def _bounded(G: np.ndarray, M: np.ndarray, lam: np.ndarray, lam_a: np.ndarray) -> str:
    """Why lam_a is not finite and bounded, or ''."""
    if not np.all(np.isfinite(lam_a)):
        return f"non-finite output {lam_a.tolist()}"
    asked = float(np.linalg.norm(lam))
    # Both what the actuators render and what they are asked for: directions that nearly
    # cancel render little with huge actuator forces, which a device would still get.
    for what, size in (("renders", np.linalg.norm(M @ lam_a)), ("asks", np.linalg.norm(lam_a))):
        if size > AMPLIFICATION * asked + 1e-300:
            return (
                f"{what} {size:.3g} N for {asked:.3g} N of contact force (over {AMPLIFICATION:g}x)"
            )
    return ""


def _steps(f: Allocator, make: Callable, ts: np.ndarray) -> tuple[np.ndarray, str]:
    """|lam_a(t_i+1) - lam_a(t_i)| (max over actuators) along ``ts``, or why a point's
    output is not finite and bounded."""
    vals = []
    for t in ts:
        G, M, lam = make(float(t))
        lam_a = _call(f, G, M, lam)
        why = _bounded(G, M, lam, lam_a)
        if why:
            return np.zeros(0), f"at t = {t:.6g}: {why}"
        vals.append(lam_a)
    return np.abs(np.diff(np.array(vals), axis=0)).max(axis=1), ""


def _sweep(f: Allocator, name: str) -> Outcome:
    """Through the singular point (t = 0): bounded everywhere, and continuous: the largest
    step between neighbouring points, zoomed into REFINE times (each time its interval cut
    into ZOOM), vanishes for a continuous map and stays for a jump."""
    make = SINGULAR[name]
    ts = np.linspace(-0.05, 0.05, SWEEP_POINTS)
    steps, why = _steps(f, make, ts)
    if why:
        return Outcome(name, False, why)
    first = float(steps.max())
    for _ in range(REFINE):
        i = int(steps.argmax())
        ts = np.linspace(ts[i], ts[i + 1], ZOOM + 1)
        steps, why = _steps(f, make, ts)
        if why:
            return Outcome(name, False, why)
    last = float(steps.max())
    if last > JUMP_N:
        return Outcome(name, False, f"jumps by {last:.3g} N at t = {ts[int(steps.argmax())]:.6g}")
    return Outcome(name, True, f"largest step {first:.3g} N, {last:.3g} N zoomed in")


def _grasps(seed: int = 0, n: int = 20) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Random regular grasps: 2-4 contacts on a 30 mm sphere, 1-3 directions each."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        p = int(rng.integers(2, 5))
        pts = rng.normal(size=(p, 3))
        pts *= 0.03 / np.linalg.norm(pts, axis=1, keepdims=True)
        dirs = [[tuple(rng.normal(size=3)) for _ in range(int(rng.integers(1, 4)))] for _ in pts]
        out.append((grasp_matrix(pts, np.zeros(3)), block_actuation(dirs), rng.normal(size=3 * p)))
    return out


def _scales(f: Allocator, linear: bool) -> Outcome:
    name = "forces from 1e-9 to 1e3 N"
    for G, M, lam in _grasps():
        base = _call(f, G, M, lam)
        for s in SCALES:
            got = _call(f, G, M, s * lam)
            why = _bounded(G, M, s * lam, got)
            if why:
                return Outcome(name, False, f"at {s:g} N: {why}")
            # Relative to the largest force: a component that cancels to near zero keeps
            # its rounding, which an elementwise tolerance would call non-linear.
            tol = LINEAR_RTOL * max(float(np.abs(s * base).max()), 1e-300)
            if linear and not np.allclose(got, s * base, rtol=0, atol=tol):
                worst = float(np.abs(got - s * base).max())
                return Outcome(name, False, f"not linear: at {s:g} x, off by {worst:.3g} N")
    return Outcome(name, True)


def _superposition(f: Allocator) -> Outcome:
    name = "linear in lam"
    rng = np.random.default_rng(1)
    for G, M, a in _grasps(2):
        b = rng.normal(size=a.size)
        want = _call(f, G, M, a) + 2.5 * _call(f, G, M, b)
        got = _call(f, G, M, a + 2.5 * b)
        why = _bounded(G, M, a + 2.5 * b, got) or _bounded(G, M, a, want)
        if why:
            return Outcome(name, False, why)
        scale = max(float(np.abs(want).max()), 1e-300)
        if not np.allclose(got, want, rtol=0, atol=LINEAR_RTOL * scale):
            off = float(np.abs(got - want).max())
            return Outcome(name, False, f"f(a + 2.5 b) - f(a) - 2.5 f(b) is {off:.3g} N")
    return Outcome(name, True)


def _nan(f: Allocator) -> Outcome:
    name = "NaN and inf input"
    G, M, lam = _grasps(3, 1)[0]
    for label, args in (
        ("lam", (G, M, np.where(np.arange(lam.size) == 1, np.nan, lam))),
        ("lam", (G, M, np.where(np.arange(lam.size) == 0, np.inf, lam))),
        ("G", (np.where(np.arange(G.size).reshape(G.shape) == 4, np.nan, G), M, lam)),
    ):
        try:
            out = _call(f, *args)
        except Exception:  # refused: what the tick's safety chain also does
            continue
        if not np.all(np.isfinite(out)):
            return Outcome(name, False, f"a non-finite {label} gave {out.tolist()}")
    return Outcome(name, True, "refused or finite")


def check(f: Allocator, claims: Claims = Claims()) -> list[Outcome]:
    """Every case of the suite for ``f``: the rank changes (skipped, and said, when it
    does not claim to be robust), the forces' range, linearity if claimed, NaN input. An
    exception from ``f`` on a regular case fails that case, naming it."""
    cases: list[tuple[str, Callable[[], Outcome]]] = [
        (name, lambda name=name: _sweep(f, name)) for name in SINGULAR
    ]
    if not claims.robust:
        cases = []
    cases.append(("forces from 1e-9 to 1e3 N", lambda: _scales(f, claims.linear)))
    if claims.linear:
        cases.append(("linear in lam", lambda: _superposition(f)))
    cases.append(("NaN and inf input", lambda: _nan(f)))
    out = [] if claims.robust else [
        Outcome(name, True, "skipped: not claimed robust") for name in SINGULAR
    ]  # fmt: skip
    for name, run in cases:
        try:
            out.append(run())
        except Exception as exc:
            out.append(Outcome(name, False, f"raised {type(exc).__name__}: {exc}"))
    return out


def allocator(name: str) -> tuple[Allocator, Claims]:
    """The allocator ``name`` as the suite calls it, and what it claims (KeyError: none). An
    installed plugin: its Python function, robust, linear if it says so (its ``linear``).
    A built-in: the seed's exact formulas are not robust (they divide by what a rank change
    sends to zero); ``adaptive`` at alpha 0.5 (linear for a fixed alpha)."""
    from hapticd.allocation import METHODS, allocate, plugins

    if name not in METHODS:
        plugin = plugins.get(name)
        if plugin is None:
            raise KeyError(name)
        return plugins.python_function(plugin.obj), Claims(linear=plugins.linear(name))
    alpha = 0.5 if name == "adaptive" else 0.0

    def f(G: np.ndarray, M: np.ndarray, lam: np.ndarray) -> np.ndarray:
        return allocate(name, G, M, lam, alpha=alpha)

    return f, Claims(robust=not name.endswith("_exact"))
