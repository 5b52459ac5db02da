"""allocate_many: a batch of grasps gives what the independent oracle (tests.allocation_oracle:
the robust methods by SVD, grasp by grasp) or the seed's formula gives one by one, for every
method; allocate() is the same definition with a batch of one."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from hapticd.allocation import (
    METHODS,
    ROBUST_METHODS,
    AllocationError,
    Robustness,
    allocate,
    allocate_many,
    batch,
    two_contact_structure,
)
from hapticd.allocation.batch import EXACT_METHODS
from hapticd.allocation.cases import SWEEPS, block_actuation, sweep
from hapticd.allocation.grasp import grasp_matrix, null_space_basis
from tests.allocation_oracle import robust_allocation

KINDS = (
    "none",
    "none",
    "none",
    "coincident",
    "collinear",
    "at_center",
    "parallel_dirs",
    "normal_dirs",
    "vertical",
    "tilt",
    "zero",
)


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _directions(rng, counts, pts, kind, tiny):
    dirs = [[unit(rng.normal(size=3)) for _ in range(k)] for k in counts]
    if kind == "parallel_dirs" and counts[0] >= 2:
        dirs[0][1] = unit(dirs[0][0] + rng.normal(size=3) * tiny)
    elif kind in ("normal_dirs", "vertical", "tilt") and len(counts) >= 2:
        e = unit(pts[1] - pts[0]) if np.linalg.norm(pts[1] - pts[0]) > 0 else np.array([1.0, 0, 0])
        up = np.array([0, 0, 1.0])
        base = [e, -e] if kind == "normal_dirs" else [up, up]
        tilt = tiny if kind == "tilt" else 0.0
        dirs[0][0] = unit(base[0] + tilt * e)
        dirs[1][0] = unit(base[1] - tilt * e)
    return block_actuation(dirs)


@st.composite
def batches(draw, min_p=1, max_p=3, counts=None):
    """(G (N, 6, 3p), M_a (N, 3p, r) or shared (3p, r), lam (N, 3p)): mostly generic grasps,
    some degenerate (coincident or collinear contacts, dependent or singular directions)."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    p = draw(st.integers(min_p, max_p))
    if counts is None:
        # One direction per finger half of the time: the closed form's case.
        one_each = draw(st.booleans())
        counts = [1] * p if one_each else [draw(st.integers(1, 3)) for _ in range(p)]
    n_grasps = draw(st.integers(1, 6))
    shared = draw(st.booleans())
    scale = 10.0 ** draw(st.integers(-9, 3))
    Gs, Ms, lams = [], [], []
    for _ in range(n_grasps):
        kind = draw(st.sampled_from(KINDS))
        tiny = 10.0 ** draw(st.integers(-16, -2))
        pts = rng.uniform(-0.06, 0.06, (p, 3))
        center = rng.uniform(-0.03, 0.03, 3)
        lam = rng.normal(size=3 * p) * scale
        if kind == "coincident" and p >= 2:
            pts[1] = pts[0] + rng.normal(size=3) * tiny * draw(st.sampled_from([0.0, 1.0]))
        elif kind == "collinear" and p >= 3:
            pts = pts[0] + np.outer(rng.uniform(-0.05, 0.05, p), unit(rng.normal(size=3)))
        elif kind == "at_center":
            center = pts[0].copy()
        elif kind == "zero":
            lam[:] = 0.0
        Gs.append(grasp_matrix(pts, center))
        Ms.append(_directions(rng, counts, pts, kind, tiny))
        lams.append(lam)
    M = Ms[0] if shared else np.array(Ms)
    return np.array(Gs), M, np.array(lams)


def one_by_one(method, G, M, lam, alpha=0.0, robust=None):
    """The oracle grasp by grasp: the SVD definition (robust methods) or the seed's formula."""
    rb = Robustness() if robust is None else robust
    a = np.broadcast_to(np.asarray(alpha, dtype=float), (G.shape[0],))
    Ms = np.broadcast_to(M, (G.shape[0], *M.shape[-2:]))
    rows = [
        robust_allocation(method, G[i], Ms[i], lam[i], rb, float(a[i]))
        if method in ROBUST_METHODS
        else allocate(method, G[i], Ms[i], lam[i])
        for i in range(G.shape[0])
    ]
    return np.array(rows).reshape(G.shape[0], M.shape[-1])


