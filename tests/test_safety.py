import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hapticd.physics import jit, kernels
from hapticd.physics.safety import SafetyChain


@pytest.fixture(scope="module", autouse=True, params=["python", "compiled"])
def safety_path(request):
    """Every test here both ways: the chain's normal tick (hapticd.physics.kernels.safety_step)
    uncompiled and compiled (tests/test_kernel_safety.py compares them)."""
    if request.param == "python":
        yield request.param
        return
    compiled = jit.compile_kernels(["safety_step"])
    init = SafetyChain.__init__

    def compiled_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        self.use_kernels(compiled)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(SafetyChain, "__init__", compiled_init)
        yield request.param


wild = st.one_of(
    st.floats(-1e6, 1e6),
    st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 1e-300, 1e300]),
)


@given(st.lists(arrays(float, (2, 3), elements=wild), min_size=1, max_size=40))
def test_output_is_always_finite_within_limits_and_latches(stream):
    limits = [3.0, 5.0]
    chain = SafetyChain(limits)
    latched_at = None
    for k, forces in enumerate(stream):
        out = chain.apply(forces, k, k * 1e-3)
        assert np.all(np.isfinite(out))
        for i, lim in enumerate(limits):
            assert math.hypot(*out[i]) <= lim * (1 + 1e-12)
        if latched_at is None and not np.all(np.isfinite(forces)):
            latched_at = k
        if latched_at is not None:
            assert chain.latched and chain.fault.tick == latched_at
            assert np.all(out == 0.0)
        elif np.all(np.isfinite(forces)):
            for i, lim in enumerate(limits):
                f = forces[i]
                n = math.hypot(*f)
                if n <= lim:
                    np.testing.assert_array_equal(out[i], f)
                else:  # clamped: direction kept
                    np.testing.assert_allclose(out[i], f * (lim / n), rtol=1e-12)


def test_fault_cause_and_reset():
    chain = SafetyChain([1.0])
    chain.apply(np.array([[np.nan, 0, 0]]), 7, 0.007)
    assert chain.fault.tick == 7 and "non-finite" in chain.fault.cause
    assert np.all(chain.apply(np.array([[0.5, 0, 0]]), 8, 0.008) == 0)
    chain.reset()
    np.testing.assert_array_equal(chain.apply(np.array([[0.5, 0, 0]]), 9, 0.009), [[0.5, 0, 0]])


def test_bad_limits_rejected():
    with pytest.raises(ValueError):
        SafetyChain([1.0, 0.0])
    with pytest.raises(ValueError):
        SafetyChain([np.inf])


# -- ramp, rate limit, workspace, watchdog --------------------------------------------------

from hapticd.physics.safety import SafetyParams  # noqa: E402

finite = st.floats(-50, 50)


@given(
    st.lists(arrays(float, (2, 3), elements=finite), min_size=2, max_size=80),
    st.floats(0.0, 0.05),
    st.floats(100.0, 5000.0),
)
def test_ramp_and_rate_limit_hold_on_any_finite_stream(stream, ramp_s, rate):
    dt = 1e-3
    limits = [4.0, 6.0]
    chain = SafetyChain(limits, SafetyParams(ramp_s=ramp_s, max_rate_n_per_s=rate), dt=dt)
    chain.start(0.0)
    prev = np.zeros((2, 3))
    for k, forces in enumerate(stream):
        t = k * dt
        out = chain.apply(forces, k, t).copy()
        scale = 1.0 if ramp_s == 0 else min(1.0, t / ramp_s)
        for i, lim in enumerate(limits):
            n = math.hypot(*out[i])
            assert n <= lim * scale * (1 + 1e-12) + 1e-15  # the ramp, within the limit
            if np.any(out[i] != 0):
                assert math.hypot(*(out[i] - prev[i])) <= rate * dt * (1 + 1e-9)
            else:
                assert np.all(forces[i] == 0) or scale == 0 or n == 0
        prev = out


def test_a_drop_to_zero_is_never_delayed():
    chain = SafetyChain([5.0], SafetyParams(max_rate_n_per_s=100.0), dt=1e-3)
    chain.start(0.0)
    for k in range(200):
        chain.apply(np.array([[3.0, 0, 0]]), k, k * 1e-3)
    assert chain.output[0, 0] == pytest.approx(3.0)  # reached at 0.1 N per tick
    np.testing.assert_array_equal(chain.apply(np.zeros((1, 3)), 200, 0.2), 0)


def test_watchdog_latches_a_stalled_loop():
    chain = SafetyChain([5.0], SafetyParams(watchdog_s=0.05))
    chain.apply(np.ones((1, 3)), 0, 0.0, t_wall=10.0)
    chain.apply(np.ones((1, 3)), 1, 0.001, t_wall=10.001)
    assert not chain.latched
    out = chain.apply(np.ones((1, 3)), 2, 0.002, t_wall=10.2)
    assert chain.latched and "watchdog: 199" in chain.fault.cause
    assert np.all(out == 0)


