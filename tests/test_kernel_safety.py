"""The safety chain's tick (hapticd.physics.kernels.safety_step, its one source) compiled
against uncompiled: the same output bits, faults, causes, counters, ramps and deadman
state for generated streams, limits, ramps, rate limits, workspaces and deadman buttons;
a clamped force keeps its direction and lands on its limit, over the whole range of
floats; the kernel decides every trip, and the chain names it; hostile forces and a
finger leaving the workspace through a whole run on the compiled path end in zero
force, a latched fault and the devices disabled.

tests/test_safety.py runs every one of its tests compiled and uncompiled as well."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, event, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hapticd.daemon.session import build_session
from hapticd.physics import jit, kernels
from hapticd.physics.frame import Frame
from hapticd.physics.safety import Deadman, Fault, SafetyChain, SafetyParams
from hapticd.profile import load_profile
from tests.conftest import ROOT, capture_writes

LIFT = ROOT / "configs" / "lift-weight.yaml"
GRASP = ROOT / "configs" / "grasp-stiffness.yaml"


@pytest.fixture(scope="module")
def compiled():
    """The compiled kernel (numba is a dependency: no skip without it)."""
    return jit.compile_kernels(["safety_step"])


# The kernel compiled, and the same function uncompiled (the chain's own without a kernel).
PATHS = ["compiled", "plain"]


def kernel_for(path: str, compiled) -> dict:
    return compiled if path == "compiled" else {}


# Every scale a force can have: tiny (subnormal), ordinary, huge but finite, and the
# poison: the magnitude's inlined hypot must be Python's to the last bit at each.
magnitudes = st.one_of(
    st.floats(-20.0, 20.0),
    st.floats(-1e-300, 1e-300),
    st.floats(-1e300, 1e300),
    st.sampled_from([0.0, -0.0, 5e-324, -5e-324, 1.7e308, -1.7e308]),
)
poison = st.sampled_from([math.nan, math.inf, -math.inf])


@st.composite
def cases(draw) -> dict:
    n = draw(st.integers(1, 3))
    ticks = draw(st.integers(1, 40))
    force = magnitudes | poison if draw(st.booleans()) else magnitudes
    deadman = None
    if draw(st.booleans()):
        deadman = tuple(
            draw(st.none() | st.builds(Deadman, st.integers(0, 3), st.floats(0.0, 0.01)))
            for _ in range(n)
        )
    radius = draw(st.none() | st.floats(0.05, 0.2))
    params = SafetyParams(
        ramp_s=draw(st.sampled_from([0.0, 0.005, 0.02])),
        max_rate_n_per_s=draw(st.sampled_from([math.inf, 500.0, 5000.0])),
        workspace_center_m=draw(st.tuples(*[st.floats(-0.02, 0.02)] * 3)),
        workspace_radius_m=math.inf if radius is None else radius,
        watchdog_s=draw(st.sampled_from([math.inf, 0.05])),
        deadman=deadman or (),
    )
    return {
        "limits": [draw(st.floats(0.5, 12.0)) for _ in range(n)],
        "params": params,
        "forces": [draw(arrays(float, (n, 3), elements=force)) for _ in range(ticks)],
        "positions": [
            draw(arrays(float, (n, 3), elements=st.floats(-0.15, 0.15))) for _ in range(ticks)
        ],
        "buttons": [
            draw(arrays(np.uint32, (n,), elements=st.integers(0, 15))) for _ in range(ticks)
        ],
        "walls": [draw(st.sampled_from([1e-3, 1e-3, 1e-3, 0.2])) for _ in range(ticks)],
        "ramp_down_at": draw(st.none() | st.integers(0, ticks)),
        "reset_at": draw(st.none() | st.integers(0, ticks)),
    }


def run_both(case: dict, kernel: dict) -> tuple[SafetyChain, SafetyChain, list[int]]:
    """Feed both chains the case's ticks, the first with the kernel uncompiled, the second
    with ``kernel`` (compiled, or empty: uncompiled); every output and the chains' whole
    arrays (ramps, deadman state, counters) compared bit for bit. Returns the chains and
    the second's kernel's outcomes."""
    dt = 1e-3
    chains = [SafetyChain(case["limits"], case["params"], dt=dt) for _ in range(2)]
    step = kernel.get("safety_step") or kernels.uncompiled("safety_step")
    calls = []

    def counting(*a):
        out = step(*a)
        calls.append(out)
        return out

    chains[1].use_kernels({"safety_step": counting})  # the kernel seam, counted
    for c in chains:
        c.start(0.0)
    wall = 100.0
    for k, forces in enumerate(case["forces"]):
        t = k * dt
        wall += case["walls"][k]
        if case["ramp_down_at"] == k:
            for c in chains:
                c.ramp_down(t, 0.01)
        if case["reset_at"] == k:
            for c in chains:
                c.reset(t)
        outs = [
            c.apply(forces, k, t, case["positions"][k], wall, case["buttons"][k]).copy()
            for c in chains
        ]
        assert outs[0].tobytes() == outs[1].tobytes(), (k, outs)
        assert np.all(np.isfinite(outs[1]))
        for row, limit in zip(outs[1].tolist(), case["limits"], strict=True):
            assert math.hypot(*row) <= limit * (1 + 1e-12)
        a, b = chains
        assert a.fault == b.fault
        assert (a.clamped_ticks, a.rate_limited_ticks) == (b.clamped_ticks, b.rate_limited_ticks)
        assert a.gate == b.gate and a.deadman_status() == b.deadman_status()
        for x, y in zip(a.kernel_arrays, b.kernel_arrays, strict=True):
            assert x.tobytes() == y.tobytes(), k
    return chains[0], chains[1], calls


@given(case=cases())
def test_the_chain_compiled_and_uncompiled_gives_the_same_bits(compiled, case):
    _, b, outcomes = run_both(case, compiled)
    trips = sum(1 for f in outcomes if f >= kernels.SAFETY_NON_FINITE)
    event(f"ticks tripped by the kernel: {min(trips, 2)}+")
    event(f"fault: {b.fault.kind if b.fault else None}")


@pytest.mark.parametrize("path", PATHS)
@given(
    forces=arrays(float, (2, 3), elements=magnitudes.filter(lambda x: x != 0.0)),
    data=st.data(),
)
def test_clamped_forces_keep_their_direction_and_land_on_the_limit(compiled, path, forces, data):
    """Every force above its limit is scaled by limit / |f| (its norm scaled: no square
    overflows for 1e300 N nor underflows for 1e-300 N), to rounding."""
    # A limit below both forces, from 0.01 N: below it, a force near the largest float
    # scales by a subnormal factor and loses its direction's digits (no device's limit is
    # that small).
    smallest = min(math.hypot(*row) for row in forces.tolist())
    assume(smallest > 0.02)
    limit = data.draw(st.floats(0.01, min(smallest / (1 + 1e-9), 1e300)), label="limit")
    case = {
        "limits": [limit, limit],
        "params": SafetyParams(),
        "forces": [forces],
        "positions": [np.zeros((2, 3))],
        "buttons": [np.zeros(2, dtype=np.uint32)],
        "walls": [1e-3],
        "ramp_down_at": None,
        "reset_at": None,
    }
    _, b, outcomes = run_both(case, kernel_for(path, compiled))
    assert outcomes == [kernels.SAFETY_CLAMPED] and b.clamped_ticks == 1
    for row, out in zip(forces.tolist(), b.output.tolist(), strict=True):
        s = limit / math.hypot(*row)
        np.testing.assert_allclose(out, [row[0] * s, row[1] * s, row[2] * s], rtol=1e-12)
        if s > 0.0:  # else a norm beyond the largest float: zero force
            assert math.hypot(*out) == pytest.approx(limit, rel=1e-12)


@pytest.mark.parametrize("path", PATHS)
def test_the_kernel_decides_every_trip_and_the_chain_names_it(compiled, path):
    """Ordinary ticks are made safe and counted by the kernel; a finger exactly at the
    workspace's radius is inside, one a hair beyond it trips (its index in the outcome, its
    distance in the message); a non-finite force trips naming every finger that has one;
    the watchdog is the chain's. Each trip zeroes the output and latches its fault."""
    chain = SafetyChain(
        [2.0, 2.0],
        SafetyParams(max_rate_n_per_s=500.0, workspace_radius_m=0.1, watchdog_s=0.05),
    )
    step = kernel_for(path, compiled).get("safety_step") or kernels.uncompiled("safety_step")
    outcomes = []
    chain.use_kernels({"safety_step": lambda *a: outcomes.append(step(*a)) or outcomes[-1]})
    pos = np.array([[0.05, 0.0, 0.0], [-0.05, 0.0, 0.0]])
    f = np.array([[3.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    for k in range(20):
        chain.apply(f, k, k * 1e-3, pos, 1.0 + k * 1e-3)
    assert chain.clamped_ticks == 20 and chain.rate_limited_ticks > 0
    assert all(o < kernels.SAFETY_NON_FINITE for o in outcomes)
    edge = pos.copy()
    edge[1, 0] = -0.1  # exactly at the radius: inside
    chain.apply(f, 20, 0.02, edge, 1.02)
    assert chain.fault is None and chain.output[0, 0] == 2.0
    edge[1, 0] = math.nextafter(-0.1, -1.0)  # one float beyond it
    chain.apply(f, 21, 0.021, edge, 1.021)
    assert outcomes[-1] == kernels.SAFETY_WORKSPACE | 1 << kernels.SAFETY_FINGERS
    assert chain.fault == Fault(
        21,
        0.021,
        "finger 1 left the workspace: 0.1000 m from its centre (limit 0.1 m)",
        "workspace",
    )
    assert np.all(chain.output == 0.0)
    chain.reset(0.03)
    chain.apply(f, 22, 0.03, pos, 1.03)
    chain.apply(f, 23, 0.031, pos, 1.2)  # 170 ms since the last tick
    assert chain.fault.kind == "watchdog" and chain.fault.tick == 23
    assert chain.fault.cause == "watchdog: 170.0 ms between ticks (limit 50 ms)"
    assert np.all(chain.output == 0.0)
    chain.reset(0.04)  # forces on again: the watchdog starts afresh
    chain.apply(f, 24, 0.04, pos, 2.0)
    assert np.any(chain.output != 0.0)
    bad = np.array([[math.inf, 0.0, 0.0], [math.nan, 0.0, 0.0]])
    chain.apply(bad, 25, 0.041, pos, 2.001)
    assert outcomes[-1] == kernels.SAFETY_NON_FINITE | 0b11 << kernels.SAFETY_FINGERS
    assert chain.fault.kind == "nonfinite_force" and chain.fault.tick == 25
    assert chain.fault.cause == "non-finite force for finger(s) [0, 1]"
    assert np.all(chain.output == 0.0)
    # A non-finite force and a stall on one tick: the non-finite force is named first.
    chain.reset(0.05)
    chain.apply(f, 26, 0.05, pos, 3.0)
    chain.apply(np.array([[0.0, 0.0, 0.0], [0.0, math.nan, 0.0]]), 27, 0.051, pos, 3.5)
    assert chain.fault.cause == "non-finite force for finger(s) [1]"


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize(
    "bad",
    [(0.0, math.nan, 0.0), (math.nan, 0.0, 0.0), (0.0, 0.0, -math.inf), (math.inf, 0.0, math.nan)],
)
def test_a_non_finite_position_is_beyond_the_workspace(compiled, path, bad):
    """A finger whose position is not finite (a NaN beside zeros too) has left the
    workspace: zero force and the fault, naming it."""
    chain = SafetyChain([2.0, 2.0], SafetyParams(workspace_radius_m=0.1))
    chain.use_kernels(kernel_for(path, compiled))
    pos = np.array([[0.05, 0.0, 0.0], bad])
    out = chain.apply(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), 3, 0.003, pos)
    assert np.all(out == 0.0)
    assert chain.fault.kind == "workspace" and chain.fault.tick == 3
    assert chain.fault.cause.startswith("finger 1 left the workspace: ")


def test_arrays_the_kernel_cannot_take_are_copied_for_it(compiled):
    """A list, another dtype, a non-contiguous view: the same output, from the kernel; a
    shape that is not (F, 3) is refused."""
    chain = SafetyChain([2.0, 2.0])
    called = []
    step = compiled["safety_step"]
    chain.use_kernels({"safety_step": lambda *a: called.append(1) or step(*a)})
    want = [[2.0, 0.0, 0.0], [0.0, 2.0, 0.0]]
    strided = np.zeros((2, 6))
    strided[:, ::2] = [[3.0, 0.0, 0.0], [0.0, 2.0, 0.0]]
    for forces in (
        [[3.0, 0.0, 0.0], [0.0, 2.0, 0.0]],
        np.array([[3, 0, 0], [0, 2, 0]], dtype=np.float32),
        strided[:, ::2],
    ):
        assert chain.apply(forces, 0, 0.0).tolist() == want
    assert called == [1, 1, 1]
    chain.apply(np.array([[3.0, 0.0, 0.0], [0.0, 2.0, 0.0]]), 1, 0.001)
    assert called == [1, 1, 1, 1]
    with pytest.raises(ValueError, match=r"\(2, 3\) arrays"):
        chain.apply([3.0, 0.0, 0.0], 2, 0.002)


class Poison:
    """A last stage that puts ``value`` into finger 0's rendered force from ``at`` (s) on:
    what a broken renderer could hand to the safety chain."""

    name = "poison"

    corrupts = ("rendered_force",)

    def __init__(self, loop, value: float, at: float) -> None:
        self.loop, self.value, self.at = loop, value, at

    def run(self, frame) -> None:
        if self.loop.now() >= self.at:
            frame.rendered_force[0] = self.value


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 1e300, -1e6])
@pytest.mark.parametrize("path", [LIFT, GRASP], ids=["lift", "grasp"])
def test_hostile_forces_through_the_compiled_safety_path(compiled, path, value):
    """Non-finite forces: zero force, a latched nonfinite_force fault with its message, the
    devices disabled. Huge finite ones: clamped to the limit, direction kept, no fault."""
    profile = load_profile(path, ["rendering.kernels=compiled"])
    session = build_session(profile, paced=False, duration_s=1.2)
    loop = session.loop
    assert session.safety._step is not kernels.uncompiled("safety_step")
    last = session.renderer.stage_names[-1]
    session.renderer.insert(Poison(loop, value, 1.0), after=last)
    written = capture_writes(session)
    summary = session.run()
    forces = np.array(written)
    limit = max(session.safety.limits)
    assert np.all(np.isfinite(forces))
    assert np.all(np.linalg.norm(forces, axis=1) <= limit * (1 + 1e-12))
    if math.isfinite(value):
        assert summary["fault"] is None, summary
        # Finger 0 pushed at its limit along (1, 1, 1) * sign once the rate limit let it
        # (the last tick's, before the shutdown's zeros).
        f0 = forces[-2 * len(session.devices)]
        assert np.linalg.norm(f0) == pytest.approx(session.safety.limits[0], rel=1e-9)
        np.testing.assert_allclose(f0 / np.linalg.norm(f0), np.sign(value) / math.sqrt(3))
        return
    fault = session.safety.fault
    assert fault is not None and fault.kind == "nonfinite_force", summary
    assert fault.cause == "non-finite force for finger(s) [0]"
    assert fault.tick == 1000
    assert np.all(forces[-len(session.devices) :] == 0.0)
    assert all(not dev.enabled for dev in session.devices)


