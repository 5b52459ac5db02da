"""The free-body step (hapticd.physics.kernels.free_body_step, the Dynamics stage's part of the
tick's one call) against ``tests.dynamics_oracle.step_body``, the same model written
independently in numpy: the same results to rounding on every output, whatever the state,
contacts, surfaces, gravity and substeps; compiled and uncompiled, the same bits; the
object's state written in place; a spin that overflows gives a non-finite pose (for the
loop's object check), not an error, compiled or not.

The step runs in the renderer's one call, the frame's contacts put in by a stage inserted
before it (tests/ticks.py: the call in parts), the fingers out of contact themselves."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hapticd.physics.render import Renderer
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject, Surface
from tests import ticks
from tests.dynamics_oracle import SurfaceSet, step_body
from tests.strategies import unit_vectors

DT = 1e-3  # s, one tick at 1 kHz


def floats(lo: float, hi: float):
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


def vec(lo: float, hi: float):
    return st.tuples(floats(lo, hi), floats(lo, hi), floats(lo, hi)).map(np.array)


@st.composite
def rotations(draw) -> np.ndarray:
    """A rotation matrix: an angle (rad) about a unit axis (Rodrigues)."""
    axis = draw(unit_vectors())
    angle = draw(floats(0.0, np.pi))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


@st.composite
def materials(draw) -> Material:
    mu_d = draw(st.just(0.0) | floats(0.05, 1.0))  # frictionless or not
    return Material(
        stiffness=draw(floats(50.0, 2000.0)),
        damping=draw(floats(0.0, 10.0)),
        mu_static=mu_d * draw(floats(1.0, 1.5)),
        mu_dynamic=mu_d,
    )


@st.composite
def stage_cases(draw) -> dict:
    """A free box (principal axes turned), its fingers' contacts as the frame has them,
    surfaces near it, gravity or none, substeps."""
    size = draw(vec(0.01, 0.1))
    box = ConvexShape.box(size)
    Q = draw(rotations())
    shape = ConvexShape(
        box.normals, box.offsets, box.vertices, box.volume, Q @ box.inertia_unit_mass @ Q.T
    )
    material = Material(
        draw(floats(50.0, 1000.0)),
        draw(floats(0.0, 5.0)),
        torsion=draw(st.just(0.0) | floats(1e-4, 0.05)),
    )
    position = draw(vec(-0.05, 0.05))
    obj = {
        "shape": shape,
        "material": material,
        "position": position,
        "rotation": draw(rotations()),
        "mass": draw(floats(0.05, 2.0)),
        "velocity": draw(vec(-1.0, 1.0)),
        "omega": draw(vec(-10.0, 10.0)),
    }
    surfaces = []
    for i in range(draw(st.integers(0, 3))):
        n = draw(unit_vectors())
        offset = float(n @ position) + draw(floats(-0.06, 0.03))
        surfaces.append(Surface(f"surface {i}", tuple(n), offset, draw(materials())))
    n_fingers = draw(st.integers(1, 3))
    frame = {
        "in_contact": [draw(st.booleans()) for _ in range(n_fingers)],
        "contact_point": [position + draw(vec(-0.05, 0.05)) for _ in range(n_fingers)],
        "contact_force": [draw(vec(-5.0, 5.0)) for _ in range(n_fingers)],
        "contact_normal": [draw(unit_vectors()) for _ in range(n_fingers)],
    }
    return {
        "object": obj,
        "surfaces": surfaces,
        "gravity": draw(st.none() | vec(-10.0, 10.0)),
        "substeps": draw(st.integers(1, 8)),
        "frame": frame,
        "ticks": draw(st.integers(1, 3)),
    }


# The frame's fields the Dynamics stage reads, put in before it.
CONTACTS = ("in_contact", "contact_point", "contact_force", "contact_normal")


def free_object(case: dict) -> SceneObject:
    """A ``stage_cases`` case's object, free."""
    o = case["object"]
    return SceneObject(
        o["shape"],
        o["material"],
        o["position"].copy(),
        o["rotation"].copy(),
        fixed=False,
        mass=o["mass"],
        velocity=o["velocity"].copy(),
        omega=o["omega"].copy(),
    )


