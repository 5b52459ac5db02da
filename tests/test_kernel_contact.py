"""Contact's one source (hapticd.physics.kernels.contact_step, the Contact stage's part of the
tick's one call) compiled against the same call uncompiled: the same bits in every output field
and in the proxies, tick after tick, for generated boxes (turned, moved between ticks),
grounds and walls, fingers inside, outside, at edges and corners, fast ones and first
ticks; a large mesh (in one call and in parts); a non-finite input refused by name with
nothing written; the object's planes at its pose (kernels.world_planes) are its polytope's,
every bit; hostile device positions end in zero force and a latched fault."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hapticd.allocation.actuation import Actuation
from hapticd.daemon.session import build_session
from hapticd.physics import jit, kernels
from hapticd.physics.frame import Frame
from hapticd.physics.render import Renderer
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject, Surface
from hapticd.profile import load_profile
from tests import ticks
from tests.conftest import ROOT
from tests.strategies import unit_vectors
from tests.test_dynamics import floats, rotations, vec

LIFT = ROOT / "configs" / "lift-weight.yaml"
GRASP = ROOT / "configs" / "grasp-stiffness.yaml"
OUTPUTS = (
    "proxy_pos",
    "in_contact",
    "surface_point",
    "contact_point",
    "contact_normal",
    "env_force",
)


@st.composite
def finger_points(draw, center: np.ndarray, R: np.ndarray, half: np.ndarray) -> np.ndarray:
    """A fingertip centre near the box: on a face, edge or corner's side (each axis -1, 0
    or +1 of the half size, scaled 0.5-1.3: inside to outside), plus a few mm."""
    signs = np.array([draw(st.sampled_from([-1.0, 0.0, 1.0])) for _ in range(3)])
    scale = draw(st.sampled_from([1.0]) | floats(0.5, 1.3))
    noise = draw(st.just(np.zeros(3)) | vec(-0.004, 0.004))
    return center + R @ (signs * half * scale) + noise


@st.composite
def contact_cases(draw) -> dict:
    """A box (2-8 cm, turned), surfaces (none, a ground, walls: their planes sometimes
    flush with or nearly parallel to the box's faces), 1-3 fingers (radius 0-12 mm) and
    2-8 ticks of device positions and velocities; between ticks the box may move (a free
    object's new polytope)."""
    size = draw(vec(0.02, 0.08))
    half = 0.5 * size
    R = draw(rotations() | st.just(np.eye(3)))
    center = draw(vec(-0.03, 0.03))
    surfaces = []
    for name in draw(st.sampled_from([(), ("ground",), ("ground", "wall"), ("wall", "wall")])):
        if draw(st.booleans()):  # along one of the box's faces, flush or a little off
            axis = draw(st.integers(0, 2))
            sign = draw(st.sampled_from([1.0, -1.0]))
            normal = -sign * R[:, axis] + draw(
                st.sampled_from([0.0, 1e-9]) | floats(0.0, 1e-4)
            ) * draw(unit_vectors())
            normal = normal / np.linalg.norm(normal)
            face = center + sign * half[axis] * R[:, axis]
            offset = float(normal @ face) + draw(st.sampled_from([0.0]) | floats(-0.003, 0.003))
        else:
            normal = draw(unit_vectors())
            offset = float(normal @ center) - draw(floats(0.0, 0.06))
        mat = Material(draw(floats(100.0, 5000.0)), draw(floats(0.0, 20.0)))
        surfaces.append(Surface(name, tuple(float(x) for x in normal), offset, mat))
    n_fingers = draw(st.integers(1, 3))
    radii = [draw(st.sampled_from([0.0, 0.008]) | floats(0.0, 0.012)) for _ in range(n_fingers)]
    ticks = []
    for _ in range(draw(st.integers(2, 8))):
        pos = [draw(finger_points(center, R, half)) for _ in range(n_fingers)]
        vel = [draw(vec(-1.0, 1.0)) for _ in range(n_fingers)]
        move = None
        if draw(st.integers(0, 3)) == 0:  # the object moved (and turned) before this tick
            move = (draw(vec(-0.01, 0.01)), draw(rotations()))
        ticks.append((pos, vel, move))
    return {
        "size": size,
        "R": R,
        "center": center,
        "surfaces": surfaces,
        "radii": radii,
        "ticks": ticks,
    }


def _run(case: dict, mode: str) -> list[dict[str, np.ndarray]]:
    """Every tick's outputs and proxies of the one call (``mode``: compiled or not)."""
    obj = SceneObject(ConvexShape.box(case["size"]), Material(500.0), case["center"], case["R"])
    r = ticks.renderer(Scene(obj, list(case["surfaces"]), None), list(case["radii"]), mode)
    contact = ticks.stage(r, "contact")
    frame = r.frame
    out = []
    for pos, vel, move in case["ticks"]:
        if move is not None:
            obj.position = obj.position + move[0]
            obj.rotation = move[1] @ obj.rotation
        # Yesterday's numbers: a path that forgets to write a field is caught.
        for name in OUTPUTS:
            getattr(frame, name)[...] = 7
        r.step(np.array(pos), np.array(vel))
        got = {name: getattr(frame, name).copy() for name in OUTPUTS}
        got["state"] = contact.state[:, : kernels._C_PUSHED].copy()
        out.append(got)
    return out


def _assert_same(ref: list[dict], got: list[dict]) -> None:
    assert len(ref) == len(got)
    for tick, (a, b) in enumerate(zip(ref, got, strict=True)):
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"tick {tick}: {name}")


@given(contact_cases())
def test_the_compiled_contact_equals_the_uncompiled_bit_for_bit(case):
    """One source: numba neither fuses multiply-adds nor reorders without fastmath, and
    sqrt is correctly rounded; the proxies, active planes and multipliers too."""
    _assert_same(_run(case, "uncompiled"), _run(case, "compiled"))


def test_the_cases_reach_contacts_creases_and_surfaces():
    """The generated cases are not all out of contact: over 150 derandomized ones, fingers
    touch the object, the surfaces, and both at once (a crease between obstacles)."""
    seen: set[str] = set()

    @settings(max_examples=150, derandomize=True, database=None)
    @given(contact_cases())
    def collect(case):
        for tick in _run(case, "compiled"):
            on_object = tick["in_contact"] != 0
            on_surface = np.any(tick["env_force"] != 0.0, axis=1)
            if np.any(on_object):
                seen.add("object")
            if np.any(on_surface):
                seen.add("surface")
            if np.any(on_object & on_surface):
                seen.add("both")

    collect()
    assert seen == {"object", "surface", "both"}


def _edge_case(mode: str) -> tuple[Renderer, SceneObject]:
    """A fixed 5 cm cube on the ground, one 8 mm fingertip, the one call compiled or not."""
    obj = SceneObject(ConvexShape.box(np.full(3, 0.05)), Material(500.0), np.zeros(3), np.eye(3))
    ground = Surface("ground", (0.0, 0.0, 1.0), -0.025, Material(1000.0, 5.0))
    return ticks.renderer(Scene(obj, [ground], None), [0.008], mode), obj


def _step(r: Renderer, pos, vel=(0.0, 0.0, 0.0)) -> Frame:
    return r.step(np.array([pos], dtype=float), np.array([vel], dtype=float))


@pytest.mark.parametrize(
    "path",
    [
        # Into the crease between the box's side and the ground: two obstacles' planes.
        [(0.05, 0.0, -0.01), (0.03, 0.0, -0.03)],
        # Into a corner of the box from outside, fast (one tick).
        [(0.06, 0.06, 0.06), (0.02, 0.02, 0.02)],
        # Along an edge and through the box's middle.
        [(0.0, 0.04, 0.04), (0.0, 0.02, 0.03), (0.0, 0.0, 0.0), (0.0, -0.04, 0.0)],
        # A first tick deep inside, then out.
        [(0.001, 0.002, 0.0), (0.1, 0.0, 0.0)],
    ],
)
def test_hand_made_paths_give_the_same_bits_both_ways(path):
    outs = []
    for mode in ticks.MODES:
        r, _ = _edge_case(mode)
        out = []
        for p in path:
            frame = _step(r, p, (0.1, -0.2, -0.3))
            out.append({name: getattr(frame, name).copy() for name in OUTPUTS})
        outs.append(out)
    _assert_same(*outs)
    assert any(t["in_contact"][0] for t in outs[0])


@pytest.mark.parametrize("mode", ticks.MODES)
@pytest.mark.parametrize(
    ("field", "where"),
    [("device_pos", 0), ("device_pos", 2), ("device_vel", 1), ("radius", 0), ("plane", 0)],
)
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_non_finite_input_is_refused_by_name_with_nothing_written(mode, field, where, bad):
    """The call raises ValueError naming the finger and field (or the obstacle); the frame
    and the proxies are as they were, and a finite tick after goes on from them as if the
    bad one had never come."""
    r, obj = _edge_case(mode)
    ref, _ = _edge_case("compiled")
    contact = ticks.stage(r, "contact")
    for p in [(0.06, 0.0, 0.0), (0.02, 0.0, 0.0)]:
        _step(r, p)
        _step(ref, p)
    before = {name: getattr(r.frame, name).copy() for name in OUTPUTS}
    state = contact.state.copy()
    pos, vel = np.array([[0.02, 0.0, 0.0]]), np.zeros((1, 3))
    if field == "radius":
        contact.state[0, kernels._C_RADIUS] = bad
        want = "finger 0's radius is not finite"
    elif field == "plane":
        shape = obj.shape
        obj.shape = dataclasses.replace(shape, offsets=np.full(6, bad))
        r.plan()  # a new shape: the call binds it
        want = "a plane of the object is not finite"
    else:
        (pos if field == "device_pos" else vel)[0, where] = bad
        want = f"finger 0's {field} is not finite"
    with pytest.raises(ValueError, match=f"^contact: {want}"):
        r.step(pos, vel)
    for name in OUTPUTS:
        np.testing.assert_array_equal(getattr(r.frame, name), before[name])
    if field != "radius":
        np.testing.assert_array_equal(contact.state, state)
    # Put right: the next tick is the reference's.
    contact.state[0, kernels._C_RADIUS] = 0.008
    if field == "plane":
        obj.shape = shape
        r.plan()
    for s in (r, ref):
        _step(s, (0.015, 0.001, 0.0))
    for name in OUTPUTS:
        np.testing.assert_array_equal(getattr(r.frame, name), getattr(ref.frame, name))


@pytest.mark.parametrize("mode", ticks.MODES)
def test_a_non_finite_surface_is_named(mode):
    obj = SceneObject(ConvexShape.box(np.full(3, 0.05)), Material(500.0), np.zeros(3), np.eye(3))
    wall = Surface("wall", (1.0, 0.0, 0.0), math.inf, Material(1000.0))
    r = ticks.renderer(Scene(obj, [wall], None), [0.008], mode)
    with pytest.raises(ValueError, match=r"^contact: a plane of surface 'wall' is not finite"):
        _step(r, (0.0, 0.0, 0.1))


@pytest.mark.parametrize("mode", ticks.MODES)
def test_a_non_finite_first_tick_starts_the_proxies_at_the_next_one(mode):
    r, _ = _edge_case(mode)
    with pytest.raises(ValueError, match="finger 0's device_pos"):
        _step(r, (math.nan, 0.0, 0.0))
    frame = _step(r, (0.0, 0.0, 0.1))
    np.testing.assert_array_equal(frame.proxy_pos[0], [0.0, 0.0, 0.1])


def test_a_large_mesh_runs_in_the_call_both_ways():
    """Any number of planes per obstacle: a 1000-sided prism, compiled and not alike."""
    k = 1000
    angles = np.linspace(0.0, 2.0 * np.pi, k, endpoint=False)
    normals = np.stack([np.cos(angles), np.sin(angles), np.zeros(k)], axis=1)
    outs = []
    for mode in ticks.MODES:
        r, obj = _edge_case(mode)
        obj.shape = dataclasses.replace(obj.shape, normals=normals, offsets=np.full(k, 0.02))
        r.plan()
        out = []
        for x in [(0.04, 0.0, 0.0), (0.015, 0.002, 0.0), (0.0, 0.015, 0.01), (-0.02, 0.0, 0.0)]:
            frame = _step(r, x)
            out.append({name: getattr(frame, name).copy() for name in OUTPUTS})
        outs.append(out)
        # Slid over the fine faces to the one nearest the device (within a face's angle),
        # the device projected onto it (28 mm out).
        assert out[1]["in_contact"][0] == 1
        n = out[1]["contact_normal"][0]
        u = np.array([0.015, 0.002, 0.0]) / math.hypot(0.015, 0.002)
        assert n @ u > math.cos(2.0 * math.pi / k)
        assert n @ out[1]["surface_point"][0] == pytest.approx(0.028, abs=1e-12)
    _assert_same(*outs)


@given(
    size=vec(0.01, 0.1),
    Q=rotations(),
    R=rotations(),
    position=vec(-0.1, 0.1),
    extra=st.lists(unit_vectors(), max_size=4),
    path=st.lists(vec(-0.15, 0.15), min_size=2, max_size=4),
)
def test_the_objects_planes_at_its_pose_are_its_polytopes_bit_for_bit(
    size, Q, R, position, extra, path
):
    """The call puts the object's planes at its pose itself (kernels.world_planes, compiled
    in): the same planes, every bit, as its polytope (SceneObject.polytope: the same
    function on floats), which the bring-up and the analysis read. An object at any pose (a
    box turned in its body frame, with extra faces) renders exactly as one whose shape is
    that polytope at the origin, unturned. (Uncompiled, the same bits: the cases above.)"""
    box = ConvexShape.box(size)
    normals = np.vstack([box.normals @ Q.T, np.array(extra).reshape(-1, 3)])
    offsets = np.concatenate([box.offsets, np.full(len(extra), 0.01)])
    shape = ConvexShape(normals, offsets, box.vertices, box.volume, box.inertia_unit_mass)
    posed = SceneObject(shape, Material(200.0), position, R)
    poly = posed.polytope
    world = dataclasses.replace(shape, normals=poly.normals, offsets=poly.offsets)
    placed = SceneObject(world, Material(200.0), np.zeros(3), np.eye(3))
    outs = []
    for obj in (posed, placed):
        r = ticks.renderer(Scene(obj, [], None), [0.004], "compiled")
        out = []
        for x in path:
            frame = _step(r, x + position)
            out.append({name: getattr(frame, name).copy() for name in (*OUTPUTS, "contact_force")})
        outs.append(out)
    _assert_same(*outs)


@pytest.mark.parametrize("path", [LIFT, GRASP], ids=["lift", "grasp"])
def test_the_bundled_profiles_render_their_contact_with_the_kernel(path):
    jit.compile_kernels(list(jit.SIGNATURES))
    s = build_session(
        load_profile(path, ["rendering.kernels=compiled"]), paced=False, duration_s=0.01
    )
    assert s.renderer.one_call._fn is s.renderer.kernels["tick_step"]
    assert "contact" in s.renderer.stage_names and len(s.renderer.one_call._parts) == 1


def _hostile_run(path, mode: str, value: float, where: str) -> tuple[dict, np.ndarray, float, int]:
    """Run ``path`` for 1.2 s with finger 0's position ``value`` (every axis) from 1 s on:
    reported by its device (``where="device"``), or put into the frame's row after the
    device bank read it (``"frame"``: a device layer that let a bad sample through). The
    summary, every force written, the force limit and the number of devices."""
    profile = load_profile(path, [f"rendering.kernels={mode}"])
    session = build_session(profile, paced=False, duration_s=1.2)
    assert ("tick_step" in session.renderer.kernels) == (mode == "compiled")
    loop = session.loop
    if where == "device":
        dev0 = session.devices[0]

        def read_state(st, _read=dev0.read_state):
            _read(st)
            if loop.now() >= 1.0:
                st.position[...] = value

        dev0.read_state = read_state
    else:
        bank = loop.bank

        def read(frame, k, t, defer=False, _read=bank.read):
            # Checked and entered here (not left to the one call's check), then spoiled.
            _read(frame, k, t)
            if loop.now() >= 1.0:
                frame.device_pos[0] = value
            return False

        bank.read = read
    written = []
    for dev in session.devices:

        def write_force(f, _write=dev.write_force):
            written.append(np.array(f, dtype=float))
            _write(f)

        dev.write_force = write_force
    summary = session.run()
    return summary, np.array(written), max(session.safety.limits), len(session.devices)


@pytest.mark.parametrize("value", [math.nan, math.inf, -1e300, 1e6])
@pytest.mark.parametrize("path", [LIFT, GRASP], ids=["lift", "grasp"])
def test_hostile_device_positions_end_in_zero_force_and_a_fault_on_the_compiled_path(path, value):
    """NaN, inf and huge positions from finger 0's device, with the compiled contact: a
    latched fault, every force finite and within the limit, zero at the end."""
    jit.compile_kernels(list(jit.SIGNATURES))
    summary, forces, limit, n = _hostile_run(path, "compiled", value, "device")
    assert np.all(np.isfinite(forces))
    assert np.all(np.linalg.norm(forces, axis=1) <= limit + 1e-12)
    assert summary["fault"] is not None, summary
    assert np.all(forces[-n:] == 0.0)


@pytest.mark.parametrize("value", [math.nan, math.inf, -1e300, 1e6])
@pytest.mark.parametrize("path", [LIFT, GRASP], ids=["lift", "grasp"])
def test_hostile_positions_past_the_device_bank_fault_alike_both_ways(path, value):
    """The same positions put straight into the frame (past the bank's check): every force
    written is finite, within the limit and the uncompiled run's, bit for bit, and so is
    how the run ends; a non-finite one faults the contact stage by name."""
    jit.compile_kernels(list(jit.SIGNATURES))
    summary, forces, limit, n = _hostile_run(path, "compiled", value, "frame")
    ref, ref_forces, _, _ = _hostile_run(path, "python", value, "frame")
    assert np.all(np.isfinite(forces))
    assert np.all(np.linalg.norm(forces, axis=1) <= limit + 1e-12)
    assert summary["fault"] == ref["fault"]
    np.testing.assert_array_equal(forces, ref_forces)
    if not math.isfinite(value):
        assert "contact: finger 0's device_pos is not finite" in summary["fault"]["cause"]
        assert np.all(forces[-n:] == 0.0)


def _one_call_renderer(shape: ConvexShape, calls: list | None = None) -> Renderer:
    """A fixed frictionless object of ``shape`` on the ground, two fingers, IF, every kernel
    compiled: the plan runs as one call (hapticd.physics.render.OneCall), counted in ``calls``."""
    obj = SceneObject(shape, Material(500.0), np.zeros(3), np.eye(3))
    ground = Surface("ground", (0.0, 0.0, 1.0), -0.03, Material(1000.0, 5.0))
    r = Renderer(Scene(obj, [ground], None), [0.008] * 2, Actuation([[(1.0, 0, 0)]] * 2), "if")
    fns = jit.compile_kernels(r.kernel_names)
    if calls is not None:
        tick = fns["tick_step"]

        def counted(*args):
            outcome = tick(*args)
            calls.append(outcome)
            return outcome

        fns["tick_step"] = counted
    r.use_kernels(fns)
    assert r.one_call is not None
    return r


def test_the_one_call_refuses_a_non_finite_sample_by_name_and_goes_on():
    r = _one_call_renderer(ConvexShape.box(np.full(3, 0.05)))
    ref = _one_call_renderer(ConvexShape.box(np.full(3, 0.05)))
    pos = np.array([[-0.03, 0.0, 0.0], [0.03, 0.0, 0.0]])
    for x in (pos * 2.0, pos):
        r.step(x, np.zeros((2, 3)))
        ref.step(x, np.zeros((2, 3)))
    bad = pos.copy()
    bad[1, 2] = math.nan
    with pytest.raises(ValueError, match=r"^contact: finger 1's device_pos is not finite"):
        r.step(bad, np.zeros((2, 3)))
    a = r.step(pos * 0.99, np.zeros((2, 3)))
    b = ref.step(pos * 0.99, np.zeros((2, 3)))
    for name in (*OUTPUTS, "contact_force", "rendered_force"):
        np.testing.assert_array_equal(a.get(name), b.get(name), err_msg=name)
    assert np.all(a.in_contact == 1)


def test_a_large_mesh_runs_in_the_one_call():
    """A 1000-sided prism (any number of planes): in one call, tick after tick, the same
    forces as the plan in parts (a stage inserted after contact)."""
    k = 1000
    angles = np.linspace(0.0, 2.0 * np.pi, k, endpoint=False)
    normals = np.stack([np.cos(angles), np.sin(angles), np.zeros(k)], axis=1)
    prism = dataclasses.replace(
        ConvexShape.box(np.full(3, 0.05)), normals=normals, offsets=np.full(k, 0.02)
    )
    calls: list[int] = []
    one = _one_call_renderer(prism, calls)
    staged = _one_call_renderer(prism)
    staged.insert(Nothing(), after="contact")  # a plan with an inserted stage: in parts
    assert len(staged.one_call._parts) == 3
    for s in np.linspace(0.0, 1.0, 20):
        x = np.array([[-0.03 + 0.01 * s, 0.003 * s, 0.0], [0.03 - 0.01 * s, 0.0, -0.002 * s]])
        a, b = one.step(x, np.zeros((2, 3))), staged.step(x, np.zeros((2, 3)))
        for name in (*OUTPUTS, "contact_force", "rendered_force"):
            np.testing.assert_array_equal(a.get(name), b.get(name), err_msg=name)
    assert calls == [kernels.TICK_DONE] * 20 and np.all(a.in_contact == 1)


class Nothing:
    """A stage that reads and writes nothing."""

    name = "nothing"
    reads: tuple[str, ...] = ()
    writes: tuple[str, ...] = ()

    def run(self, frame: Frame) -> None:
        pass
