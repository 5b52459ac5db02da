import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hapticd.allocation import METHODS, AllocationError, allocate
from hapticd.allocation.grasp import grasp_matrix, internal_projector
from tests.strategies import point_pairs, unit_vectors

A, MASS, g = 0.05, 0.09, 9.81
PTS = np.array([[-A, 0, 0], [A, 0, 0]])
G2 = grasp_matrix(PTS, np.zeros(3))
LAM = np.array([2, 0, MASS * g / 2, -2, 0, MASS * g / 2])


def blockdiag(d1, d2):
    M = np.zeros((6, 2))
    M[0:3, 0] = d1
    M[3:6, 1] = d2
    return M


@pytest.mark.parametrize("suffix", ["", "_exact"])
def test_actuators_along_normals_seed_case(suffix):
    M = blockdiag([1, 0, 0], [-1, 0, 0])
    np.testing.assert_allclose(allocate("pinv" + suffix, G2, M, LAM), [2, 2], atol=1e-12)
    np.testing.assert_allclose(allocate("if" + suffix, G2, M, LAM), [2, 2], atol=1e-12)
    # G M_a has rank 1 and carries no external force: EF renders nothing.
    np.testing.assert_allclose(allocate("ef" + suffix, G2, M, LAM), [0, 0], atol=1e-12)


@pytest.mark.parametrize("suffix", ["", "_exact"])
def test_actuators_both_vertical_seed_case(suffix):
    M = blockdiag([0, 0, 1], [0, 0, 1])
    for method in ("pinv", "if", "ef"):
        np.testing.assert_allclose(
            allocate(method + suffix, G2, M, LAM), [0.44145, 0.44145], atol=1e-12
        )


@pytest.mark.parametrize("theta_deg", [10, 30, 45, 60])
def test_if_renders_the_squeeze_exactly_with_tilted_actuators(theta_deg):
    th = np.radians(theta_deg)
    M = blockdiag([np.cos(th), 0, np.sin(th)], [-np.cos(th), 0, np.sin(th)])
    f = 1.5
    lam = np.array([f, 0, 0, -f, 0, 0])
    lam_if = allocate("if", G2, M, lam)
    lam_pinv = allocate("pinv", G2, M, lam)
    np.testing.assert_allclose(lam_if, [f / np.cos(th)] * 2, rtol=1e-12)
    np.testing.assert_allclose(lam_pinv, [f * np.cos(th)] * 2, rtol=1e-12)
    # Internal (squeeze) part of the rendered force equals the contact force's.
    P = internal_projector(G2)
    np.testing.assert_allclose(P @ (M @ lam_if), P @ lam, atol=1e-12)


def test_ef_matches_the_external_wrench_when_it_can():
    M = blockdiag([0.8, 0, 0.6], [-0.8, 0, 0.6])
    lam_a = allocate("ef", G2, M, LAM)
    # Weight: G lam = (0, 0, mg, 0, 0, 0) is in the range of G M_a here.
    np.testing.assert_allclose(G2 @ M @ lam_a, G2 @ LAM, atol=1e-12)


def test_single_contact_if_equals_pinv():
    G1 = grasp_matrix(PTS[:1], np.zeros(3))
    M = np.array([[0.6], [0.0], [0.8]])
    lam = np.array([1.0, 0.3, -0.2])
    np.testing.assert_allclose(allocate("if", G1, M, lam), allocate("pinv", G1, M, lam), atol=1e-14)


def _grasp():
    """Two contacts 1 to 20 cm apart, a unit actuated direction each, contact forces in N."""
    pts = point_pairs(extent=0.1, min_gap=1e-2, max_gap=0.2)
    dirs = st.tuples(unit_vectors(), unit_vectors())
    lam = arrays(float, (6,), elements=st.floats(-20, 20))
    return pts, dirs, lam


@given(*_grasp())
def test_pinv_is_least_squares(pts, dirs, lam):
    M = blockdiag(*dirs)
    G = grasp_matrix(pts, np.zeros(3))
    lam_a = allocate("pinv", G, M, lam)
    # Residual orthogonal to the actuated directions: the normal equations hold.
    np.testing.assert_allclose(M.T @ (lam - M @ lam_a), 0, atol=1e-9)


