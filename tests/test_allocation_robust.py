"""Robust allocators: exact where well-conditioned; finite, bounded and continuous everywhere."""

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from hapticd.allocation import (
    DEFAULT_ROBUSTNESS,
    AdaptiveState,
    Robustness,
    accuracy,
    allocate,
    allocate_many,
    closed,
    two_contact_structure,
)
from hapticd.allocation import general as general_path
from hapticd.allocation.accuracy import one_contact_residuals, two_contact_residuals
from hapticd.allocation.actuation import Actuation
from hapticd.allocation.cases import SWEEPS
from hapticd.allocation.cases import block_actuation as block_m
from hapticd.allocation.grasp import grasp_matrix, internal_projector
from hapticd.physics.render import Renderer
from hapticd.physics.scene import ConvexShape, Material, SceneObject
from tests.allocation_oracle import filtered_gain, svd_internal_projector, svd_pinv

EPS = DEFAULT_ROBUSTNESS.eps
ROBUST = ("pinv", "if", "ef")


def filtered_pinv(A: np.ndarray, eps: float) -> np.ndarray:
    """The general path's filtered pseudoinverse of A (m, n), (n, m): its pinv of each unit
    vector (hapticd.allocation.general on one grasp per column)."""
    m, n = A.shape
    out = np.zeros((m, n))
    args = (np.zeros((m, 6, m)), A[None].copy(), np.eye(m), np.zeros(m), eps, 0.005, False, out)
    general_path.solve_grasps(general_path.PINV, *args, np.zeros(general_path.work_shape(m, n)))
    return out.T


def soft_internal_projector(G: np.ndarray, robust: Robustness = DEFAULT_ROBUSTNESS) -> np.ndarray:
    """The general path's soft projector onto the internal forces N(G), (3p, 3p), of G
    (6, 3p): ``general.soft_apply`` on each unit vector."""
    n = G.shape[1]
    w = np.zeros(general_path.work_shape(n, 1))
    w[0:6, :n] = G
    general_path.soft_prepare(w, n, robust.eps, robust.min_separation_m)
    out = np.empty((n, n))
    src, dst = w.shape[0] - 2, w.shape[0] - 1
    for k in range(n):
        w[src, :n] = np.eye(n)[k]
        general_path.soft_apply(w, n, robust.eps * robust.eps, src, dst)
        out[:, k] = w[dst, :n]
    return out


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


@st.composite
def grasps(draw, min_p=1, max_p=4, degenerate=False, accept=None):
    """(G, M_a, lam): p contacts, 1-3 directions each; degenerate cases on request.

    ``accept(G, M)``: the geometry is drawn again (from the same seed, up to 40 times)
    until it holds, so a test that needs such cases gets mostly valid ones.
    """
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    p = draw(st.integers(min_p, max_p))
    for _ in range(40):
        pts = rng.uniform(-0.06, 0.06, (p, 3))
        center = rng.uniform(-0.03, 0.03, 3)
        dirs = [[unit(rng.normal(size=3)) for _ in range(rng.integers(1, 4))] for _ in range(p)]
        if accept is None or accept(grasp_matrix(pts, center), block_m(dirs)):
            break
    scale = 10.0 ** draw(st.integers(-9, 3))
    lam = rng.normal(size=3 * p) * scale
    if degenerate:
        kind = draw(
            st.sampled_from(
                [
                    "coincident",
                    "collinear",
                    "at_center",
                    "parallel_dirs",
                    "normal_dirs",
                    "vertical",
                    "zero",
                    "tilt",
                ]
            )
        )
        if kind == "coincident" and p >= 2:
            pts[1] = pts[0] + rng.normal(size=3) * 10.0 ** draw(st.integers(-16, -3))
        elif kind == "collinear" and p >= 3:
            e = unit(rng.normal(size=3))
            pts = pts[0] + np.outer(rng.uniform(-0.05, 0.05, p), e)
        elif kind == "at_center":
            center = pts[0].copy()
        elif kind == "parallel_dirs":
            d = dirs[0][0]
            dirs[0] = [d, unit(d + rng.normal(size=3) * 10.0 ** draw(st.integers(-15, -2)))]
        elif kind in ("normal_dirs", "vertical", "tilt") and p >= 2:
            e = unit(pts[1] - pts[0])
            up = np.array([0, 0, 1.0])
            base = [e, -e] if kind == "normal_dirs" else [up, up]
            tilt = 10.0 ** draw(st.integers(-15, -1)) if kind == "tilt" else 0.0
            dirs[0] = [unit(base[0] + tilt * e)]
            dirs[1] = [unit(base[1] - tilt * e)]
        elif kind == "zero":
            lam = np.zeros_like(lam)
    return grasp_matrix(pts, center), block_m(dirs), lam