def dynamics_renderer(case: dict, mode: str) -> Renderer:
    """A renderer of a ``stage_cases`` case's scene (``mode``: compiled or uncompiled) whose
    plan puts the case's contacts into the frame before the Dynamics stage."""
    gravity = None if case["gravity"] is None else case["gravity"].copy()
    scene = Scene(free_object(case), list(case["surfaces"]), gravity, case["substeps"])
    f = case["frame"]
    r = ticks.renderer(scene, [0.008] * len(f["in_contact"]), mode)
    put = ticks.Put(CONTACTS)
    put.values = {name: np.array(value) for name, value in f.items()}
    r.insert(put, after="allocation")
    return r


def run_dynamics(case: dict, mode: str) -> SceneObject:
    """The case's object after its ticks (the fingers a metre away: no contact of their own)."""
    r = dynamics_renderer(case, mode)
    n = r.n_fingers
    for _ in range(case["ticks"]):
        r.step(ticks.far(n), np.zeros((n, 3)))
    return r.obj


STATE = ("position", "velocity", "omega", "rotation")


def numpy_step(case: dict) -> SceneObject:
    """One tick of ``step_body`` for the case's object and the frame's contacts as the stage
    reads them: each finger in contact a spring of the object's stiffness at its contact
    point, carrying the reaction of its force; with torsional friction mu_t, a cap of
    mu_t |f . n| on the spin about its normal."""
    obj = free_object(case)
    k, mu_t = obj.material.stiffness, obj.material.torsion
    springs, torsion = [], []
    f = case["frame"]
    for on, point, force, n in zip(
        f["in_contact"], f["contact_point"], f["contact_force"], f["contact_normal"], strict=True
    ):
        if not on:
            continue
        springs.append((point.copy(), -force, k))
        if mu_t > 0.0 and abs(force @ n) > 0.0:
            torsion.append((n.copy(), mu_t * abs(float(force @ n))))
    step_body(
        obj,
        np.zeros(3),
        np.zeros(3),
        DT,
        gravity=case["gravity"],
        surfaces=SurfaceSet(case["surfaces"]) if case["surfaces"] else None,
        substeps=case["substeps"],  # 1-8 (0 would let the Dynamics stage choose)
        torsion=torsion or None,
        springs=springs or None,
    )
    return obj


# Both evaluate one model in a different order (forces summed in another order, Euler's
# equations in the world frame or the body frame, Rodrigues with a Bjorck step or a
# quaternion exponential): rounding of about 1e-16 per operation, grown over up to 8
# substeps of stiff springs. Over 2000 generated cases the largest difference was 2.4e-14
# of the quantity's size; 1e-12 leaves a margin of 40, and any difference in the model (a
# term left out, another friction cap, a wrong frame) shows at 1e-6 or more.
RTOL = 1e-12


@given(stage_cases())
def test_the_step_equals_the_numpy_model(case):
    want = numpy_step(case)
    got = run_dynamics({**case, "ticks": 1}, "uncompiled")  # the reference
    for name in STATE:
        a, b = getattr(want, name), getattr(got, name)
        # The size of the quantity, before or after the step (either may be near zero).
        scale = max(np.abs(a).max(), np.abs(case["object"][name]).max())
        diff = np.abs(a - b).max()
        assert diff <= RTOL * scale, f"{name}: differs by {diff:.3g} (size {scale:.3g})"
    # The world-frame shape the next tick's contact sees, from the new pose.
    np.testing.assert_allclose(
        want.polytope.offsets,
        got.polytope.offsets,
        rtol=0,
        atol=RTOL * (1 + np.abs(want.polytope.offsets).max()),
    )


def huge(limit: float):
    """Finite floats of any size up to ``limit`` (either sign), the large ones often."""
    return st.floats(-limit, limit, allow_nan=False, allow_infinity=False) | st.sampled_from(
        [1e154, -1e160, 1e200, 1.7e308]
    )


