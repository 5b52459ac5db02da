import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hapticd.allocation.grasp import (
    decompose,
    grasp_matrix,
    internal_projector,
    null_space_basis,
    skew,
)
from tests.strategies import point_pairs

finite = st.floats(-0.2, 0.2, allow_nan=False)


def test_layout_force_rows_then_moment_about_center():
    pts = np.array([[0.1, 0.0, 0.0], [0.0, 0.2, 0.0]])
    center = np.array([0.0, 0.0, 0.05])
    G = grasp_matrix(pts, center)
    assert G.shape == (6, 6)
    lam = np.array([1.0, 2.0, 3.0, -4.0, 5.0, 0.5])
    w = G @ lam
    f = lam[:3] + lam[3:]
    m = np.cross(pts[0] - center, lam[:3]) + np.cross(pts[1] - center, lam[3:])
    np.testing.assert_allclose(w, np.concatenate([f, m]), atol=1e-15)


def test_skew_is_cross_product():
    v, u = np.array([1.0, -2.0, 3.0]), np.array([0.5, 0.1, -4.0])
    np.testing.assert_allclose(skew(v) @ u, np.cross(v, u))


def test_two_antipodal_contacts_rank5_nullspace_along_grasp_line():
    a = 0.05
    G = grasp_matrix(np.array([[-a, 0, 0], [a, 0, 0]]), np.zeros(3))
    assert np.linalg.matrix_rank(G) == 5
    e = np.array([1.0, 0, 0])
    n = np.concatenate([e, -e]) / np.sqrt(2)
    np.testing.assert_allclose(internal_projector(G), np.outer(n, n), atol=1e-12)


def test_seed_worked_case_wrench():
    a, m = 0.05, 0.09
    G = grasp_matrix(np.array([[-a, 0, 0], [a, 0, 0]]), np.zeros(3))
    lam = np.array([2, 0, m * 9.81 / 2, -2, 0, m * 9.81 / 2])
    np.testing.assert_allclose(G @ lam, [0, 0, 0.8829, 0, 0, 0], atol=1e-12)


@given(point_pairs(extent=0.2, min_gap=1e-3, max_gap=0.4), arrays(float, (3,), elements=finite))
def test_two_contact_nullspace_independent_of_reference(pts, center):
    d = pts[1] - pts[0]
    G = grasp_matrix(pts, center)
    e = d / np.linalg.norm(d)
    n = np.concatenate([e, -e]) / np.sqrt(2)
    np.testing.assert_allclose(internal_projector(G), np.outer(n, n), atol=1e-9)


@given(arrays(float, (3, 3), elements=finite), arrays(float, (9,), elements=st.floats(-10, 10)))
def test_decompose_parts_are_orthogonal_and_internal_is_balanced(pts, lam):
    G = grasp_matrix(pts, np.zeros(3))
    internal, external = decompose(G, lam)
    np.testing.assert_allclose(internal + external, lam, atol=1e-9)
    np.testing.assert_allclose(G @ internal, 0, atol=1e-8)
    assert abs(internal @ external) < 1e-8 * (1 + lam @ lam)


def test_null_space_of_empty_and_zero_matrices():
    assert null_space_basis(np.zeros((0, 3))).shape == (3, 3)
    np.testing.assert_allclose(null_space_basis(np.zeros((1, 2))), np.eye(2))
