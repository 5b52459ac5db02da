"""The free-body step (hapticd.kernels.free_body_step, the Dynamics stage's physics) against
``hapticd.dynamics.step_body``, the same model written independently in numpy: the same
results to rounding on every output, whatever the state, contacts, surfaces, gravity and
substeps; a spin that overflows gives a non-finite pose (for the loop's object check), not
an error, compiled or not. tests/test_kernels.py compares compiled and uncompiled."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hapticd import jit
from hapticd.dynamics import SurfaceSet, step_body
from hapticd.frame import Frame
from hapticd.scene import ConvexShape, Material, Scene, SceneObject, Surface
from hapticd.stages import Dynamics
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


def dynamics_stage(case: dict, kernel) -> tuple[Dynamics, Frame]:
    """The Dynamics stage for a ``stage_cases`` case (``kernel``: compiled, or None) and
    its frame."""
    o = case["object"]
    obj = SceneObject(
        o["shape"],
        o["material"],
        o["position"].copy(),
        o["rotation"].copy(),
        fixed=False,
        mass=o["mass"],
        velocity=o["velocity"].copy(),
        omega=o["omega"].copy(),
    )
    gravity = None if case["gravity"] is None else case["gravity"].copy()
    scene = Scene(obj, list(case["surfaces"]), gravity, case["substeps"])
    f = case["frame"]
    frame = Frame(len(f["in_contact"]), 3)
    for name, value in f.items():
        getattr(frame, name)[...] = value
    return Dynamics(scene, frame.n_fingers, DT, kernel), frame


def run_dynamics(case: dict, kernel) -> SceneObject:
    """The case's object after its ticks of the Dynamics stage."""
    stage, frame = dynamics_stage(case, kernel)
    for _ in range(case["ticks"]):
        stage.run(frame)
    return stage.scene.object


STATE = ("position", "velocity", "omega", "rotation")


@pytest.fixture(scope="module")
def compiled():
    """The compiled free-body kernel (numba is a dependency: no skip without it)."""
    return jit.compile_kernels(["free_body_step"])["free_body_step"]


def numpy_step(case: dict) -> SceneObject:
    """One tick of ``step_body`` for the case's object and the frame's contacts as the stage
    reads them: each finger in contact a spring of the object's stiffness at its contact
    point, carrying the reaction of its force; with torsional friction mu_t, a cap of
    mu_t |f . n| on the spin about its normal."""
    stage, frame = dynamics_stage(case, None)
    obj = stage.scene.object
    k, mu_t = obj.material.stiffness, obj.material.torsion
    springs, torsion = [], []
    for on, point, f, n in zip(
        frame.in_contact,
        frame.contact_point,
        frame.contact_force,
        frame.contact_normal,
        strict=True,
    ):
        if not on:
            continue
        springs.append((point.copy(), -f, k))
        if mu_t > 0.0 and abs(f @ n) > 0.0:
            torsion.append((n.copy(), mu_t * abs(float(f @ n))))
    step_body(
        obj,
        np.zeros(3),
        np.zeros(3),
        DT,
        gravity=case["gravity"],
        surfaces=SurfaceSet(case["surfaces"]) if case["surfaces"] else None,
        substeps=stage.substeps,
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
    got = run_dynamics({**case, "ticks": 1}, None)  # uncompiled: the reference
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


@pytest.mark.parametrize("path", ["uncompiled", "compiled"])
@given(
    omega=st.tuples(huge(1.7e308), huge(1.7e308), huge(1.7e308)),
    force=st.tuples(huge(1.7e308), huge(1.7e308), huge(1.7e308)),
)
def test_the_step_never_raises_on_finite_input(compiled, path, omega, force):
    """A spin whose square overflows (|w| above about 1e154 rad/s, or a finger's force whose
    torque makes one) gives a non-finite pose instead of a math error; the loop's object
    check then sees the spin beyond its limit and ends the run."""
    from hapticd.servo import MAX_OBJECT_SPIN_RAD_PER_S

    obj = SceneObject(
        ConvexShape.box(np.array([0.05, 0.04, 0.03])),
        Material(500.0),
        np.zeros(3),
        np.eye(3),
        fixed=False,
        mass=0.1,
        velocity=np.zeros(3),
        omega=np.array(omega),
    )
    frame = Frame(1, 1)
    frame.in_contact[0] = 1
    frame.contact_point[0] = (0.025, 0.02, 0.0)
    frame.contact_force[0] = force
    frame.contact_normal[0] = (1.0, 0.0, 0.0)
    stage = Dynamics(Scene(obj, [], None, 2), 1, DT, compiled if path == "compiled" else None)
    stage.run(frame)
    if not np.all(np.isfinite(obj.rotation)):
        spin = np.hypot.reduce(np.abs(obj.omega)) if np.all(np.isfinite(obj.omega)) else np.inf
        assert not spin <= MAX_OBJECT_SPIN_RAD_PER_S  # NaN counts as beyond: the check's way
