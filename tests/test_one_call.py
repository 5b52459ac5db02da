"""The renderer's plan as one call per tick (hapticd.physics.render.OneCall,
hapticd.physics.kernels.tick_step) against the same plan in parts (a probe stage inserted after
every stage, so that the call runs each stage as a part of its own): the same frame, tick after
tick, for the bundled profiles' scenes, a free object pushed onto the ground, three fingers, the
adaptive allocator and a material set between ticks; three and five fingers holding a cube run
every tick as one call, their forces allocate()'s; the environment's and the passivity
controller's forces against their definitions (a projector onto the span of the actuated
directions, hapticd.physics.passivity's observer and controller).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from hapticd.allocation.actuation import Actuation
from hapticd.allocation.robust import AllocationError
from hapticd.daemon.build import build_renderer, load_trajectories
from hapticd.physics import jit
from hapticd.physics import kernels as kn
from hapticd.physics.frame import FIELDS, Frame
from hapticd.physics.passivity import PassivityParams
from hapticd.physics.render import Renderer
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject, Surface
from hapticd.profile import load_profile
from tests.conftest import ROOT, our_code_filters

COMPARED = [f.name for f in FIELDS if f.name not in ("t", "t_wall", "compute_s", "tick")]


@pytest.fixture(scope="module")
def compiled():
    """Every kernel the renderers below name, compiled (loaded from the run's cache)."""
    return jit.compile_kernels(list(jit.SIGNATURES))


class Probe:
    """A stage that does nothing: inserted after a stage, it splits the call there."""

    def __init__(self, after: str) -> None:
        self.name = f"probe {after}"
        self.runs = 0

    def run(self, frame) -> None:
        self.runs += 1


def _in_parts(r: Renderer) -> Renderer:
    """``r``'s plan with a probe after every stage: the call runs each stage on its own."""
    for name in r.stage_names:
        r.insert(Probe(name), after=name)
    return r


def _pair(make, kernels):
    one, parts = make(), make()
    one.use_kernels(kernels)
    parts.use_kernels(kernels)
    return one, _in_parts(parts)


def _same(
    one: Renderer, staged: Renderer, pos: np.ndarray, vel: np.ndarray, k: int, skip=(), atol=0.0
) -> None:
    a = one.step(pos, vel)
    b = staged.step(pos, vel)
    for name in (n for n in COMPARED if n not in skip):
        np.testing.assert_allclose(
            a.get(name), b.get(name), rtol=0, atol=atol, err_msg=f"{name} at tick {k}"
        )


@pytest.mark.parametrize("profile", ["lift-weight", "grasp-stiffness"])
def test_the_bundled_profiles_render_the_same_in_one_call(profile, compiled):
    """Bit for bit: each stage's part runs the same code on the same numbers."""
    prof = load_profile(ROOT / "configs" / f"{profile}.yaml", ["rendering.passivity.enabled=true"])
    kernels = {n: compiled[n] for n in build_renderer(prof).kernel_names}
    assert "tick_step" in kernels
    one, staged = _pair(lambda: build_renderer(prof), kernels)
    assert len(one.one_call._parts) == 1
    assert len(staged.one_call._parts) == 2 * len(one.stage_names) + 1
    paths = [p for p in load_trajectories(prof) if p is not None]
    times, pos = paths[0][0], np.stack([p[1] for p in paths], axis=1)
    dt = float(times[1] - times[0])
    touched = 0
    for k in range(0, len(times) - 1, 3):
        vel = (pos[k + 1] - pos[k]) / dt
        _same(one, staged, pos[k], vel, k)
        touched += bool(one.frame.in_contact.any())
    assert touched > 20  # the comparison saw contact, not only free air


def _box(fixed: bool) -> SceneObject:
    return SceneObject(
        ConvexShape.box(np.array([0.04, 0.04, 0.04])),
        Material(400.0, 2.0, 0.6, 0.4, 0.002),
        np.array([0.0, 0.0, 0.02]),
        np.eye(3),
        fixed=fixed,
        mass=0.2,
    )


def _scene(fixed: bool) -> Scene:
    ground = Surface("ground", (0.0, 0.0, 1.0), 0.0, Material(2000.0, 5.0, 0.5, 0.4))
    return Scene(_box(fixed), [ground], np.array([0.0, 0.0, -9.81]), substeps=2)


def _squeeze(n_fingers: int, ticks: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Fingers around the box pressing in and lifting, then one pushing into the ground."""
    angles = np.linspace(0.0, 2 * np.pi, n_fingers, endpoint=False)
    out = []
    for k in range(ticks):
        s = min(1.0, k / (ticks / 2))
        r = 0.035 - 0.01 * s
        pos = np.stack(
            [r * np.cos(angles), r * np.sin(angles), np.full(n_fingers, 0.02 + 0.01 * s)], axis=1
        )
        if k > ticks * 3 // 4:
            pos[0] = (0.1, 0.0, -0.002)  # into the ground, away from the box
        out.append((pos, np.full((n_fingers, 3), 0.01)))
    return out


def _projected(frame: Frame, act: Actuation, force: np.ndarray) -> np.ndarray:
    """``force`` (F, 3) N projected onto the span of each finger's actuated directions in the
    world: D pinv(D) f, the projector's definition."""
    world = act.world_directions(frame.device_pos.tolist())
    out = np.zeros_like(force)
    for i, ds in enumerate(world):
        D = np.array(ds).T
        out[i] = D @ np.linalg.pinv(D) @ force[i]
    return out


@pytest.mark.parametrize("n_fingers", [2, 3])
@pytest.mark.parametrize("fixed", [True, False])
def test_a_grasp_on_the_ground_renders_the_same_in_one_call(n_fingers, fixed, compiled):
    """Friction, the ground's force through the actuated directions (two of them for the
    first finger with two fingers) and their sum, the free body's step, all in the one
    call; with three fingers, ticks with three contacts too. The environment's force is
    its projection."""
    directions = [[(0.6, 0.0, 0.8), (0.0, 1.0, 0.0)], [(0.0, 1.0, 0.0)], [(0.0, 0.6, 0.8)]]
    directions[0] = directions[0][:1] if n_fingers == 3 else directions[0]
    act = Actuation(copy.deepcopy(directions[:n_fingers]), "world")

    def make() -> Renderer:
        return Renderer(_scene(fixed), [0.008] * n_fingers, act, "if", dt=1e-3)

    names = make().kernel_names
    one, staged = _pair(make, {n: compiled[n] for n in names})
    assert "output" in one.stage_names and ("dynamics" in one.stage_names) is not fixed
    assert len(one.one_call._parts) == 1
    contacts = set()
    ground = 0
    for k, (pos, vel) in enumerate(_squeeze(n_fingers, 240)):
        _same(one, staged, pos, vel, k)
        f = one.frame
        contacts.add(int(f.in_contact.sum()))
        assert np.isfinite(f.rendered_force).all()
        expected = _projected(f, act, f.env_force)
        np.testing.assert_allclose(f.env_rendered, expected, rtol=0, atol=1e-12)
        ground += bool(np.abs(f.env_force).max() > 0.01)
    assert max(contacts) == n_fingers and 0 in contacts and ground > 10


def test_an_adaptive_plan_runs_as_one_call_alpha_too(compiled):
    """adaptive's alpha moves inside the call (on the tick's contact forces): the frame,
    alpha included, equals the call in parts tick by tick, through three contacts and
    release."""

    def make() -> Renderer:
        act = Actuation([[(0.6, 0.0, 0.8)], [(0.0, 1.0, 0.0)], [(0.0, 0.6, 0.8)]], "world")
        return Renderer(_scene(False), [0.008] * 3, act, "adaptive", dt=1e-3)

    one, staged = _pair(make, {n: compiled[n] for n in make().kernel_names})
    assert len(one.one_call._parts) == 1
    alphas = []
    for k, (pos, vel) in enumerate(_squeeze(3, 240)):
        _same(one, staged, pos, vel, k)
        alphas.append(float(one.frame.alpha))
    assert max(alphas) > 0.01  # alpha moved


@pytest.mark.parametrize("n_fingers", [3, 5])
def test_many_fingers_run_every_tick_as_one_call_with_allocates_forces(n_fingers, compiled):
    """Fingers closing on a free cube and holding it (every finger in contact): no tick is
    handed back (the safety chain's outcome comes back every tick), and lam_a and the
    allocated force are allocate()'s on the same tick's contacts, with contact onset,
    to 1e-9 N."""
    from hapticd.physics.safety import SafetyChain
    from tests.test_kernel_allocation import _allocate_with_onset

    angles = np.linspace(0.0, 2 * np.pi, n_fingers, endpoint=False)
    dirs = [[(float(-0.8 * np.cos(a)), float(-0.8 * np.sin(a)), 0.6)] for a in angles]
    r = Renderer(_scene(False), [0.008] * n_fingers, Actuation(dirs, "world"), "if", dt=1e-3)
    r.use_kernels({n: compiled[n] for n in r.kernel_names})
    safety = SafetyChain([8.0] * n_fingers, dt=1e-3)
    safety.use_kernels({"safety_step": compiled["safety_step"]})
    safety.start(0.0)
    frame = r.frame
    held = 0
    for k, (pos, _) in enumerate(_squeeze(n_fingers, 200)):
        frame.device_pos[...] = pos
        center = r.obj.position.copy()  # the grasp's reference point: before the dynamics
        frame.t[()] = k * 1e-3
        outcome = r.run(frame, safety if safety.ready() else None)
        assert outcome is not None, f"tick {k} handed back"
        assert safety.done(outcome, k, k * 1e-3, None)
        case = {
            "n": n_fingers,
            "robust": r.allocator.robust,
            "method": "if",
            "frame": "world",
            "local": [np.array(d[0]) for d in dirs],
            "center": center,
            "frame_fields": {
                "in_contact": frame.in_contact.tolist(),
                "device_pos": frame.device_pos.copy(),
                "contact_point": frame.contact_point.copy(),
                "contact_force": frame.contact_force.copy(),
            },
        }
        x, rendered = _allocate_with_onset(case, 0.0)
        np.testing.assert_allclose(frame.lam_a, x, rtol=0, atol=1e-9, err_msg=f"tick {k}")
        np.testing.assert_allclose(frame.allocated_force, rendered, rtol=0, atol=1e-9)
        held += bool(frame.in_contact.all())
    assert held > 20


def test_a_material_set_between_ticks_is_the_next_ticks(compiled):
    """An analysis sets the object's material tick by tick without a new plan."""
    act = Actuation([[(1.0, 0.0, 0.0)], [(-1.0, 0.0, 0.0)]], "world")

    def make() -> Renderer:
        return Renderer(_box(True), [0.008, 0.008], act, "pinv", dt=1e-3)

    one, staged = _pair(make, {n: compiled[n] for n in make().kernel_names})
    pos = np.array([[-0.025, 0.0, 0.02], [0.025, 0.0, 0.02]])
    vel = np.zeros((2, 3))
    _same(one, staged, pos, vel, 0)
    before = one.frame.rendered_force.copy()
    for r in (one, staged):
        r.obj.material = Material(800.0, 2.0, 0.6, 0.4, 0.002)
    _same(one, staged, pos, vel, 1)
    np.testing.assert_allclose(one.frame.rendered_force, 2 * before, rtol=1e-9)
    assert float(one.frame.stiffness_n_per_m) == 800.0


def test_non_finite_inputs_are_refused_by_name(compiled):
    act = Actuation([[(1.0, 0.0, 0.0)], [(-1.0, 0.0, 0.0)]], "world")
    r = Renderer(_box(True), [0.008, 0.008], act, "if", dt=1e-3)
    r.use_kernels({n: compiled[n] for n in r.kernel_names})
    pos = np.array([[-0.025, 0.0, 0.02], [0.025, 0.0, 0.02]])
    r.step(pos, np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"contact: finger 1's device_vel is not finite"):
        r.step(pos, np.array([[0.0, 0.0, 0.0], [0.0, np.nan, 0.0]]))
    r.obj.material = Material(float("inf"))
    with pytest.raises(AllocationError, match="non-finite contact geometry or force"):
        r.step(pos, np.zeros((2, 3)))


def test_every_plan_runs_as_the_call_with_its_python_stages_between_parts(compiled):
    """Allocation by the seed's exact formulas runs between the call's parts; the robust
    methods (on any actuation), adaptive and passivity are in the call."""
    end = kn.STAGE_END
    act = Actuation([[(1.0, 0.0, 0.0), (0.0, 1.0, 0.0)], [(-1.0, 0.0, 0.0)]], "world")
    r = Renderer(_box(True), [0.008, 0.008], act, "if", dt=1e-3)
    r.use_kernels({n: compiled[n] for n in r.kernel_names})
    for method, whole in (("if", True), ("adaptive", True), ("ef_exact", False), ("ef", True)):
        r.set_param("allocator", method)
        r.step(np.zeros((2, 3)), np.zeros((2, 3)))
        assert (len(r.one_call._parts) == 1) is whole, method
        if not whole:
            parts = r.one_call._parts
            assert parts[0] == (kn.STAGE_CONTACT, kn.STAGE_ALLOCATION) and parts[2][1] == end
            assert parts[1].name == "allocation"
    passive = Renderer(
        _box(True), [0.008, 0.008], act, "if", dt=1e-3, passivity=PassivityParams(0.01, 5.0)
    )
    passive.use_kernels({n: compiled[n] for n in passive.kernel_names})
    passive.step(np.zeros((2, 3)), np.zeros((2, 3)))
    assert passive.one_call._parts == [(kn.STAGE_CONTACT, end)]
    assert "passivity" in passive.stage_names


@pytest.mark.parametrize("mode", ["compiled", "python"])
def test_the_passivity_controller_in_the_call_is_its_definition(mode, compiled):
    """Every tick of a lift with passivity (a low threshold, so that it acts), each finger's
    energy, damping and damping force are hapticd.physics.passivity's observer and controller
    (tests.test_passivity.step) on the force before it
    (allocated plus the environment's) and the finger's motion projected onto its actuated
    directions (grasp frame)."""
    from tests import test_passivity as passivity

    over = [
        f"rendering.kernels={mode}",
        "rendering.passivity.enabled=true",
        "rendering.passivity.velocity_threshold_m_per_s=0.001",
    ]
    prof = load_profile(ROOT / "configs" / "lift-weight.yaml", over)
    r = build_renderer(prof)
    if mode == "compiled":
        r.use_kernels({n: compiled[n] for n in r.kernel_names})
    params = r.passivity.params
    paths = [p for p in load_trajectories(prof) if p is not None]
    times, pos = paths[0][0], np.stack([p[1] for p in paths], axis=1)
    dt = r.dt
    energy = np.zeros(2)
    last = None
    acted = 0
    for k in range(len(times) - 1):
        f = r.step(pos[k], (pos[k + 1] - pos[k]) / float(times[1] - times[0]))
        x = f.device_pos.copy()
        dx = np.zeros((2, 3)) if last is None else x - last
        last = x
        before = f.allocated_force + f.env_rendered
        moved = _projected(f, r.actuation, dx)
        for i in range(2):
            e, alpha = passivity.step(
                energy[i], before[i].tolist(), dx[i].tolist(), moved[i].tolist(), dt, params
            )
            energy[i] = e
            assert f.passivity_energy[i] == pytest.approx(e, abs=1e-12, rel=1e-9), (k, i)
            assert f.passivity_damping[i] == pytest.approx(alpha, abs=1e-9, rel=1e-9), (k, i)
            np.testing.assert_allclose(
                f.passivity_force[i], -alpha / dt * moved[i], rtol=1e-9, atol=1e-12
            )
            acted += alpha > 0.0
        np.testing.assert_allclose(f.rendered_force, before + f.passivity_force, rtol=0, atol=1e-15)
    assert acted > 5


def _lift_run(tmp_path, overrides, monkeypatch, in_call: bool):
    """The lift profile's loop, unpaced, recorded; the safety chain's tick in the one call,
    or (the chain never ``ready`` for it) the chain's own call of it (``run``)."""
    from hapticd import recording
    from hapticd.daemon.session import build_session
    from hapticd.physics.safety import SafetyChain

    prof = load_profile(ROOT / "configs" / "lift-weight.yaml", overrides)
    path = tmp_path / f"{in_call}.hrec"
    with monkeypatch.context() as m:
        if not in_call:
            m.setattr(SafetyChain, "ready", lambda self: False)
        s = build_session(prof, paced=False, duration_s=3.0, record_path=path)
        s.run()
    return s.loop.safety, recording.read(path)


def test_the_safety_chain_in_the_call_clamps_and_limits_as_the_chain(tmp_path, monkeypatch):
    """The safety chain's tick made in the one call: the same forces sent, tick by
    tick, and the same counts of clamped and rate-limited ticks, as the chain's own."""
    low = [
        "rendering.kernels=compiled",
        "safety.max_force_n=0.5",
        "safety.max_force_rate_n_per_s=5",
    ]
    (one, a), (chain, b) = (_lift_run(tmp_path, low, monkeypatch, flag) for flag in (True, False))
    assert one.fault is None and chain.fault is None
    assert one.clamped_ticks == chain.clamped_ticks > 100
    assert one.rate_limited_ticks == chain.rate_limited_ticks > 10
    np.testing.assert_array_equal(a["device_force"], b["device_force"])
    assert np.abs(a["device_force"]).max() > 0.1


@pytest.mark.parametrize("profile", ["lift-weight", "grasp-stiffness"])
def test_python_mode_runs_the_same_call_uncompiled(profile, compiled):
    """rendering.kernels=python: the one call is the same function, uncompiled; its ticks
    equal the compiled call's to 1e-9 (N, m; numba may contract and reorder float ops)."""
    prof = load_profile(ROOT / "configs" / f"{profile}.yaml", ["rendering.kernels=python"])
    one, fast = build_renderer(prof), build_renderer(prof)
    assert one.kernels == {}
    fast.use_kernels({n: compiled[n] for n in fast.kernel_names})
    assert (
        one.one_call._fn is kn.uncompiled("tick_step") and fast.one_call._fn is not one.one_call._fn
    )
    paths = [p for p in load_trajectories(prof) if p is not None]
    times, pos = paths[0][0], np.stack([p[1] for p in paths], axis=1)
    dt = float(times[1] - times[0])
    touched = 0
    for k in range(0, len(times) - 1, 40):
        _same(one, fast, pos[k], (pos[k + 1] - pos[k]) / dt, k, atol=1e-9)
        touched += bool(one.frame.in_contact.any())
    assert touched > 5


@pytest.mark.parametrize("path", ["python", "compiled"])
def test_the_call_makes_the_chains_tick_with_its_deadman_ramps_and_trips(path, compiled):
    """A chain with a deadman, the enable ramp, a rate limit and a workspace runs in the one
    call on every tick (the frame's nominal time and buttons), tick by tick as the chain's
    own ``apply`` (uncompiled) on the same forces, positions and buttons: the same bits,
    deadman state and counts. The finger that leaves the workspace trips in the call: zero
    force, and the fault latched with its message at that tick."""
    from hapticd.physics.safety import Deadman, SafetyChain, SafetyParams

    n, ticks = 2, 200
    angles = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    dirs = [[(float(-0.8 * np.cos(a)), float(-0.8 * np.sin(a)), 0.6)] for a in angles]
    r = Renderer(_scene(False), [0.008] * n, Actuation(dirs, "world"), "if", dt=1e-3)
    kernels = compiled if path == "compiled" else {}
    r.use_kernels({k: kernels[k] for k in r.kernel_names} if kernels else {})
    prm = SafetyParams(
        ramp_s=0.02,
        max_rate_n_per_s=100.0,
        workspace_radius_m=0.08,
        deadman=(Deadman(1, 0.01), None),
    )
    chain, ref = SafetyChain([8.0] * n, prm, dt=1e-3), SafetyChain([8.0] * n, prm, dt=1e-3)
    chain.use_kernels(kernels)
    frame = r.frame
    gated = held = 0
    for k, (pos, _) in enumerate(_squeeze(n, ticks)):  # finger 0 leaves at tick 151
        t = k * 1e-3
        frame.device_pos[...] = pos
        frame.t[()], frame.tick[()] = t, k
        frame.buttons[0] = 2 if 30 <= k < 90 or k >= 110 else 1  # finger 0's deadman: bit 1
        outcome = r.run(frame, chain if chain.ready() else None)
        assert (outcome is None) == (chain.fault is not None), k  # latched: the chain's own
        if outcome is None or not chain.done(outcome, k, t, None):
            chain.run(frame, None)
        want = ref.apply(frame.rendered_force, k, t, frame.device_pos, None, frame.buttons)
        assert frame.device_force.tobytes() == want.tobytes(), k
        assert chain.fault == ref.fault and chain.deadman_status() == ref.deadman_status()
        assert chain.kernel_arrays[0].tobytes() == ref.kernel_arrays[0].tobytes(), k
        pushed = np.linalg.norm(frame.device_force, axis=1)
        gated += bool(pushed[0] == 0.0 and pushed[1] > 0.0)
        held += bool(pushed[0] > 0.0)
    assert gated > 10 and held > 10 and chain.rate_limited_ticks > 0
    assert chain.fault.kind == "workspace" and chain.fault.tick == 151
    assert chain.fault.cause.startswith("finger 0 left the workspace: 0.1000 m from its centre")
    assert np.all(frame.device_force == 0.0)


@pytest.mark.parametrize("n_fingers", [2, 5])
def test_the_call_with_the_safety_chain_allocates_nothing_a_tick(n_fingers, compiled):
    """The hot path allocates no Python object a tick: over 500 ticks of a held free cube on
    the ground (every stage, the safety chain's tick in the call; with five fingers the
    general path of allocation and adaptive's alpha), no memory block that hapticd's code
    allocated is left or grew. (numba's own unboxing of each array argument is C memory
    it frees on return, outside Python's allocator.)"""
    import tracemalloc

    from hapticd.physics.safety import SafetyChain

    angles = np.linspace(0.0, 2 * np.pi, n_fingers, endpoint=False)
    dirs = [[(float(-0.8 * np.cos(a)), float(-0.8 * np.sin(a)), 0.6)] for a in angles]
    method = "if" if n_fingers == 2 else "adaptive"
    r = Renderer(_scene(False), [0.008] * n_fingers, Actuation(dirs, "world"), method, dt=1e-3)
    r.use_kernels({n: compiled[n] for n in r.kernel_names})
    safety = SafetyChain([8.0] * n_fingers, dt=1e-3)
    safety.use_kernels({"safety_step": compiled["safety_step"]})
    safety.start(0.0)
    frame = r.frame
    path = _squeeze(n_fingers, 1000)  # every finger holds the cube until tick 750

    def tick(k: int) -> None:
        frame.device_pos[...] = path[k][0]
        frame.t[()] = k * 1e-3
        outcome = r.run(frame, safety if safety.ready() else None)
        assert outcome is not None and safety.done(outcome, k, k * 1e-3, None)

    for k in range(200):
        tick(k)
    tracemalloc.start()
    try:
        before = tracemalloc.take_snapshot()
        for k in range(200, 700):
            tick(k)
        after = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    ours = our_code_filters()[:1]
    grown = [
        d
        for d in after.filter_traces(ours).compare_to(before.filter_traces(ours), "lineno")
        if d.size_diff > 0 or d.count_diff > 0
    ]
    assert not grown, grown
    assert frame.in_contact.all() and np.abs(frame.device_force).max() > 0.1


@pytest.mark.parametrize("profile", ["lift-weight", "grasp-stiffness"])
def test_the_compiled_call_skips_numbas_dispatch_only_on_its_declared_arrays(profile, compiled):
    """``direct``: the call goes straight to the compiled code (no per-call type dispatch)
    only when every argument the renderer bound is exactly the array tick_step's signature
    declares; one argument off in dtype, dimensions, order, writability or class keeps
    numba's dispatcher, which refuses it (no unchecked call on a wrong array). The direct
    call's ticks are the dispatcher's, bit for bit; uncompiled, the function itself."""
    from hapticd.physics.render import direct
    from hapticd.physics.safety import SafetyChain

    prof = load_profile(ROOT / "configs" / f"{profile}.yaml")
    fast, slow = build_renderer(prof), build_renderer(prof)
    fast.use_kernels({n: compiled[n] for n in fast.kernel_names})
    slow.use_kernels({n: compiled[n] for n in slow.kernel_names})
    chains = [SafetyChain([8.0] * fast.n_fingers, dt=1e-3) for _ in range(2)]
    for chain in chains:
        chain.use_kernels({"safety_step": compiled["safety_step"]})
        chain.start(0.0)
    fn = compiled["tick_step"]
    assert direct(kn.uncompiled("tick_step"), ()) is kn.uncompiled("tick_step")
    paths = [p for p in load_trajectories(prof) if p is not None]
    times, pos = paths[0][0], np.stack([p[1] for p in paths], axis=1)
    dt = float(times[1] - times[0])
    touched, most = 0, 0.0
    for k in range(0, len(times) - 1, 5):
        for r, chain in zip((fast, slow), chains, strict=True):
            r.frame.device_pos[...] = pos[k]
            r.frame.device_vel[...] = (pos[k + 1] - pos[k]) / dt
            r.frame.t[()] = k * 1e-3
            assert r.run(r.frame, chain if chain.ready() else None) is not None
        if k == 0:  # bound now, with the chain's arrays: the slow one keeps the dispatcher
            args = fast.one_call._args
            entry = direct(fn, args)
            assert entry is not fn and fast.one_call._call is entry
            slow.one_call._call = fn
        np.testing.assert_array_equal(fast.frame.record, slow.frame.record, err_msg=f"tick {k}")
        touched += bool(fast.frame.in_contact.any())
        most = max(most, float(np.abs(fast.frame.device_force).max()))
    assert touched > 10 and most > 0.1

    class Sub(np.ndarray):
        pass

    for i, a in enumerate(args):
        wrong = [
            a.astype(np.float32 if a.dtype != np.float32 else np.float64),
            a.reshape(-1) if a.ndim > 1 else a.reshape(1, -1),
            a.view(Sub),
        ]
        if a.dtype.itemsize > 1:
            wrong.append(a.astype(a.dtype.newbyteorder()))
        if a.ndim == 1 and a.size > 1:
            wrong.append(np.repeat(a, 2)[::2])  # not contiguous
        ro = a.copy()
        ro.flags.writeable = False
        wrong.append(ro)
        for bad in wrong:
            spoilt = (*args[:i], bad, *args[i + 1 :])
            assert direct(fn, spoilt) is fn, (i, bad.dtype, bad.shape)
            if type(bad) is np.ndarray:  # numba types a subclass as its base
                with pytest.raises(TypeError):
                    fn(*spoilt)
    assert direct(fn, args[:-1]) is fn


def test_a_copied_renderer_goes_on_from_its_own_state():
    """The carried state is one array the stages hold views of: a deep copy (which detaches
    each array) takes its stages' values back into its own array and goes on exactly as the
    original does, without touching the original's."""
    act = Actuation([[(0.6, 0.0, 0.8)], [(0.0, 0.6, 0.8)]], "world")
    passive = PassivityParams(velocity_threshold=0.01, max_damping=5.0)
    r = Renderer(_scene(False), [0.008] * 2, act, "adaptive", dt=1e-3, passivity=passive)
    ticks = _squeeze(2, 120)
    for pos, vel in ticks[:60]:
        r.step(pos, vel)
    twin = copy.deepcopy(r)
    twin.frame = Frame(2, act.n_actuators)  # a frame's copy holds no views of its record
    before = r.state.copy()
    for pos, vel in ticks[60:]:
        twin.step(pos, vel)
    np.testing.assert_array_equal(r.state, before)  # the original's state untouched
    for pos, vel in ticks[60:]:
        r.step(pos, vel)
    np.testing.assert_array_equal(twin.state, r.state)
    np.testing.assert_array_equal(twin.frame.rendered_force, r.frame.rendered_force)
    assert np.shares_memory(twin._contact.state, twin.state)
    assert np.shares_memory(twin.allocator.work, twin.state)
    assert np.abs(r.state).max() > 0
