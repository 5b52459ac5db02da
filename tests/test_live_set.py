"""A live set costs the servo tick only stores: a number writes its slots in the running call,
a structural change is prepared in the submitting thread and swapped in at a tick boundary."""

from __future__ import annotations

import threading
import tracemalloc

import numpy as np
import pytest

from hapticd.daemon.session import build_session
from hapticd.loop.commands import SetParam
from hapticd.params import PARAMS
from hapticd.physics import jit
from hapticd.physics import kernels as kn
from hapticd.physics.render import OneCall, Renderer
from hapticd.profile import load_profile
from tests.conftest import GRASP_PROFILE, IN_PROCESS, ROOT

LIFT_PROFILE = ROOT / "configs" / "lift-weight.yaml"
# Each finger 2 mm into the 5 cm cube (radius 8 mm), on either side along x.
SQUEEZE = np.array([[0.031, 0.0, 0.0], [-0.031, 0.0, 0.0]])


def _loop(path, kernels: str = "python"):
    """A loop built from the profile at ``path``, not running: its ticks made by hand."""
    profile = load_profile(path, [*IN_PROCESS, f"rendering.kernels={kernels}"])
    return build_session(profile, paced=False).loop


def _tick(loop, pos: np.ndarray = SQUEEZE):
    frame = loop.frame
    frame.device_pos[:] = pos
    frame.device_vel[:] = 0.0
    loop.renderer.run(frame)
    return frame


class Builds:
    """Counts plans made and calls bound, with the thread that made each."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.planned: list[str] = []
        self.bound: list[str] = []
        planned, bind = Renderer._planned, OneCall._bind

        def counted_planned(r, *a, **k):
            self.planned.append(threading.current_thread().name)
            return planned(r, *a, **k)

        def counted_bind(call, *a, **k):
            self.bound.append(threading.current_thread().name)
            return bind(call, *a, **k)

        monkeypatch.setattr(Renderer, "_planned", counted_planned)
        monkeypatch.setattr(OneCall, "_bind", counted_bind)

    @property
    def count(self) -> int:
        return len(self.planned) + len(self.bound)


def _set(loop, name, value, k: int = 1):
    """Submit a set (prepared here) and apply it at tick ``k``'s boundary; its Applied."""
    done = loop.submit(SetParam(name, PARAMS[name].check(value)))
    loop._apply_inbox(k, k * loop.period)
    assert done.is_set() and done.error is None, done.error
    return done


def _without_tick_work(call: OneCall) -> np.ndarray:
    """The call's plan less what each tick rewrites (the planes at the object's pose, the
    free body's scratch, the object's position in the allocation's params)."""
    names, at = kn.TICK_PLAN, call._layout
    keep = np.ones(call._plan.size, dtype=bool)
    centre = kn.TICK_AT + kn.TICK_ALLOCATION_AT + 5
    keep[centre : centre + 3] = False
    # Each block by name (the generated layout orders them as it will): the planes and
    # their row counts, and the free body's scratch.
    ends = [*at[1 : len(names)], call._plan.size]
    for i, name in enumerate(names):
        if name in ("planes", "scratch") or (name == "rows" and names[i - 1] == "planes"):
            keep[at[i] : ends[i]] = False
    return call._plan[keep].copy()


NUMBERS = [
    (LIFT_PROFILE, "stiffness_n_per_m", 350.0),
    (LIFT_PROFILE, "damping_n_s_per_m", 0.9),
    (LIFT_PROFILE, "mass_kg", 0.09),
    (LIFT_PROFILE, "friction", [0.7, 0.5]),
    (GRASP_PROFILE, "stiffness_n_per_m", 120.0),
    (GRASP_PROFILE, "mass_kg", 0.2),
]


