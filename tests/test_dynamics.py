"""The free-body step on plain floats (``step_body_small``, the Dynamics stage's path for
shapes of up to SMALL_SHAPE vertices) against the numpy step (``step_body``): one model,
so the same results on every output, whatever the state, forces, contacts and substeps."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from hapticd.dynamics import SurfaceSet, step_body, step_body_small
from hapticd.scene import ConvexShape, Material, SceneObject, Surface
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
def cases(draw) -> dict:
    size = draw(vec(0.01, 0.1))
    box = ConvexShape.box(size)
    # Principal axes turned away from the box's: the float path's full inertia matrix.
    Q = draw(rotations())
    shape = ConvexShape(
        box.normals, box.offsets, box.vertices, box.volume, Q @ box.inertia_unit_mass @ Q.T
    )
    state = {
        "shape": shape,
        "material": Material(draw(floats(50.0, 1000.0))),
        "position": draw(vec(-0.05, 0.05)),
        "rotation": draw(rotations()),
        "mass": draw(floats(0.05, 2.0)),
        "velocity": draw(vec(-0.5, 0.5)),
        "omega": draw(vec(-10.0, 10.0)),
    }
    # Ground and walls: planes through or near the object, so vertices often touch them.
    surfaces = []
    for i in range(draw(st.integers(0, 3))):
        n = draw(unit_vectors())
        offset = float(n @ state["position"]) + draw(floats(-0.06, 0.03))
        surfaces.append(Surface(f"surface {i}", tuple(n), offset, draw(materials())))
    springs = [
        (state["position"] + draw(vec(-0.05, 0.05)), draw(vec(-5.0, 5.0)), draw(floats(10, 1e3)))
        for _ in range(draw(st.integers(0, 2)))
    ]
    torsion = [
        (draw(unit_vectors()), draw(floats(0.0, 0.05))) for _ in range(draw(st.integers(0, 2)))
    ]
    return {
        "state": state,
        "force": draw(vec(-5.0, 5.0)),
        "torque": draw(vec(-0.1, 0.1)),
        "gravity": draw(st.none() | vec(-10.0, 10.0)),
        "surfaces": SurfaceSet(surfaces) if surfaces else None,
        "substeps": draw(st.integers(1, 8)),
        "springs": springs or None,
        "torsion": torsion or None,
    }


def _object(state: dict) -> SceneObject:
    return SceneObject(
        state["shape"],
        state["material"],
        state["position"].copy(),
        state["rotation"].copy(),
        fixed=False,
        mass=state["mass"],
        velocity=state["velocity"].copy(),
        omega=state["omega"].copy(),
    )


def run_both(case: dict) -> tuple[SceneObject, SceneObject]:
    big, small = _object(case["state"]), _object(case["state"])
    kw = {k: case[k] for k in ("gravity", "surfaces", "substeps", "springs", "torsion")}
    step_body(big, case["force"], case["torque"], DT, **kw)
    step_body_small(small, tuple(case["force"]), tuple(case["torque"]), DT, **kw)
    return big, small


# Both paths evaluate one model in a different order (forces summed in another order,
# Euler's equations in the world frame or the body frame, Rodrigues with a Bjorck step or
# a quaternion exponential): rounding of about 1e-16 per operation, grown over up to 8
# substeps of stiff springs. Over 2000 generated cases the largest difference was 2.4e-14
# of the quantity's size; 1e-12 leaves a margin of 40, and any difference in the model (a
# term left out, another friction cap, a wrong frame) shows at 1e-6 or more.
RTOL = 1e-12


@given(cases())
def test_the_float_step_equals_the_numpy_step(case):
    big, small = run_both(case)
    for name in ("position", "velocity", "omega", "rotation"):
        a, b = getattr(big, name), getattr(small, name)
        # The size of the quantity, before or after the step (either may be near zero).
        scale = max(np.abs(a).max(), np.abs(case["state"][name]).max())
        diff = np.abs(a - b).max()
        assert diff <= RTOL * scale, f"{name}: differs by {diff:.3g} (size {scale:.3g})"
    # The world-frame shape the next tick's contact sees, from the new pose.
    np.testing.assert_allclose(
        big.polytope.offsets,
        small.polytope.offsets,
        rtol=0,
        atol=RTOL * (1 + np.abs(big.polytope.offsets).max()),
    )


def huge(limit: float):
    """Finite floats of any size up to ``limit`` (either sign), the large ones often."""
    return st.floats(-limit, limit, allow_nan=False, allow_infinity=False) | st.sampled_from(
        [1e154, -1e160, 1e200, 1.7e308]
    )


@given(
    omega=st.tuples(huge(1.7e308), huge(1.7e308), huge(1.7e308)),
    torque=st.tuples(huge(1.7e308), huge(1.7e308), huge(1.7e308)),
)
def test_the_float_step_never_raises_on_finite_input(omega, torque):
    """A spin whose square overflows (|w| above about 1e154 rad/s, or a torque that makes
    one) gives a non-finite pose, as the compiled step does, instead of a math error; the
    loop's object check then sees the spin beyond its limit and ends the run."""
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
    step_body_small(obj, (0.0, 0.0, 0.0), torque, DT, substeps=2)
    if not np.all(np.isfinite(obj.rotation)):
        spin = np.hypot.reduce(np.abs(obj.omega)) if np.all(np.isfinite(obj.omega)) else np.inf
        assert not spin <= MAX_OBJECT_SPIN_RAD_PER_S  # NaN counts as beyond: the check's way