def assert_rows_equal(got, ref, lam):
    """Equal to 1e-9 of each grasp's force scale (|lam| or |lam_a|, whichever is larger)."""
    assert got.shape == ref.shape
    scale = np.maximum(np.abs(ref).max(axis=1, initial=0), np.abs(lam).max(axis=1, initial=0))
    err = np.abs(got - ref).max(axis=1, initial=0)
    assert np.all(err <= 1e-9 * scale + 1e-300), (err, scale)


# -- equal to the oracle one by one -----------------------------------------------------------


@pytest.mark.parametrize("method", METHODS)
@given(batches(), st.data())
def test_equals_allocate_one_by_one(method, b, data):
    G, M, lam = b
    n = G.shape[0]
    alpha = data.draw(
        st.one_of(
            st.floats(0, 1),
            st.lists(st.sampled_from([0.0, 0.3, 1.0]) | st.floats(0, 1), min_size=n, max_size=n),
        )
    )
    got = allocate_many(method, G, M, lam, alpha=np.asarray(alpha))
    assert_rows_equal(got, one_by_one(method, G, M, lam, alpha), lam)


@pytest.fixture(scope="module")
def compiled_grasps():
    """allocate_many's robust methods compiled (hapticd.allocation.kernels.allocate_grasps)."""
    from hapticd.physics import jit

    return jit.compile_kernels(["allocate_grasps"])["allocate_grasps"]