@pytest.mark.parametrize("mode", ticks.MODES)
@given(
    omega=st.tuples(huge(1.7e308), huge(1.7e308), huge(1.7e308)),
    force=st.tuples(huge(1.7e308), huge(1.7e308), huge(1.7e308)),
)
def test_the_step_never_raises_on_finite_input(mode, omega, force):
    """A spin whose square overflows (|w| above about 1e154 rad/s, or a finger's force whose
    torque makes one) gives a non-finite pose instead of a math error; the loop's object
    check then sees the spin beyond its limit and ends the run."""
    from hapticd.loop.servo import MAX_OBJECT_SPIN_RAD_PER_S

    case = {
        "object": {
            "shape": ConvexShape.box(np.array([0.05, 0.04, 0.03])),
            "material": Material(500.0),
            "position": np.zeros(3),
            "rotation": np.eye(3),
            "mass": 0.1,
            "velocity": np.zeros(3),
            "omega": np.array(omega),
        },
        "surfaces": [],
        "gravity": None,
        "substeps": 2,
        "frame": {
            "in_contact": [True],
            "contact_point": [np.array([0.025, 0.02, 0.0])],
            "contact_force": [np.array(force)],
            "contact_normal": [np.array([1.0, 0.0, 0.0])],
        },
        "ticks": 1,
    }
    obj = run_dynamics(case, mode)
    if not np.all(np.isfinite(obj.rotation)):
        spin = np.hypot.reduce(np.abs(obj.omega)) if np.all(np.isfinite(obj.omega)) else np.inf
        assert not spin <= MAX_OBJECT_SPIN_RAD_PER_S  # NaN counts as beyond: the check's way


@given(stage_cases())
def test_the_step_compiled_and_uncompiled_agree_bit_for_bit(case):
    """numba neither fuses multiply-adds nor reorders without fastmath; sin, cos and sqrt
    are the same C library's: the same bits, on the state and the world-frame shape."""
    ref, got = run_dynamics(case, "uncompiled"), run_dynamics(case, "compiled")
    for name in STATE:
        np.testing.assert_array_equal(getattr(ref, name), getattr(got, name), err_msg=name)
    np.testing.assert_array_equal(ref.polytope.offsets, got.polytope.offsets)
    np.testing.assert_array_equal(ref.polytope.normals, got.polytope.normals)


@pytest.mark.parametrize("mode", ticks.MODES)
def test_the_step_writes_the_objects_state_in_place_and_takes_what_is_set(mode):
    """The call writes the object's state in place, into its one state array (whose views
    are its position, velocity, omega and rotation; the scene's fields are a copy of it);
    state put there from outside (a reset) is taken on the next tick, not overwritten."""
    obj = SceneObject(
        ConvexShape.box(np.full(3, 0.05)),
        Material(100.0),
        np.zeros(3),
        np.eye(3),
        fixed=False,
        mass=0.1,
    )
    r = ticks.renderer(Scene(obj, [], np.array([0.0, 0.0, -9.81]), 2), [0.008], mode)
    given_velocity, state = obj.velocity, obj.state
    frame = r.step(ticks.far(1), np.zeros((1, 3)))
    assert obj.velocity is given_velocity and obj.state is state  # written in place
    assert obj.velocity[2] == pytest.approx(-9.81 * DT) and state[5] == obj.velocity[2]
    np.testing.assert_array_equal(frame.object_vel, obj.velocity)
    obj.velocity = np.array([1, 0, 0])  # ints, from outside: copied into the state
    obj.position = np.zeros(3)
    assert obj.velocity is given_velocity and state[3] == 1.0
    r.step(ticks.far(1), np.zeros((1, 3)))
    assert obj.velocity.dtype == float and obj.velocity[0] == 1.0
    assert obj.position[0] == pytest.approx(1.0 * DT)
    np.testing.assert_array_equal(r.frame.object_pos, obj.position)