def singular_values(A):
    return np.linalg.svd(A, compute_uv=False) if A.size else np.zeros(0)


def well_conditioned(method, G, M):
    """Every singular value involved is structurally zero or clearly above eps."""

    def ok(A):
        s = singular_values(A)
        return bool(np.all((s < 1e-10) | (s > 1.5 * EPS)))

    p = G.shape[1] // 3
    pts = np.array([[G[5, 3 * i + 1], G[3, 3 * i + 2], G[4, 3 * i]] for i in range(p)])
    if p >= 2:
        dmin = min(np.linalg.norm(pts[i] - pts[j]) for i in range(p) for j in range(i))
        if dmin < 2 * DEFAULT_ROBUSTNESS.min_separation_m:
            return False
    if not ok(M):
        return False
    if method == "ef":
        return ok(G @ M)
    if method == "if":
        P_int = internal_projector(G)
        # Three or more contacts that are nearly collinear (pairwise far apart) blend too.
        if np.abs(soft_internal_projector(G) - P_int).max() > 1e-9:
            return False
        B = P_int @ M
        if not ok(B):
            return False
        P = np.eye(M.shape[1]) - np.linalg.pinv(B) @ B
        return ok(M @ P)
    return True


# -- equal to the seed where well-conditioned ------------------------------------------------


@pytest.mark.parametrize("method", ROBUST)
@given(st.data())
def test_equals_seed_formula_where_well_conditioned(method, data):
    # EF's G M_a is well-conditioned for one or two contacts only: with more, the moment
    # rows (lever arms of centimetres) put singular values between 0 and 1.5 eps.
    max_p = 2 if method == "ef" else 4
    G, M, lam = data.draw(grasps(max_p=max_p, accept=lambda G, M: well_conditioned(method, G, M)))
    assume(well_conditioned(method, G, M))  # the rare geometry the 40 draws did not fix
    robust = allocate(method, G, M, lam)
    exact = allocate(method + "_exact", G, M, lam)
    scale = max(np.abs(exact).max(), np.abs(lam).max(), 1e-300)
    np.testing.assert_allclose(robust, exact, rtol=0, atol=1e-9 * scale)


@pytest.mark.parametrize("method", [*ROBUST, "adaptive"])
@given(st.data())
def test_two_contact_closed_form_equals_general_path(method, data):
    G, M, lam = data.draw(grasps(min_p=2, max_p=2, degenerate=data.draw(st.booleans())))
    M = block_m([[M[0:3, 0]], [M[3:6, -1]]])  # one direction per finger: the closed form applies
    assert two_contact_structure(G, M) is not None
    alpha = data.draw(st.floats(0, 1))
    fast = allocate(method, G, M, lam, alpha=alpha)
    general = allocate(method, G, M, lam, alpha=alpha, fast=False)
    np.testing.assert_allclose(fast, general, rtol=0, atol=1e-9 * max(np.abs(lam).max(), 1e-300))


# -- finite and bounded everywhere -----------------------------------------------------------


def bound(method, G, M, eps=EPS):
    """Documented bound on |M_a lam_a| / |lam| (docs/allocation.md) for the threshold eps."""
    sm = singular_values(M).max()
    if method == "pinv":
        return 1.0
    if method == "if":
        return 1.0 + 2.0 * sm / eps
    return sm * singular_values(G).max() / eps


@pytest.mark.parametrize("method", ROBUST)
@given(grasps(degenerate=True))
def test_finite_and_bounded_in_degenerate_grasps(method, g):
    G, M, lam = g
    lam_a = allocate(method, G, M, lam)
    assert np.all(np.isfinite(lam_a))
    rendered = np.linalg.norm(M @ lam_a)
    assert rendered <= bound(method, G, M) * np.linalg.norm(lam) * (1 + 1e-9) + 1e-300


@pytest.mark.parametrize("method", ROBUST)
@given(grasps(degenerate=True), st.floats(1e-9, 1e3))
def test_linear_in_lam_from_nanonewtons_to_kilonewtons(method, g, s):
    G, M, lam = g
    a = allocate(method, G, M, lam)
    b = allocate(method, G, M, s * lam)
    np.testing.assert_allclose(b, s * a, rtol=1e-9, atol=1e-300)


