"""Contact's one source (hapticd.kernels.contact_step) compiled against the same function
uncompiled, through the Contact stage: the same bits in every output field and in the
proxies, tick after tick, for generated boxes (turned, moving between ticks), grounds and
walls, fingers inside, outside, at edges and corners, fast ones and first ticks; a large
mesh (stage by stage and in the renderer's one call); a non-finite input refused by name
with nothing written (in the one call too); hostile device positions end in zero force
and a latched fault."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hapticd import jit, kernels
from hapticd.actuation import Actuation
from hapticd.daemon.session import build_session
from hapticd.frame import Frame
from hapticd.profile import load_profile
from hapticd.render import Renderer
from hapticd.scene import ConvexShape, Material, Scene, SceneObject, Surface
from hapticd.stages import Contact
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


@pytest.fixture(scope="module")
def compiled():
    """The compiled contact kernel (numba is a dependency: no skip without it)."""
    return jit.compile_kernels(["contact_step"])["contact_step"]


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


def _run(case: dict, kernel) -> list[dict[str, np.ndarray]]:
    """Every tick's outputs and proxies of a Contact stage (``kernel`` None: uncompiled)."""
    obj = SceneObject(
        ConvexShape.box(case["size"]), Material(500.0), case["center"], case["R"], fixed=False
    )
    scene = Scene(obj, list(case["surfaces"]), None)
    stage = Contact(scene, list(case["radii"]), kernel)
    n = len(case["radii"])
    frame = Frame(n, n)
    out = []
    for pos, vel, move in case["ticks"]:
        if move is not None:
            obj.position = obj.position + move[0]
            obj.rotation = move[1] @ obj.rotation
            obj.update_world()
        frame.device_pos[...] = pos
        frame.device_vel[...] = vel
        # Yesterday's numbers: a path that forgets to write a field is caught.
        for name in OUTPUTS:
            getattr(frame, name)[...] = 7
        stage.run(frame)
        got = {name: getattr(frame, name).copy() for name in OUTPUTS}
        got["state"] = stage.state[:, : kernels._C_PUSHED].copy()
        out.append(got)
    return out


def _assert_same(ref: list[dict], got: list[dict]) -> None:
    assert len(ref) == len(got)
    for tick, (a, b) in enumerate(zip(ref, got, strict=True)):
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"tick {tick}: {name}")


@given(contact_cases())
def test_the_compiled_contact_equals_the_uncompiled_bit_for_bit(compiled, case):
    """One source: numba neither fuses multiply-adds nor reorders without fastmath, and
    sqrt is correctly rounded; the proxies, active planes and multipliers too."""
    _assert_same(_run(case, None), _run(case, compiled))


def test_the_cases_reach_contacts_creases_and_surfaces(compiled):
    """The generated cases are not all out of contact: over 150 derandomized ones, fingers
    touch the object, the surfaces, and both at once (a crease between obstacles)."""
    seen: set[str] = set()

    @settings(max_examples=150, derandomize=True, database=None)
    @given(contact_cases())
    def collect(case):
        for tick in _run(case, compiled):
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


def _edge_case(kernel, device: list) -> Contact:
    obj = SceneObject(ConvexShape.box(np.full(3, 0.05)), Material(500.0), np.zeros(3), np.eye(3))
    ground = Surface("ground", (0.0, 0.0, 1.0), -0.025, Material(1000.0, 5.0))
    return Contact(Scene(obj, [ground], None), [0.008], kernel), obj


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
def test_hand_made_paths_give_the_same_bits_both_ways(compiled, path):
    outs = []
    for kernel in (None, compiled):
        stage, _ = _edge_case(kernel, path)
        frame = Frame(1, 1)
        ticks = []
        for p in path:
            frame.device_pos[0] = p
            frame.device_vel[0] = (0.1, -0.2, -0.3)
            stage.run(frame)
            ticks.append({name: getattr(frame, name).copy() for name in OUTPUTS})
        outs.append(ticks)
    _assert_same(*outs)
    assert any(t["in_contact"][0] for t in outs[0])