def test_leaving_the_workspace_latches():
    chain = SafetyChain(
        [5.0, 5.0], SafetyParams(workspace_center_m=(0, 0, 0.01), workspace_radius_m=0.075)
    )
    inside = np.array([[0.05, 0, 0.01], [-0.05, 0, 0.01]])
    chain.apply(np.ones((2, 3)), 0, 0.0, positions=inside)
    assert not chain.latched
    chain.apply(np.ones((2, 3)), 1, 0.001, positions=inside + np.array([[0.03, 0, 0], [0, 0, 0]]))
    assert chain.latched and "finger 0 left the workspace" in chain.fault.cause
    chain.apply(np.ones((2, 3)), 2, 0.002, positions=np.full((2, 3), np.nan))
    assert np.all(chain.output == 0)


def test_a_stalled_servo_loop_ends_in_zero_force():
    """The loop's watchdog times the gap between ticks on its clock: a tick that takes
    longer than the 0.1 s limit latches a fault at that tick, and every force after it is
    zero. The clock is the test's own (1 ms a reading, 0.15 s more at the stalled tick), so
    that a loaded machine stalling this process trips nothing else."""
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile
    from tests.conftest import GRASP_PROFILE, AtTick

    s = build_session(load_profile(GRASP_PROFILE), paced=False)
    assert not s.loop.wall_watchdog  # replay devices on the nominal clock: a simulation
    s.loop.wall_watchdog = True  # as with a device in the loop
    now = [0.0]

    def clock() -> float:
        now[0] += 1e-3
        return now[0]

    def stall(frame) -> None:
        now[0] += 0.15

    s.loop.watchdog_clock = clock
    # In the pinch, a tick takes longer than the 0.1 s watchdog.
    s.renderer.insert(AtTick(2999, stall), after="allocation")
    out = s.run()
    assert out["fault"] is not None and "watchdog" in out["fault"]["cause"]
    assert "151.0 ms between ticks" in out["fault"]["cause"]  # its 1 ms and the stall
    assert out["fault"]["tick"] == 2999
    for dev in s.devices:
        assert np.all(dev.forces[2999:] == 0)
        assert np.any(dev.forces[:2999] != 0)


def test_a_stall_in_the_renderers_one_call_ends_in_zero_force():
    """The same with the safety chain's tick made in the renderer's one call (no stage
    inserted: the plan is one call): the chain takes the watchdog's time after the call,
    and the stalled tick's force, already made, is not sent: zero from that tick on."""
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile
    from tests.conftest import GRASP_PROFILE

    s = build_session(load_profile(GRASP_PROFILE, ["rendering.kernels=compiled"]), paced=False)
    assert s.renderer.one_call is not None
    s.loop.wall_watchdog = True
    readings = [0]

    def clock() -> float:  # 1 ms a tick (one reading each), 0.15 s more at tick 2999
        readings[0] += 1
        return readings[0] * 1e-3 + (0.15 if readings[0] > 2999 else 0.0)

    s.loop.watchdog_clock = clock
    out = s.run()
    assert out["fault"] is not None and "151.0 ms between ticks" in out["fault"]["cause"]
    assert out["fault"]["tick"] == 2999
    for dev in s.devices:
        assert np.all(dev.forces[2999:] == 0)
        assert np.any(dev.forces[2990:2999] != 0)


def test_a_ramp_down_ends_at_exactly_zero_despite_rounded_tick_times():
    from hapticd.physics.safety import SafetyChain

    dt = 1e-3
    for start in range(2000, 4000, 7):  # many start ticks: some end a hair short of 1.0
        chain = SafetyChain([5.0, 5.0], dt=dt)
        chain.ramp_down((start + 1) * dt, 0.05)
        k = start + 1
        while not chain.ramped_down(k * dt):
            chain.apply(np.full((2, 3), 1.0), k, k * dt)
            k += 1
        out = chain.apply(np.full((2, 3), 1.0), k, k * dt)
        assert k - (start + 1) == 50 and np.all(out == 0.0), (start, out)


def test_an_unpaced_simulation_paused_by_the_machine_is_not_a_stalled_loop():
    """Unpaced on replay devices time is the nominal clock: a pause of the process (a
    loaded machine, a debugger) endangers no one and must not latch the watchdog."""
    import time

    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile
    from tests.conftest import GRASP_PROFILE, AtTick

    s = build_session(load_profile(GRASP_PROFILE), paced=False)
    s.renderer.insert(AtTick(2999, lambda f: time.sleep(0.15)), after="allocation")
    out = s.run()
    assert out["fault"] is None
    assert out["ticks"] == 7801
    # A paced run, or any run with a device that is not simulated, keeps the watchdog.
    assert build_session(load_profile(GRASP_PROFILE), paced=True).loop.wall_watchdog


def test_each_path_is_the_one_tested(safety_path):
    uncompiled = SafetyChain([1.0])._step is kernels.uncompiled("safety_step")
    assert uncompiled == (safety_path == "python")