def test_the_exact_formula_blows_up_where_the_robust_one_does_not():
    G = grasp_matrix(np.array([[-0.025, 0, 0], [0.025, 0, 0]]), np.zeros(3))
    lam = np.array([1.0, 0, 0, -1.0, 0, 0])
    for tilt in (1e-2, 1e-6):
        th = np.pi / 2 - tilt
        M = block_m([[[np.cos(th), 0, np.sin(th)]], [[-np.cos(th), 0, np.sin(th)]]])
        assert np.abs(allocate("if_exact", G, M, lam)).max() > 0.9 / tilt  # the trap: f / sin(eps)
        assert np.abs(allocate("if", G, M, lam)).max() < 1.0 / EPS


def test_no_contact_single_contact_and_zero_force():
    assert allocate("if", np.zeros((6, 0)), np.zeros((0, 0)), np.zeros(0)).shape == (0,)
    G1 = grasp_matrix(np.array([[0.02, 0, 0]]), np.zeros(3))
    M1 = block_m([[[1, 0, 0], [0, 1, 0]]])
    lam = np.array([2.0, -1.0, 5.0])
    np.testing.assert_allclose(allocate("if", G1, M1, lam), [2.0, -1.0])  # = pinv
    for method in ROBUST:
        np.testing.assert_array_equal(allocate(method, G1, M1, np.zeros(3)), 0)


# -- continuous through every kind of rank change -------------------------------------------


def max_jump(method, make, ts):
    """Largest change of lam_a between neighbouring t, and lam_a (len(ts), r), in one batch
    (allocate() is the same definition with a batch of one)."""
    G, M, lam = (np.array(x) for x in zip(*(make(float(t)) for t in ts), strict=True))
    vals = allocate_many(method, G, M, lam)
    return float(np.abs(np.diff(vals, axis=0)).max()), vals


SWEEP_CASES = [(name, method) for name, (_, singular) in SWEEPS.items() for method in ROBUST]


@pytest.mark.parametrize(("name", "method"), SWEEP_CASES)
def test_sweep_through_rank_change_is_continuous_and_bounded(name, method):
    make, singular_for = SWEEPS[name]
    coarse = np.linspace(-0.05, 0.05, 2001)  # passes through t = 0, the singular point
    fine = np.linspace(-0.005, 0.005, 2001)  # ten times finer around it

    jump_coarse, vals = max_jump(method, make, coarse)
    jump_fine, _ = max_jump(method, make, fine)
    assert np.all(np.isfinite(vals))
    assert np.abs(vals).max() < 10.0
    # A continuous map's largest step shrinks with the grid; a jump would not.
    assert jump_fine < 0.2 * jump_coarse + 1e-12
    assert jump_coarse < 0.05
    if method == singular_for:
        # The seed's formula is not continuous there: the sweep really crosses the singularity.
        exact_coarse, _ = max_jump(method + "_exact", make, coarse)
        exact_fine, _ = max_jump(method + "_exact", make, fine)
        assert exact_fine > 0.2 * exact_coarse or exact_coarse > 1.0


def test_filtered_gain_is_continuous_and_bounded():
    """The allocators' gain on a singular value s: s times ``closed._gain`` of s^2 (1/s
    from eps on, s/eps^2 below), against the oracle's."""
    s = np.linspace(0, 1, 100001)
    g = s * np.array([closed._gain(x * x, EPS * EPS) for x in s.tolist()])
    np.testing.assert_allclose(g, filtered_gain(s, EPS), rtol=1e-12, atol=0)
    assert g.max() == pytest.approx(1 / EPS)
    assert np.abs(np.diff(g)).max() < 1e-3
    for x, want in ((0.5, 2.0), (2.0, 0.5), (EPS / 2, 0.5 / EPS)):
        assert x * closed._gain(x * x, EPS * EPS) == pytest.approx(want, rel=1e-12)
    A = np.array([[1.0, 0.0], [0.0, 1e-12]])
    np.testing.assert_allclose(filtered_pinv(A, EPS), [[1.0, 0], [0, 1e-12 / EPS**2]])


@given(grasps(degenerate=True), st.sampled_from([0.01, 0.2, 0.9]))
def test_filtered_pinv_and_soft_projector_equal_their_svd_definition(g, eps):
    """The Gram-matrix forms the allocators run against the definitions by SVD (the
    independent oracle), near singular configurations included."""
    G, M, _ = g
    rb = Robustness(eps=eps)
    for A in (M, G @ M):
        np.testing.assert_allclose(filtered_pinv(A, eps), svd_pinv(A, eps), rtol=0, atol=1e-9 / eps)
    want = svd_internal_projector(G, rb)
    np.testing.assert_allclose(soft_internal_projector(G, rb), want, rtol=0, atol=1e-9)