@given(case=cases())
def test_the_stage_on_a_frame_is_the_uncompiled_chain(compiled, case):
    """``run`` (the loop's call: the compiled normal path straight from the frame) against
    the uncompiled chain's ``apply``, tick by tick."""
    n = len(case["limits"])
    dt = 1e-3
    ref = SafetyChain(case["limits"], case["params"], dt=dt)
    stage = SafetyChain(case["limits"], case["params"], dt=dt)
    stage.use_kernels(compiled)
    frame = Frame(n, n)
    wall = 100.0
    for c in (ref, stage):
        c.start(0.0)
    for k, forces in enumerate(case["forces"]):
        t = k * dt
        wall += case["walls"][k]
        if case["ramp_down_at"] == k:
            for c in (ref, stage):
                c.ramp_down(t, 0.01)
        frame.tick[()] = k
        frame.t[()] = t
        frame.rendered_force[...] = forces
        frame.device_pos[...] = case["positions"][k]
        frame.buttons[...] = case["buttons"][k]
        want = ref.apply(forces, k, t, case["positions"][k], wall, case["buttons"][k])
        stage.run(frame, wall)
        assert frame.device_force.tobytes() == want.tobytes(), k
        assert stage.fault == ref.fault
        assert stage.clamped_ticks == ref.clamped_ticks
        assert stage.rate_limited_ticks == ref.rate_limited_ticks


@pytest.mark.parametrize("path", ["python", "compiled"])
def test_new_limits_reach_the_kernel_and_a_copy_changes_nothing(compiled, path):
    chain = SafetyChain([5.0, 5.0])
    chain.use_kernels(compiled if path == "compiled" else {})
    push = np.array([[10.0, 0.0, 0.0], [0.0, 0.0, -10.0]])
    chain.limits[0] = 100.0  # a copy of the limits: nothing changes
    assert chain.apply(push, 0, 0.0).tolist() == [[5.0, 0.0, 0.0], [0.0, 0.0, -5.0]]
    chain.set_param("force_limit_n", 2.0)
    assert chain.limits == [2.0, 2.0]
    assert chain.apply(push, 1, 0.001).tolist() == [[2.0, 0.0, 0.0], [0.0, 0.0, -2.0]]