@pytest.mark.parametrize(("path", "name", "value"), NUMBERS, ids=lambda x: getattr(x, "stem", x))
def test_a_number_writes_its_slots_in_the_running_call_and_binds_nothing(
    path, name, value, monkeypatch
):
    loop = _loop(path)
    _tick(loop)
    call = loop.renderer.one_call
    builds = Builds(monkeypatch)
    _set(loop, name, value)
    _tick(loop)
    # No plan, no new call, no bind: in the submitting thread, at the boundary or the tick.
    assert builds.count == 0
    assert loop.renderer.one_call is call and call._frame is loop.frame
    assert loop.param(name) == pytest.approx(value)
    # The slots hold what a bind of the changed scene writes, nowhere else differs.
    set_by_slots = _without_tick_work(call)
    monkeypatch.undo()
    call._bind(loop.frame)
    np.testing.assert_array_equal(set_by_slots, _without_tick_work(call))
    p = call._params
    if name == "stiffness_n_per_m":
        assert p[kn.TICK_FORCES_AT] == value and float(loop.frame.stiffness_n_per_m) == value
    if name == "mass_kg":
        assert float(loop.frame.mass_kg) == value


def test_the_next_tick_renders_the_stiffness_set():
    loop = _loop(GRASP_PROFILE)
    k = loop.param("stiffness_n_per_m")
    before = _tick(loop).contact_force.copy()
    assert np.all(np.linalg.norm(before, axis=1) > 0.0)  # both fingers pressing
    _set(loop, "stiffness_n_per_m", 2.0 * k)
    after = _tick(loop).contact_force
    np.testing.assert_allclose(after, 2.0 * before, rtol=1e-12)


def test_a_force_limit_writes_each_fingers_slot_in_the_chains_array(monkeypatch):
    loop = _loop(GRASP_PROFILE)
    arrays = loop.safety.kernel_arrays
    builds = Builds(monkeypatch)
    _set(loop, "force_limit_n", 3.0)
    assert builds.count == 0 and loop.safety.kernel_arrays[0] is arrays[0]
    F = len(loop.safety.rated)
    at = kn.SAFETY_PARAMS + kn.SAFETY_LIMIT * F
    assert arrays[0][at : at + F].tolist() == [3.0] * F == loop.safety.limits


def test_applying_a_number_allocates_nothing():
    loop = _loop(LIFT_PROFILE)
    _tick(loop)
    tracemalloc.start()
    try:
        for name, value in (
            ("stiffness_n_per_m", 300.0),
            ("mass_kg", 0.08),
            ("force_limit_n", 4.0),
        ):
            change = loop.prepare_set(name, value)  # each after the last has landed
            base = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            loop.apply_change(change)
            peak = tracemalloc.get_traced_memory()[1]
            # A bind would allocate its plan and views (kilobytes); a store nothing lasting.
            assert peak - base < 512, (change.name, peak - base)
    finally:
        tracemalloc.stop()
    assert loop.stale_changes == 0


STRUCTURAL = [
    (GRASP_PROFILE, "allocator", "pinv"),
    (LIFT_PROFILE, "allocator", "ef_exact"),
    (GRASP_PROFILE, "actuated_directions", [[[0.8, 0.0, 0.6]], [[-0.8, 0.0, 0.6]]]),
    (GRASP_PROFILE, "friction", [0.8, 0.6]),  # friction turned on: a stage more
    (LIFT_PROFILE, "friction", [0.0, 0.0]),  # and off
]


@pytest.mark.parametrize(
    ("path", "name", "value"), STRUCTURAL, ids=lambda x: getattr(x, "stem", str(x)[:12])
)
def test_a_structural_change_is_made_in_the_submitting_thread_and_swapped_at_a_boundary(
    path, name, value, monkeypatch
):
    loop = _loop(path)
    _tick(loop)
    r = loop.renderer
    old_call, old_stages, old_index = r.one_call, r.stage_names, int(loop.frame.allocator)
    builds = Builds(monkeypatch)
    submitted: list = []
    client = threading.Thread(
        target=lambda: submitted.append(loop.submit(SetParam(name, PARAMS[name].check(value)))),
        name="control client",
    )
    client.start()
    client.join(timeout=30)
    assert submitted and not client.is_alive()
    # Made in the client's thread, once; the running plan untouched until the boundary.
    assert builds.planned == ["control client"] and builds.bound == ["control client"]
    command = loop._inbox[0][0]
    assert r.one_call is old_call and r.stage_names == old_stages
    assert int(loop.frame.allocator) == old_index
    assert loop.param(name) != PARAMS[name].check(value)
    loop._apply_inbox(1, loop.period)
    assert submitted[0].error is None, submitted[0].error
    # The swap: the prepared call, already bound to the loop's frame; nothing built here.
    assert r.one_call is not old_call and r.one_call._frame is loop.frame
    assert (r.one_call, "one_call") == (command.change.attrs[-1][2], command.change.attrs[-1][1])
    assert r.one_call.started == old_call.started
    _tick(loop)
    assert len(builds.planned) == 1 and len(builds.bound) == 1
    assert loop.safety.fault is None and np.isfinite(loop.frame.rendered_force).all()
    if name == "allocator":
        assert r.method == value and int(loop.frame.allocator) != old_index
    elif name == "friction":
        assert ("friction" in r.stage_names) is (value[0] > 0)
    else:
        assert np.allclose(r.actuation.local[0][0], (0.8, 0.0, 0.6))


