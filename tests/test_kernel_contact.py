"""The compiled contact kernel (hapticd.kernels.contact_step) against the Contact stage's
Python code: the same bits in every output field and in the proxies, tick after tick, for
generated boxes (turned, moving between ticks), grounds and walls, fingers inside,
outside, at edges and corners, fast ones and first ticks; the cases it does not take run
the Python code on the same proxies; hostile device positions end in zero force and a
latched fault on the compiled path."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hapticd import jit, kernels
from hapticd.contact import _VECTOR_PLANES
from hapticd.daemon.session import build_session
from hapticd.frame import Frame
from hapticd.profile import load_profile
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
    """Every tick's outputs and proxies of a Contact stage (``kernel`` None: Python)."""
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
        # Yesterday's numbers: a path that forgets to write a field is caught (the normals
        # and env_force only before the first tick: the Python code leaves zeros it wrote).
        for name in OUTPUTS if not out else OUTPUTS[:4]:
            getattr(frame, name)[...] = 7
        stage.run(frame)
        got = {name: getattr(frame, name).copy() for name in OUTPUTS}
        got["proxies"] = stage.state[:, :3].copy()
        out.append(got)
    return out


def _assert_same(ref: list[dict], got: list[dict]) -> None:
    assert len(ref) == len(got)
    for tick, (a, b) in enumerate(zip(ref, got, strict=True)):
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"tick {tick}: {name}")


@given(contact_cases())
def test_the_compiled_contact_equals_the_python_stage_bit_for_bit(compiled, case):
    """The kernel evaluates the stage's sums in the same order (numba neither fuses
    multiply-adds nor reorders without fastmath; sqrt is correctly rounded)."""
    _assert_same(_run(case, None), _run(case, compiled))


@given(contact_cases())
def test_the_contact_kernel_as_plain_python_is_the_stage_bit_for_bit(case):
    _assert_same(_run(case, None), _run(case, kernels.contact_step))


def test_the_cases_reach_contacts_creases_and_surfaces():
    """The generated cases are not all out of contact: over 150 derandomized ones, fingers
    touch the object, the surfaces, and both at once (a crease between obstacles)."""
    seen: set[str] = set()

    @settings(max_examples=150, derandomize=True, database=None)
    @given(contact_cases())
    def collect(case):
        for tick in _run(case, None):
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
def test_hand_made_paths_give_the_same_bits(compiled, path):
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


def test_what_the_kernel_does_not_take_runs_the_python_code_on_the_same_proxies(compiled):
    """A non-finite device position, and an object of more than _VECTOR_PLANES planes: the
    kernel writes nothing, the stage's Python code runs, and both share the proxies."""
    stage, obj = _edge_case(compiled, [])
    ref, _ = _edge_case(None, [])
    frame, rframe = Frame(1, 1), Frame(1, 1)
    path = [(0.06, 0.0, 0.0), (0.02, 0.0, 0.0), (math.nan, 0.0, 0.0), (0.01, 0.0, 0.0)]
    for p in path:
        for s, f in ((stage, frame), (ref, rframe)):
            f.device_pos[0] = p
            s.run(f)
        state = stage.state.copy()
        for name in OUTPUTS:
            np.testing.assert_array_equal(getattr(frame, name), getattr(rframe, name))
        np.testing.assert_array_equal(stage.state[:, :3], ref.state[:, :3])
        assert np.array_equal(state, stage.state, equal_nan=True)
    # The kernel itself, handed the NaN: not taken, nothing written.
    frame.device_pos[0] = (math.nan, 0.0, 0.0)
    before = {name: getattr(frame, name).copy() for name in OUTPUTS}
    planes = stage._kernel_planes()
    state = stage.state.copy()
    outcome = compiled(
        frame.device_pos, frame.device_vel, planes, stage.state, frame.proxy_pos,
        frame.in_contact, frame.surface_point, frame.contact_point, frame.contact_normal,
        frame.env_force,
    )  # fmt: skip
    assert outcome == kernels.CONTACT_NOT_TAKEN
    for name in OUTPUTS:
        np.testing.assert_array_equal(getattr(frame, name), before[name])
    assert np.array_equal(stage.state, state, equal_nan=True)
    # A large mesh: vectorised in Python, not the kernel's.
    k = _VECTOR_PLANES + 1
    angles = np.linspace(0.0, 2.0 * np.pi, k, endpoint=False)
    normals = np.stack([np.cos(angles), np.sin(angles), np.zeros(k)], axis=1)
    obj.shape = dataclasses.replace(obj.shape, normals=normals, offsets=np.full(k, 0.02))
    obj.update_world()
    assert stage._kernel_planes() is None
    frame.device_pos[0] = (0.015, 0.0, 0.0)
    stage.run(frame)
    assert frame.in_contact[0] == 1


@pytest.mark.parametrize("path", [LIFT, GRASP], ids=["lift", "grasp"])
def test_the_bundled_profiles_render_their_contact_with_the_kernel(compiled, path):
    jit.compile_kernels(list(jit.SIGNATURES))
    s = build_session(
        load_profile(path, ["rendering.kernels=compiled"]), paced=False, duration_s=0.01
    )
    assert "contact_step" in s.renderer.kernel_names
    assert s.renderer.stages[s.renderer.stage_names.index("contact")].kernel is not None


def _hostile_run(path, mode: str, value: float, where: str) -> tuple[dict, np.ndarray, float, int]:
    """Run ``path`` for 1.2 s with finger 0's position ``value`` (every axis) from 1 s on:
    reported by its device (``where="device"``), or put into the frame's row after the
    device bank read it (``"frame"``: a device layer that let a bad sample through). The
    summary, every force written, the force limit and the number of devices."""
    profile = load_profile(path, [f"rendering.kernels={mode}"])
    session = build_session(profile, paced=False, duration_s=1.2)
    assert ("contact_step" in session.renderer.kernels) == (mode == "compiled")
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
def test_hostile_positions_past_the_device_bank_give_the_python_paths_forces(compiled, path, value):
    """The same positions put straight into the frame (past the bank's check): the kernel
    takes the finite ones, the Python code the rest; every force written is finite, within
    the limit and the Python path's, bit for bit, and so is how the run ends."""
    jit.compile_kernels(list(jit.SIGNATURES))
    summary, forces, limit, _ = _hostile_run(path, "compiled", value, "frame")
    ref, ref_forces, _, _ = _hostile_run(path, "python", value, "frame")
    assert np.all(np.isfinite(forces))
    assert np.all(np.linalg.norm(forces, axis=1) <= limit + 1e-12)
    assert summary["fault"] == ref["fault"]
    np.testing.assert_array_equal(forces, ref_forces)
