"""Delta kinematics: FK/IK round trip, Jacobian, virtual work, encoders, limits."""

import numpy as np
import pytest
from hapticd_drivers.delta import Delta, KinematicsError, load_description
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

DELTA = Delta(load_description("delta-omega-class"))
R_WS = DELTA.desc.workspace_radius


def in_workspace(v):
    n = np.linalg.norm(v)
    return v if n <= R_WS else v * (R_WS / n)


points = arrays(float, (3,), elements=st.floats(-R_WS, R_WS)).map(in_workspace)
angles = arrays(float, (3,), elements=st.floats(0.0, 1.0))


def test_home_pose_is_the_origin():
    np.testing.assert_allclose(DELTA.forward(np.full(3, DELTA.desc.home_angle)), 0, atol=1e-15)
    np.testing.assert_allclose(DELTA.inverse(np.zeros(3)), DELTA.desc.home_angle, atol=1e-12)


@given(points)
def test_inverse_then_forward_is_identity_across_the_workspace(p):
    np.testing.assert_allclose(DELTA.forward(DELTA.inverse(p)), p, atol=1e-12)


@given(angles)
def test_forward_then_inverse_is_identity(theta):
    p = DELTA.forward(theta)
    np.testing.assert_allclose(DELTA.inverse(p), theta, atol=1e-9)


@given(angles)
def test_jacobian_matches_finite_differences(theta):
    J = DELTA.jacobian(theta)
    h = 1e-7
    Jn = np.column_stack(
        [(DELTA.forward(theta + h * e) - DELTA.forward(theta - h * e)) / (2 * h) for e in np.eye(3)]
    )
    np.testing.assert_allclose(J, Jn, atol=1e-7)


@given(
    angles,
    arrays(float, (3,), elements=st.floats(-12, 12)),
    arrays(float, (3,), elements=st.floats(-1, 1)),
)
def test_virtual_work_force_times_displacement_equals_torque_times_rotation(theta, f, dq):
    dq = dq * 1e-6
    dx = DELTA.forward(theta + dq) - DELTA.forward(theta)
    tau = DELTA.torques(theta, f)
    assert f @ dx == pytest.approx(tau @ dq, rel=1e-4, abs=1e-12)


def test_encoder_quantisation_is_below_20_micrometres():
    rng = np.random.default_rng(3)
    worst = 0.0
    for _ in range(500):
        p = in_workspace(rng.uniform(-R_WS, R_WS, 3))
        counts = DELTA.counts_from_angles(DELTA.inverse(p))
        worst = max(worst, float(np.abs(DELTA.forward(DELTA.angles_from_counts(counts)) - p).max()))
    assert 0 < worst < 20e-6


def test_rated_force_fits_the_motors_at_home():
    th = np.full(3, DELTA.desc.home_angle)
    for f in np.vstack([np.eye(3), -np.eye(3)]) * DELTA.desc.max_force:
        assert np.abs(DELTA.torques(th, f)).max() <= DELTA.desc.max_arm_torque


def test_out_of_reach_and_bad_descriptions(tmp_path):
    with pytest.raises(KinematicsError, match="out of reach"):
        DELTA.inverse(np.array([0.0, 0.0, -1.0]))
    bad = tmp_path / "bad.yaml"
    bad.write_text("model: x\ngeometry: {base_radius_m: 0.07}\n")
    with pytest.raises(KinematicsError, match=r"missing key 'geometry\."):
        load_description(bad)
    with pytest.raises(KinematicsError, match="cannot read"):
        load_description(tmp_path / "none.yaml")