def test_soft_internal_projector_is_exact_apart_and_full_when_coincident():
    G = grasp_matrix(np.array([[-0.02, 0, 0], [0.02, 0, 0]]), np.array([0.0, 0.01, 0]))
    np.testing.assert_allclose(soft_internal_projector(G), internal_projector(G), atol=1e-12)
    G0 = grasp_matrix(np.array([[0.01, 0, 0], [0.01, 0, 0]]), np.zeros(3))
    anti = 0.5 * np.block([[np.eye(3), -np.eye(3)], [-np.eye(3), np.eye(3)]])
    np.testing.assert_allclose(soft_internal_projector(G0), anti, atol=1e-12)


# -- accuracy measures ------------------------------------------------------------------------


@given(grasps(min_p=2, max_p=2))
def test_accuracy_closed_form_matches_general(g):
    G, M, lam = g
    M = block_m([[M[0:3, 0]], [M[3:6, -1]]])
    lam_a = allocate("if", G, M, lam)
    a = accuracy(G, M, lam, lam_a)
    r1, r2, d1, d2 = two_contact_structure(G, M)
    b = two_contact_residuals(r1, r2, d1, d2, tuple(lam[:3]), tuple(lam[3:]), *lam_a)
    np.testing.assert_allclose(
        b,
        [a.internal, a.external, a.total, a.amplification],
        rtol=1e-9,
        atol=1e-12 * np.abs(lam).max(),
    )


def test_accuracy_tells_if_from_ef_on_the_seed_case():
    G = grasp_matrix(np.array([[-0.05, 0, 0], [0.05, 0, 0]]), np.zeros(3))
    M = block_m([[[0.866, 0, 0.5]], [[-0.866, 0, 0.5]]])
    lam = np.array([2, 0, 0.44, -2, 0, 0.44])  # squeeze and weight
    a_if = accuracy(G, M, lam, allocate("if", G, M, lam))
    a_ef = accuracy(G, M, lam, allocate("ef", G, M, lam))
    assert a_if.internal < 1e-12 < a_if.external
    assert a_ef.external < a_if.external
    assert a_ef.internal > a_if.internal


# -- the renderer: contacts that come and go, and the adaptive switch -----------------------


def renderer(allocator, **kw):
    obj = SceneObject(ConvexShape.box(np.full(3, 0.05)), Material(200.0), np.zeros(3), np.eye(3))
    act = Actuation([[(0.866, 0, 0.5)], [(-0.866, 0, 0.5)]], "world")
    return Renderer(obj, [0.008, 0.008], act, allocator, **kw)


@pytest.mark.parametrize("allocator", ["if", "ef", "pinv", "adaptive"])
def test_a_finger_lifting_off_changes_no_force_abruptly(allocator):
    # The adaptive switch moves at its own documented rate (dt / time constant); a slow
    # switch isolates what contact geometry does.
    r = renderer(allocator, adaptive=AdaptiveState(time_constant_s=10.0))
    path = np.linspace(0.031, 0.036, 5001)  # index finger leaves the +x face at 0.033
    prev = None
    worst = 0.0
    for x in path:
        r.step(np.array([[-0.02, 0.0, 0.0], [x, 0.0, 0.0]]), np.zeros((2, 3)))
        f = r.frame.rendered_force.copy()
        if prev is not None:
            worst = max(worst, float(np.abs(f - prev).max()))
        prev = f
    # 5 um steps at 200 N/m move a force by 1 mN; an abrupt change would be ~1 N.
    assert worst < 0.01


def test_onset_blend_matters_for_if():
    with_blend = renderer("if")
    without = renderer("if", robust=Robustness(contact_onset_n=0.0))
    jumps = []
    for r in (with_blend, without):
        forces = []
        for x in (0.032999, 0.033001):
            r.step(np.array([[-0.02, 0.0, 0.0], [x, 0.0, 0.0]]), np.zeros((2, 3)))
            forces.append(r.frame.rendered_force[0].copy())
        jumps.append(np.abs(forces[1] - forces[0]).max())
    assert jumps[0] < 1e-3 < 0.1 < jumps[1]