@pytest.mark.parametrize("mode", ["compiled", "uncompiled"])
@pytest.mark.parametrize(
    ("field", "where"),
    [("device_pos", 0), ("device_pos", 2), ("device_vel", 1), ("radius", 0), ("plane", 0)],
)
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_non_finite_input_is_refused_by_name_with_nothing_written(
    compiled, mode, field, where, bad
):
    """The stage raises ValueError naming the finger and field (or the obstacle); the frame
    and the proxies are as they were, and a finite tick after goes on from them as if the
    bad one had never come."""
    stage, obj = _edge_case(compiled if mode == "compiled" else None, [])
    ref, _ = _edge_case(compiled, [])
    frame, rframe = Frame(1, 1), Frame(1, 1)
    for p in [(0.06, 0.0, 0.0), (0.02, 0.0, 0.0)]:
        for s, f in ((stage, frame), (ref, rframe)):
            f.device_pos[0] = p
            s.run(f)
    before = {name: getattr(frame, name).copy() for name in OUTPUTS}
    state = stage.state.copy()
    if field == "radius":
        stage.state[0, kernels._C_RADIUS] = bad
        want = "finger 0's radius is not finite"
    elif field == "plane":
        shape = obj.shape
        obj.shape = dataclasses.replace(shape, offsets=np.full(6, bad))
        obj.update_world()
        want = "a plane of the object is not finite"
    else:
        getattr(frame, field)[0, where] = bad
        want = f"finger 0's {field} is not finite"
    with pytest.raises(ValueError, match=f"^contact: {want}"):
        stage.run(frame)
    for name in OUTPUTS:
        np.testing.assert_array_equal(getattr(frame, name), before[name])
    if field != "radius":
        np.testing.assert_array_equal(stage.state, state)
    # Put right: the next tick is the reference's.
    stage.state[0, kernels._C_RADIUS] = 0.008
    if field == "plane":
        obj.shape = shape
        obj.update_world()
    for s, f in ((stage, frame), (ref, rframe)):
        f.device_pos[0] = (0.015, 0.001, 0.0)
        f.device_vel[0] = 0.0
        s.run(f)
    for name in OUTPUTS:
        np.testing.assert_array_equal(getattr(frame, name), getattr(rframe, name))


@pytest.mark.parametrize("mode", ["compiled", "uncompiled"])
def test_a_non_finite_surface_is_named(compiled, mode):
    obj = SceneObject(ConvexShape.box(np.full(3, 0.05)), Material(500.0), np.zeros(3), np.eye(3))
    wall = Surface("wall", (1.0, 0.0, 0.0), math.inf, Material(1000.0))
    stage = Contact(Scene(obj, [wall], None), [0.008], compiled if mode == "compiled" else None)
    with pytest.raises(ValueError, match=r"^contact: a plane of surface 'wall' is not finite"):
        stage.run(Frame(1, 1))


def test_a_non_finite_first_tick_starts_the_proxies_at_the_next_one(compiled):
    stage, _ = _edge_case(compiled, [])
    frame = Frame(1, 1)
    frame.device_pos[0] = (math.nan, 0.0, 0.0)
    with pytest.raises(ValueError, match="finger 0's device_pos"):
        stage.run(frame)
    frame.device_pos[0] = (0.0, 0.0, 0.1)
    stage.run(frame)
    np.testing.assert_array_equal(frame.proxy_pos[0], [0.0, 0.0, 0.1])


def test_a_large_mesh_runs_on_the_kernel_both_ways(compiled):
    """Any number of planes per obstacle: a 1000-sided prism, compiled and not alike."""
    k = 1000
    angles = np.linspace(0.0, 2.0 * np.pi, k, endpoint=False)
    normals = np.stack([np.cos(angles), np.sin(angles), np.zeros(k)], axis=1)
    outs = []
    for kernel in (None, compiled):
        stage, obj = _edge_case(kernel, [])
        obj.shape = dataclasses.replace(obj.shape, normals=normals, offsets=np.full(k, 0.02))
        obj.update_world()
        frame = Frame(1, 1)
        ticks = []
        for x in [(0.04, 0.0, 0.0), (0.015, 0.002, 0.0), (0.0, 0.015, 0.01), (-0.02, 0.0, 0.0)]:
            frame.device_pos[0] = x
            stage.run(frame)
            ticks.append({name: getattr(frame, name).copy() for name in OUTPUTS})
        outs.append(ticks)
        # Slid over the fine faces to the one nearest the device (within a face's angle),
        # the device projected onto it (28 mm out).
        assert ticks[1]["in_contact"][0] == 1
        n = ticks[1]["contact_normal"][0]
        u = np.array([0.015, 0.002, 0.0]) / math.hypot(0.015, 0.002)
        assert n @ u > math.cos(2.0 * math.pi / k)
        assert n @ ticks[1]["surface_point"][0] == pytest.approx(0.028, abs=1e-12)
    _assert_same(*outs)


@pytest.mark.parametrize("path", [LIFT, GRASP], ids=["lift", "grasp"])
def test_the_bundled_profiles_render_their_contact_with_the_kernel(compiled, path):
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

        def read(frame, k, t, _read=bank.read):
            _read(frame, k, t)
            if loop.now() >= 1.0:
                frame.device_pos[0] = value

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
def test_hostile_device_positions_end_in_zero_force_and_a_fault_on_the_compiled_path(
    compiled, path, value
):
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
def test_hostile_positions_past_the_device_bank_fault_alike_both_ways(compiled, path, value):
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
    compiled: the plan runs as one call (hapticd.render.OneCall), counted in ``calls``."""
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