@given(*_grasp())
def test_if_is_exact_on_internal_forces_when_b_has_full_row_rank(pts, dirs, lam):
    M = blockdiag(*dirs)
    G = grasp_matrix(pts, np.zeros(3))
    P = internal_projector(G)
    B = P @ M
    # Well-conditioned cases only (about 6 % of random directions are not): the singular
    # ones are tests/test_allocation_robust.py's.
    assume(np.linalg.svd(B, compute_uv=False)[0] >= 0.2)
    lam_a = allocate("if", G, M, lam)
    np.testing.assert_allclose(P @ (M @ lam_a), P @ lam, atol=1e-8 * (1 + np.abs(lam).max()))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_input_raises(bad):
    M = blockdiag([1, 0, 0], [-1, 0, 0])
    lam = LAM.copy()
    lam[2] = bad
    for method in METHODS:
        with pytest.raises(AllocationError, match="NaN or inf"):
            allocate(method, G2, M, lam)
    G = G2.copy()
    G[4, 1] = bad
    with pytest.raises(AllocationError, match="G contains"):
        allocate("if", G, M, LAM)


def test_unknown_method_and_bad_shapes_raise():
    M = blockdiag([1, 0, 0], [-1, 0, 0])
    with pytest.raises(AllocationError, match="unknown allocator 'foo'"):
        allocate("foo", G2, M, LAM)
    with pytest.raises(AllocationError, match="M_a must have shape"):
        allocate("pinv", G2, M[:3], LAM)
    with pytest.raises(AllocationError, match="lam must have shape"):
        allocate("pinv", G2, M, LAM[:3])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("where", ["point", "force", "direction"])
@pytest.mark.parametrize("method", ["ef", "if_exact"])
def test_contact_allocator_refuses_non_finite_geometry(bad, where, method):
    """The per-tick allocation (the kernel's closed forms, and allocate() for the methods
    it does not take) refuses a NaN or inf anywhere in a contact's point, force or
    direction, and takes large finite values."""
    from hapticd.allocation import DEFAULT_ROBUSTNESS, AdaptiveState
    from hapticd.allocation.actuation import Actuation
    from hapticd.allocation.contacts import ContactAllocator

    def allocator(direction):
        act = Actuation([[direction], [[-1.0, 0.0, 0.0]]], "world")
        return ContactAllocator(act, method, DEFAULT_ROBUSTNESS, AdaptiveState(), 1e-3)

    points = np.array([(-A, 0.0, 0.0), (A, 0.0, 0.0)])
    forces = np.array([(2.0, 0.0, 0.4), (-2.0, 0.0, 0.4)])
    big = np.array([(1e300, -1e300, 1e300), (-1e300, 1e300, 1e300)])
    lam_a, rendered, center = np.zeros(2), np.zeros((2, 3)), np.zeros(3)
    for contacts in ([1, 0], [1, 1]):
        touching = np.array(contacts, dtype=np.uint8)
        allocator([1.0, 0.0, 0.0]).allocate(touching, points, points, big, center, lam_a, rendered)
        assert np.all(np.isfinite(lam_a))
        p, f, d = points.copy(), forces.copy(), [1.0, 0.0, 0.0]
        if where == "point":
            p[0, 1] = bad
        elif where == "force":
            f[0, 2] = bad
        else:
            d = [bad, 0.0, 0.0]
        with pytest.raises(AllocationError, match="non-finite"):
            allocator(d).allocate(touching, points, p, f, center, lam_a, rendered)


def test_adaptive_alpha_survives_a_refused_tick():
    """A tick with a NaN force (refused) or forces whose task ratio overflows leaves the
    adaptive allocator's alpha as it was: the next good tick allocates as if it never came."""
    from hapticd.allocation import DEFAULT_ROBUSTNESS, AdaptiveState
    from hapticd.allocation.actuation import Actuation
    from hapticd.allocation.contacts import ContactAllocator

    def allocator():
        act = Actuation([[[0.866, 0.0, 0.5]], [[-0.866, 0.0, 0.5]]], "world")
        return ContactAllocator(act, "adaptive", DEFAULT_ROBUSTNESS, AdaptiveState(), 1e-3)

    touching, center = np.ones(2, dtype=np.uint8), np.zeros(3)
    points = np.array([(-A, 0.0, 0.0), (A, 0.0, 0.0)])
    push = np.array([(2.0, 0.0, 3.0), (-1.0, 0.0, 3.0)])  # mostly external: alpha rises
    lam_a, rendered = np.zeros(2), np.zeros((2, 3))
    clean, spoiled = allocator(), allocator()
    for alloc in (clean, spoiled):
        alloc.allocate(touching, points, points, push, center, lam_a, rendered)
    bad = push.copy()
    bad[1, 2] = np.nan
    with pytest.raises(AllocationError, match="non-finite"):
        spoiled.allocate(touching, points, points, bad, center, lam_a, rendered)
    spoiled.allocate(touching, points, points, push * 1e300, center, lam_a, rendered)
    assert 0.0 < spoiled.alpha == clean.alpha
    want = clean.allocate(touching, points, points, push, center, np.zeros(2), np.zeros((2, 3)))
    got = spoiled.allocate(touching, points, points, push, center, lam_a, rendered)
    np.testing.assert_array_equal(got, want)