def test_adaptive_switches_continuously_from_squeeze_to_push():
    dt, tau = 1e-3, 0.05
    r = renderer("adaptive", adaptive=AdaptiveState(0.2, 0.6, tau), dt=dt)
    r_if, r_ef = renderer("if"), renderer("ef")
    alphas, forces = [], []
    for k in range(3000):
        # The thumb presses from 5 to 25 mm deep while the index stays at 5 mm: the net
        # (external) force grows from zero to more than the squeeze.
        ramp = min(1.0, max(0.0, (k - 1000) / 1000))
        pos = np.array([[-0.028 + 0.020 * ramp, 0.0, 0.0], [0.028, 0.0, 0.0]])
        for rr in (r, r_if, r_ef):
            rr.step(pos, np.zeros((2, 3)))
        alphas.append(float(r.frame.alpha))
        forces.append(r.frame.rendered_force.copy())
        if k == 900:  # pure squeeze: adaptive is IF
            np.testing.assert_allclose(
                r.frame.rendered_force, r_if.frame.rendered_force, atol=1e-12
            )
    alphas = np.array(alphas)
    assert alphas[900] == 0.0
    assert alphas[-1] > 0.95  # it did switch to external forces
    np.testing.assert_allclose(
        r.frame.rendered_force,
        (1 - alphas[-1]) * r_if.frame.rendered_force + alphas[-1] * r_ef.frame.rendered_force,
        atol=1e-12,
    )
    assert np.abs(np.diff(alphas)).max() <= dt / tau + 1e-12
    # No jolt: a hard switch would jump by |IF - EF|, here far above the bound.
    assert np.abs(r_if.frame.rendered_force - r_ef.frame.rendered_force).max() > 1.0
    assert np.abs(np.diff(np.array(forces), axis=0)).max() < 0.02


def test_adaptive_alpha_follows_the_tasks_external_ratio():
    """alpha = smoothstep((rho - ratio_low) / (ratio_high - ratio_low)) of rho = |net force| /
    (|net force| + squeeze), reached at once without a lag, by dt / time_constant_s a tick
    with one. Two contacts on the x axis, f = (+-s, n / 2, 0): net n, squeeze s."""
    from hapticd.allocation.contacts import ContactAllocator

    def tick(alloc, n, s, fingers=(1, 1)):
        forces = np.array([[s, n / 2, 0.0], [-s, n / 2, 0.0]])
        pts = np.array([[-0.02, 0.0, 0.0], [0.02, 0.0, 0.0]])
        touching = np.array(fingers, dtype=np.uint8)
        alloc.allocate(touching, pts, pts, forces, np.zeros(3), np.zeros(2), np.zeros((2, 3)))
        return alloc.alpha

    act = Actuation([[(0.0, 0.0, 1.0)], [(0.0, 0.0, 1.0)]])
    alloc = ContactAllocator(act, "adaptive", Robustness(), AdaptiveState(0.2, 0.6, 0.0), 1e-3)
    assert tick(alloc, 1.0, 9.0) == 0.0  # rho 0.1
    assert tick(alloc, 9.0, 1.0) == 1.0  # rho 0.9
    assert tick(alloc, 2.0, 3.0) == pytest.approx(0.5)  # rho 0.4, halfway
    assert tick(alloc, 3.0, 7.0) == pytest.approx(0.15625)  # rho 0.3: smoothstep(1/4)
    lag = ContactAllocator(act, "adaptive", Robustness(), AdaptiveState(time_constant_s=0.1), 0.01)
    assert math.isclose(tick(lag, 1.0, 0.0, (1, 0)), 0.1)  # one contact: rho 1, a tenth of it


@pytest.mark.parametrize("method", ["pinv", "if", "ef", "adaptive"])
@given(grasps(min_p=1, max_p=1, degenerate=True), st.floats(0, 1))
def test_one_contact_closed_form_equals_general_path(method, g, alpha):
    from hapticd.allocation import contact_offsets, one_contact
    from hapticd.allocation.closed import CODES

    G, M, lam = g
    M = block_m([[M[0:3, 0]]])
    r = tuple(contact_offsets(G)[0])
    d = tuple(M[0:3, 0])
    x = one_contact(CODES.index(method), r, d, tuple(lam), EPS, alpha)
    general = allocate(method, G, M, lam, alpha=alpha, fast=False)
    np.testing.assert_allclose([x], general, rtol=0, atol=1e-9 * max(np.abs(lam).max(), 1e-300))
    a, b = accuracy(G, M, lam, np.array([x])), one_contact_residuals(r, d, tuple(lam), x)
    np.testing.assert_allclose(
        b,
        [a.internal, a.external, a.total, a.amplification],
        rtol=1e-9,
        atol=1e-12 * np.abs(lam).max(),
    )