def _small_batch() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three two-finger grasps of a 50 mm cube, one direction each, squeezed (N)."""
    pts = np.array([[-0.025, 0.0, 0.0], [0.025, 0.0, 0.01]])
    G = np.stack([grasp_matrix(pts * s, np.zeros(3)) for s in (1.0, 0.8, 1.2)])
    M = block_actuation([[unit([1.0, 0.0, 0.5])], [unit([-1.0, 0.0, 0.5])]])
    lam = np.array([[2.0, 0.0, 1.0, -2.0, 0.0, 1.0]] * 3)
    return G, M, lam


def test_allocate_many_runs_the_compiled_kernel_by_default(compiled_grasps, monkeypatch):
    """Without kernel=, a robust method runs the installed compiler's allocate_grasps (the
    entry point hapticd registers: hapticd.physics.jit's, the kernel it compiles), and
    kernel="python" runs the uncompiled code instead."""
    from importlib.metadata import entry_points

    values = [ep.value for ep in entry_points(group=batch.COMPILERS)]
    assert "hapticd.physics.jit:compiled" in values
    assert batch.default_kernel() is compiled_grasps
    calls = []

    def spy(*args):
        calls.append(args[0])
        return compiled_grasps(*args)

    monkeypatch.setattr(batch, "_DEFAULT", [spy])
    G, M, lam = _small_batch()
    got = allocate_many("if", G, M, lam)
    assert calls == [ROBUST_METHODS.index("if")]
    np.testing.assert_array_equal(got, allocate_many("if", G, M, lam, kernel=compiled_grasps))
    python = allocate_many("if", G, M, lam, kernel=batch.PYTHON)
    assert calls == [ROBUST_METHODS.index("if")]  # not the compiled kernel
    assert_rows_equal(python, got, lam)
    assert np.abs(got).max() > 0.1  # a squeeze the directions can render
    with pytest.raises(AllocationError, match="kernel must be"):
        allocate_many("if", G, M, lam, kernel="numba")


@pytest.mark.parametrize("method", ROBUST_METHODS)
@settings(max_examples=25)  # the oracle's SVDs cost the most here
@given(batches(), st.floats(0, 1))
def test_compiled_equals_the_oracle(compiled_grasps, method, b, alpha):
    """The robust methods compiled grasp by grasp (kernel=: the closed forms and the general
    path the servo loop's kernel runs), and the general path alone (allocate()'s fast=False)."""
    G, M, lam = b
    ref = one_by_one(method, G, M, lam, alpha)
    assert_rows_equal(
        allocate_many(method, G, M, lam, alpha=alpha, kernel=compiled_grasps), ref, lam
    )
    G, M, lam, a = batch.check(method, G, M, lam, alpha)
    general = batch.solve(method, G, M, lam, a, Robustness(), False, compiled_grasps)
    assert_rows_equal(general, ref, lam)


@pytest.mark.parametrize("method", METHODS)
@given(batches(min_p=2, max_p=2, counts=[1, 1]))
def test_other_robustness_parameters(method, b):
    G, M, lam = b
    rb = Robustness(eps=0.35, min_separation_m=0.02)
    got = allocate_many(method, G, M, lam, robust=rb, alpha=0.4)
    assert_rows_equal(got, one_by_one(method, G, M, lam, 0.4, rb), lam)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", list(SWEEPS))
def test_singular_sweeps_equal_one_by_one(name, method):
    probs = sweep(name, n=401)  # passes through t = 0, the singular point
    probs += sweep(name, half_width=1e-6, n=101)  # and close around it
    G, M, lam = (np.array([q[k] for q in probs]) for k in range(3))
    got = allocate_many(method, G, M, lam, alpha=0.5)
    ref = one_by_one(method, G, M, lam, 0.5)
    assert_rows_equal(got, ref, lam)
    if method.endswith("_exact") and SWEEPS[name][1] == method.removesuffix("_exact"):
        # The sweep really reaches the formula's singularity: across the fine part (steps of
        # 2e-8) it jumps, where a continuous map would move by about 1e-8.
        assert np.abs(np.diff(ref[401:], axis=0)).max() > 0.01


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("counts", [[1, 1], [2, 1], [1, 1, 1], [2, 1, 3]])
def test_coincident_contacts_equal_one_by_one(method, counts):
    rng = np.random.default_rng(7)
    p = len(counts)
    Gs, Ms, lams = [], [], []
    for gap in [0.0, 1e-16, 1e-12, 1e-8, 1e-4, 2e-3, 4.9e-3, 5e-3, 5.1e-3, 1e-2]:
        for _ in range(3):
            pts = rng.uniform(-0.04, 0.04, (p, 3))
            pts[1] = pts[0] + gap * unit(rng.normal(size=3))
            Gs.append(grasp_matrix(pts, rng.uniform(-0.02, 0.02, 3)))
            Ms.append(block_actuation([[rng.normal(size=3) for _ in range(k)] for k in counts]))
            lams.append(rng.normal(size=3 * p) * 3.0)
    G, M, lam = np.array(Gs), np.array(Ms), np.array(lams)
    alpha = rng.uniform(0, 1, len(Gs))
    assert_rows_equal(
        allocate_many(method, G, M, lam, alpha=alpha), one_by_one(method, G, M, lam, alpha), lam
    )


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("counts", [[2], [3], [2, 1], [1, 3], [2, 1, 1]])
def test_directions_closing_through_the_threshold_equal_one_by_one(method, counts):
    # The thumb's directions close from 40 degrees apart to parallel, so singular values of
    # M_a, G M_a, B and M_a P cross eps (where the filtered gain changes formula) and 0.
    rng = np.random.default_rng(11)
    p = len(counts)
    Gs, Ms, lams = [], [], []
    for deg in np.linspace(0.0, 40.0, 321):
        th = np.radians(deg)
        pts = np.array([[-0.03, 0, 0], [0.03, 0.01, 0], [0, 0.04, 0.01]])[:p]
        thumb = [(1, 0, 0.5), (np.cos(th), np.sin(th), 0.5), (np.cos(th), 0, 0.5 + np.sin(th))]
        others = [[(-1, 0.2 * k, 0.5), (0, 1, 0), (0, 0, 1)][:c] for k, c in enumerate(counts[1:])]
        Gs.append(grasp_matrix(pts, np.zeros(3)))
        Ms.append(block_actuation([thumb[: counts[0]], *others]))
        lams.append(rng.normal(size=3 * p))
    G, M, lam = np.array(Gs), np.array(Ms), np.array(lams)
    got = allocate_many(method, G, M, lam, alpha=0.5)
    assert_rows_equal(got, one_by_one(method, G, M, lam, 0.5), lam)


@pytest.mark.parametrize("method", METHODS)
def test_closed_form_and_general_grasps_mixed_in_one_batch(method):
    # Two contacts, two directions: block-structured ones take allocate()'s closed form,
    # the others (a direction acting on both fingers) the general path.
    rng = np.random.default_rng(3)
    G = np.array([grasp_matrix(rng.uniform(-0.05, 0.05, (2, 3)), np.zeros(3)) for _ in range(12)])
    M = np.array([block_actuation([[rng.normal(size=3)], [rng.normal(size=3)]]) for _ in range(12)])
    M[1::3] = rng.normal(size=(4, 6, 2))
    assert sum(two_contact_structure(G[i], M[i]) is None for i in range(12)) == 4
    lam = rng.normal(size=(12, 6))
    assert_rows_equal(
        allocate_many(method, G, M, lam, alpha=0.7), one_by_one(method, G, M, lam, 0.7), lam
    )


@pytest.mark.parametrize("method", METHODS)
def test_shared_directions_equal_per_grasp_copies(method):
    rng = np.random.default_rng(5)
    G = np.array([grasp_matrix(rng.uniform(-0.05, 0.05, (3, 3)), np.zeros(3)) for _ in range(20)])
    M = block_actuation([[(1, 0, 0.5)], [(0, 1, 0), (-1, 0, 0.5)], [(0, 0, 1)]])
    lam = rng.normal(size=(20, 9))
    shared = allocate_many(method, G, M, lam, alpha=0.2)
    copies = allocate_many(method, G, np.broadcast_to(M, (20, 9, 4)).copy(), lam, alpha=0.2)
    np.testing.assert_allclose(shared, copies, rtol=1e-12, atol=1e-12)
    assert_rows_equal(shared, one_by_one(method, G, M, lam, 0.2), lam)


# -- linear in lam ------------------------------------------------------------------------------


def _exact_rounding(method: str, G: np.ndarray, M: np.ndarray, lam: np.ndarray) -> float:
    """The size of what the seed's exact formula sums for one grasp, |P| |lam| for each
    pseudoinverse P it applies (N, with |lam| N): its rounding grows with it, so an
    ill-conditioned grasp is linear in lam only to eps times this."""
    n_lam = float(np.linalg.norm(lam))
    if method == "pinv_exact":
        return float(np.linalg.norm(np.linalg.pinv(M), 2)) * n_lam
    if method == "ef_exact":
        return float(np.linalg.norm(np.linalg.pinv(G @ M), 2) * np.linalg.norm(G, 2)) * n_lam
    B = null_space_basis(G).T @ M
    first = float(np.linalg.norm(np.linalg.pinv(B), 2)) if B.size else 0.0
    N_B = null_space_basis(B) if B.size else np.eye(M.shape[1])
    rest = float(np.linalg.norm(np.linalg.pinv(M @ N_B), 2)) if N_B.size else 0.0
    return (first + rest * (1.0 + float(np.linalg.norm(M, 2)) * first)) * n_lam


@pytest.mark.parametrize("method", METHODS)
@given(batches(), st.floats(-1e3, 1e3), st.integers(0, 2**32 - 1))
def test_linear_in_lam(method, b, s, seed):
    G, M, lam = b
    assume(abs(s) > 1e-9)
    lam2 = np.random.default_rng(seed).normal(size=lam.shape) * np.abs(lam).max(initial=1.0)
    x, x2 = (allocate_many(method, G, M, v, alpha=0.6) for v in (lam, lam2))
    scale = np.maximum(np.abs(x).max(axis=1), np.abs(x2).max(axis=1))[:, None]
    scale = np.maximum(scale, np.abs(lam).max(axis=1, keepdims=True))
    if method in EXACT_METHODS:  # within 1e-12 of that bound: a thousand times the sums' eps
        Ms = np.broadcast_to(M, (len(G), *M.shape[-2:]))
        bound = [
            max(_exact_rounding(method, G[k], Ms[k], v[k]) for v in (lam, lam2))
            for k in range(len(G))
        ]
        scale = np.maximum(scale, 1e-3 * np.array(bound)[:, None])
    err_scaled = np.abs(allocate_many(method, G, M, s * lam, alpha=0.6) - s * x)
    assert np.all(err_scaled <= 1e-9 * abs(s) * scale + 1e-300)
    err_sum = np.abs(allocate_many(method, G, M, lam + lam2, alpha=0.6) - (x + x2))
    assert np.all(err_sum <= 1e-9 * scale + 1e-300)


# -- sizes ------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", METHODS)
def test_empty_and_single_batches(method):
    M = block_actuation([[(1, 0, 0.5)], [(-1, 0, 0.5)]])
    for Ma in (M, np.zeros((0, 6, 2))):
        out = allocate_many(method, np.zeros((0, 6, 6)), Ma, np.zeros((0, 6)), alpha=np.zeros(0))
        assert out.shape == (0, 2)
    G = grasp_matrix(np.array([[-0.02, 0, 0], [0.02, 0.001, 0]]), np.zeros(3))
    lam = np.array([1.0, 0.2, 0.3, -1.0, 0, 0.3])
    got = allocate_many(method, G[None], M, lam[None], alpha=0.5)
    assert got.shape == (1, 2)
    assert_rows_equal(got, allocate(method, G, M, lam, alpha=0.5)[None], lam[None])
    # No actuated direction, no contact: nothing to allocate (as allocate()).
    assert allocate_many(method, G[None], np.zeros((6, 0)), lam[None]).shape == (1, 0)
    assert allocate_many(method, np.zeros((3, 6, 0)), np.zeros((0, 2)), np.zeros((3, 0))).shape == (
        3,
        2,
    )


# -- bad input ----------------------------------------------------------------------------------

G2 = np.array([grasp_matrix(np.array([[-0.02, 0, 0], [0.02, 0, 0]]), np.zeros(3))] * 4)
M2 = block_actuation([[(1, 0, 0.5)], [(-1, 0, 0.5)]])
L2 = np.tile([1.0, 0, 0.2, -1.0, 0, 0.2], (4, 1))


@pytest.mark.parametrize(
    ("G", "M", "lam", "match"),
    [
        (G2[0], M2, L2, r"G must have shape \(N, 6, 3p\), got \(6, 6\)"),
        (G2[:, :5], M2, L2, r"G must have shape \(N, 6, 3p\), got \(4, 5, 6\)"),
        (G2[:, :, :5], M2, L2, r"G must have shape \(N, 6, 3p\), got \(4, 6, 5\)"),
        (G2, M2[:3], L2, r"M_a must have shape \(4, 6, r\) or shared \(6, r\).*got \(3, 2\)"),
        (G2, np.stack([M2] * 3), L2, r"M_a must have shape \(4, 6, r\).*got \(3, 6, 2\)"),
        (G2, M2[None, None], L2, r"M_a must have shape.*got \(1, 1, 6, 2\)"),
        (G2, M2, L2[:3], r"lam must have shape \(4, 6\) to match G \(4, 6, 6\), got \(3, 6\)"),
        (G2, M2, L2.reshape(-1), r"lam must have shape \(4, 6\).*got \(24,\)"),
    ],
)
def test_bad_shapes_name_the_argument_and_the_expected_shape(G, M, lam, match):
    for method in ("if", "pinv_exact"):
        with pytest.raises(ValueError, match=match):
            allocate_many(method, G, M, lam)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_input_names_the_argument_and_the_grasp(bad):
    for name in ("G", "M_a", "lam"):
        G, M, lam = G2.copy(), np.stack([M2] * 4), L2.copy()
        {"G": G, "M_a": M, "lam": lam}[name][2, 4, ...] = bad
        for method in METHODS:
            with pytest.raises(AllocationError, match=rf"{name} contains NaN or inf \(grasp 2\)"):
                allocate_many(method, G, M, lam)
    G = G2.copy()
    G[3, 0, 0], G[3, 1, 1] = np.inf, -np.inf  # inf - inf in a sum is NaN: still found
    with pytest.raises(AllocationError, match=r"G contains NaN or inf \(grasp 3\)"):
        allocate_many("pinv", G, M2, L2)
    M = M2.copy()
    M[1, 0] = bad
    with pytest.raises(AllocationError, match="M_a contains NaN or inf"):
        allocate_many("ef", G2, M, L2)


def test_bad_method_and_alpha():
    with pytest.raises(AllocationError, match="unknown allocator 'foo'"):
        allocate_many("foo", G2, M2, L2)
    for alpha in (-0.1, 1.5, np.nan, [0.2, 0.3, 2.0, 0.0]):
        with pytest.raises(AllocationError, match=r"alpha must be in \[0, 1\]"):
            allocate_many("adaptive", G2, M2, L2, alpha=np.asarray(alpha))
    with pytest.raises(AllocationError, match=r"alpha must be a scalar or have shape \(4,\)"):
        allocate_many("adaptive", G2, M2, L2, alpha=np.zeros(3))
    # The other methods ignore alpha, as allocate() does.
    np.testing.assert_array_equal(
        allocate_many("if", G2, M2, L2, alpha=np.zeros(3)), allocate_many("if", G2, M2, L2)
    )


# -- the closed forms on degenerate grasps -----------------------------------------------------

_SMALL = st.floats(-0.05, 0.05, allow_nan=False, allow_infinity=False)
_DIR = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
_FORCE = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)


@st.composite
def _two_contact_grasps(draw):
    """Two contacts with one direction each, often degenerate: coincident contacts, contacts
    min_separation_m apart, parallel or vanishing directions, zero forces."""
    r1 = draw(st.tuples(_SMALL, _SMALL, _SMALL))
    r2 = draw(
        st.tuples(_SMALL, _SMALL, _SMALL)
        | st.just(r1)
        | st.just((r1[0] + 0.005, r1[1], r1[2]))  # exactly min_separation_m apart
    )
    d1 = draw(st.tuples(_DIR, _DIR, _DIR))
    d2 = draw(st.tuples(_DIR, _DIR, _DIR) | st.just(d1) | st.just((0.0, 0.0, 0.0)))
    l1 = draw(st.tuples(_FORCE, _FORCE, _FORCE) | st.just((0.0, 0.0, 0.0)))
    l2 = draw(st.tuples(_FORCE, _FORCE, _FORCE))
    return r1, r2, d1, d2, l1, l2


@settings(max_examples=50)  # each example: up to 12 grasps, 3 methods, the oracle's SVDs
@given(st.lists(_two_contact_grasps(), min_size=1, max_size=12))
def test_the_closed_forms_equal_the_oracle_on_degenerate_grasps(compiled_grasps, grasps):
    """Two contacts with one direction each take the closed forms, compiled or not: what the
    oracle gives, whichever branch each grasp takes."""
    G = np.array([grasp_matrix(np.array(g[:2]), np.zeros(3)) for g in grasps])
    M = np.zeros((len(grasps), 6, 2))
    M[:, 0:3, 0], M[:, 3:6, 1] = [g[2] for g in grasps], [g[3] for g in grasps]
    lam = np.array([g[4] + g[5] for g in grasps])
    for method in ("pinv", "if", "ef"):
        ref = one_by_one(method, G, M, lam)
        for kernel in (batch.PYTHON, None, compiled_grasps):
            assert_rows_equal(allocate_many(method, G, M, lam, kernel=kernel), ref, lam)