def test_a_failing_set_changes_nothing_and_queues_nothing():
    loop = _loop(LIFT_PROFILE)
    _tick(loop)
    r = loop.renderer
    before = (r.one_call, r.stage_names, r.obj.material, r.obj.mass, loop.safety.limits)
    plan = r.one_call._plan.copy()
    refused = [
        ("force_limit_n", 9.0, "above the profile's safety.max_force_n"),
        ("actuated_directions", [[[1.0, 0, 0], [0, 0, 1.0]], [[-1.0, 0, 0]]], "must stay"),
        ("allocator", "nope", "unknown allocator"),
        ("mass_kg", 5e-324, "at least"),
    ]
    for name, value, why in refused:
        with pytest.raises(ValueError, match=why):
            loop.submit(SetParam(name, value))
        assert not loop._inbox
        assert (r.one_call, r.stage_names, r.obj.material, r.obj.mass, loop.safety.limits) == before
        np.testing.assert_array_equal(r.one_call._plan, plan)


def test_a_change_prepared_before_another_landed_is_prepared_again_at_its_boundary():
    loop = _loop(GRASP_PROFILE)
    _tick(loop)
    first = loop.submit(SetParam("allocator", "pinv"))
    second = loop.submit(SetParam("stiffness_n_per_m", 90.0))  # against the old call
    loop._apply_inbox(1, loop.period)
    assert first.error is None and second.error is None
    assert loop.stale_changes == 1
    r = loop.renderer
    assert r.method == "pinv" and r.obj.material.stiffness == 90.0
    assert r.one_call._params[kn.TICK_FORCES_AT] == 90.0


@pytest.fixture(scope="module")
def compiled():
    """The renderer's kernels, compiled (loaded from the run's cache)."""
    return jit.compile_kernels(list(Renderer.kernel_names))


def _lift_with_sets(kernels: dict | None) -> np.ndarray:
    loop = _loop(LIFT_PROFILE)
    if kernels is not None:
        loop.renderer.use_kernels({n: kernels[n] for n in Renderer.kernel_names})
    sets = {
        20: ("stiffness_n_per_m", 300.0),
        40: ("mass_kg", 0.08),
        60: ("allocator", "if"),
        80: ("friction", [0.6, 0.4]),
        100: ("damping_n_s_per_m", 1.0),
    }
    out = []
    for k in range(120):
        if k in sets:
            _set(loop, *sets[k], k=k)
        squeeze = 0.002 + 0.001 * np.sin(k / 10.0)  # a squeeze that varies
        pos = SQUEEZE + np.array([[-squeeze, 0, 0.0005 * k], [squeeze, 0, 0.0005 * k]])
        frame = _tick(loop, pos)
        out.append(np.concatenate([frame.rendered_force.ravel(), frame.object_pos]))
    assert loop.stale_changes == 0
    return np.array(out)


def test_sets_on_compiled_and_python_kernels_render_alike(compiled):
    python = _lift_with_sets(None)
    fast = _lift_with_sets(compiled)
    assert np.abs(python).max() > 0.0
    np.testing.assert_allclose(fast, python, rtol=1e-9, atol=1e-12)
