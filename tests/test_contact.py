"""God-object contact (hapticd.physics.kernels.contact_step, the one source, in the tick's one call:
tests/proxies.py) against analytic results: faces, edges, corners, fast fingers, sliding,
release, fine meshes, and the Gram systems' closed forms (``kernels._gram_mu``)."""

import math
import warnings

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hapticd.allocation.kernels import items
from hapticd.physics import kernels
from hapticd.physics.scene import rpy_matrix
from tests.proxies import MODES, Proxy, box

R = 0.008
HALF = 0.025
BOX = box(np.zeros(3), np.eye(3), [2 * HALF] * 3, inflate=R)
SURF = HALF + R
BOTH = pytest.mark.parametrize("mode", MODES)


def run_path(obstacle, points, mode: str = "compiled"):
    return Proxy([obstacle], mode).walk(points[0], points)


def update(obstacle, proxy, device, mode: str = "compiled"):
    return Proxy([obstacle], mode).step(proxy, device)


@pytest.mark.parametrize("axis", range(3))
@pytest.mark.parametrize("sign", [-1.0, 1.0])
@BOTH
def test_face_penetration_gives_k_d_along_normal(axis, sign, mode):
    k, d = 60.0, 0.004
    n = np.zeros(3)
    n[axis] = sign
    start = n * (SURF + 0.01)
    inside = n * (SURF - d) + np.roll([0.0, 0.003, -0.002], axis)
    res = run_path(BOX, np.linspace(start, inside, 50), mode)[-1]
    assert res.in_contact and res.n_active == 1
    np.testing.assert_allclose(res.normal, n, atol=1e-12)
    f = k * (res.proxy - inside)
    np.testing.assert_allclose(f, k * d * n, atol=1e-12)


def test_proxy_stays_on_entry_face_through_the_middle():
    # Pressing past the centre must not pop the proxy to the far face.
    path = np.linspace([-0.06, 0.0, 0.0], [0.02, 0.0, 0.0], 200)
    for res in run_path(BOX, path)[70:]:
        assert res.proxy[0] == pytest.approx(-SURF)


@BOTH
def test_fast_finger_cannot_pop_through(mode):
    res = update(BOX, np.array([-0.1, 0.0, 0.0]), np.array([0.1, 0.0, 0.0]), mode)
    np.testing.assert_allclose(res.proxy, [-SURF, 0.0, 0.0], atol=1e-15)
    assert res.in_contact


def test_edge_and_corner_entry_keeps_the_entry_face():
    # On a sharp (inflated) box a device inside always projects onto the face it
    # entered: the proxy stays on that face, the force along its normal.
    for target in ([1, 1, 0], [1, 1, 1]):
        t = np.array(target, dtype=float)
        start = t * (SURF + 0.01) + np.array([0.0005, 0, 0])  # just off the diagonal: enters +x
        inside = t * (SURF - 0.003)
        res = run_path(BOX, np.linspace(start, inside, 40))[-1]
        assert res.n_active == 1
        np.testing.assert_allclose(res.normal, [1, 0, 0], atol=1e-12)
        np.testing.assert_allclose(res.proxy - inside, [0.003, 0, 0], atol=1e-12)


def test_two_plane_projection_is_the_edge_line():
    normals, offsets = BOX
    # Planes 0 (+x) and 1 (+y): the closest point on their intersection line.
    x, mu = project((0.0, 0.0, 0.01), normals[[0, 1]], offsets[[0, 1]])
    np.testing.assert_allclose(x, [SURF, SURF, 0.01], atol=1e-15)
    np.testing.assert_allclose(mu, [SURF, SURF], atol=1e-15)
    x, mu = project((0.0, 0.0, 0.0), normals[[0, 1, 2]], offsets[[0, 1, 2]])
    np.testing.assert_allclose(x, [SURF] * 3, atol=1e-15)


@BOTH
def test_proxy_wraps_around_a_corner_when_the_device_is_outside(mode):
    res = update(BOX, np.array([0.05, 0.0, 0.0]), np.array([0.0, 0.05, 0.0]), mode)
    assert not res.in_contact
    np.testing.assert_allclose(res.proxy, [0.0, 0.05, 0.0])


def test_contact_releases_when_finger_leaves():
    path = np.concatenate(
        [
            np.linspace([-0.06, 0, 0], [-0.02, 0, 0], 50),
            np.linspace([-0.02, 0, 0], [-0.06, 0, 0], 50),
        ]
    )
    results = run_path(BOX, path)
    assert results[49].in_contact
    assert not results[-1].in_contact
    np.testing.assert_allclose(results[-1].proxy, path[-1])


@BOTH
def test_start_inside_is_pushed_out_through_nearest_face(mode):
    res = update(BOX, np.array([0.0, 0.0, 0.03]), np.array([0.0, 0.0, 0.03]), mode)
    np.testing.assert_allclose(res.proxy, [0.0, 0.0, SURF])
    assert res.in_contact


def test_sliding_along_a_face_keeps_one_constraint():
    path = np.linspace([-SURF + 0.003, -0.02, 0.0], [-SURF + 0.003, 0.02, 0.004], 60)
    p = np.array([-SURF - 0.01, -0.02, 0.0])
    p = update(BOX, p, path[0]).proxy
    for x in path:
        res = update(BOX, p, x)
        p = res.proxy
        assert res.n_active == 1
        np.testing.assert_allclose(p, [-SURF, x[1], x[2]], atol=1e-15)


def _inside_depth(obstacle, x):
    return float(np.max(obstacle[0] @ x - obstacle[1]))


rot = arrays(float, (3,), elements=st.floats(-np.pi, np.pi))
walk = arrays(float, (150, 3), elements=st.floats(-0.03, 0.03))


@given(rot, walk)
def test_proxy_never_inside_over_random_fast_trajectories(rpy, steps):
    poly = box([0.01, -0.005, 0.0], rpy_matrix(tuple(rpy)), [0.05, 0.03, 0.04], inflate=R)
    proxy = Proxy([poly])
    x = np.array([0.1, 0.1, 0.1])
    p = x.copy()
    for step in steps:
        x = np.clip(x + step, -0.12, 0.12)  # steps up to 3 cm per tick: very fast fingers
        res = proxy.step(p, x)
        p = res.proxy
        assert _inside_depth(poly, p) >= -1e-12
        if not res.in_contact:
            np.testing.assert_allclose(p, x)
        else:
            assert np.linalg.norm(res.normal) == pytest.approx(1.0)
            # The spring never pulls the finger into the object.
            assert res.normal @ (p - x) >= -1e-12


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("angle", [0.0, 0.52, 1.1, -2.5])
@pytest.mark.parametrize("n_steps", [2001, 5])
def test_frictionless_sliding_on_a_rotated_face_stays_normal(angle, n_steps):
    # The proxy lies on a rotated face only to rounding; the projected target too. A path
    # between them once counted as entering the face at a ratio of two rounding errors and
    # left the proxy up to 7 mm behind a finger sliding at constant depth.
    Rot = _rz(angle)
    stepper = Proxy([box(np.zeros(3), Rot, [0.05, 0.05, 0.05])])
    n, t = Rot[:, 0], Rot[:, 1]
    k, depth = 200.0, 0.002
    proxy = n * 0.06
    for s in np.linspace(-0.02, 0.02, n_steps):
        dev = n * (0.025 - depth) + t * s
        res = stepper.step(proxy, dev)
        proxy = res.proxy
        f = k * (proxy - dev)
        assert res.n_active == 1
        np.testing.assert_allclose(f, k * depth * n, rtol=0, atol=1e-9 * k * depth)


@BOTH
def test_a_path_parallel_to_a_far_plane_divides_nothing_out_of_range(mode):
    # A device step whose z is a subnormal number: the path is parallel to the ground to
    # within 5e-324 m. Its crossing time with the ground lies far off the segment and was
    # computed anyway: an overflow (a RuntimeWarning with numpy scalars).
    proxy = Proxy([([(0.0, 0.0, 1.0)], [-0.017])], mode)
    dev = (0.03, -0.01, -5e-324)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = proxy.step((0.05, 0.0, 0.0), dev)
    assert tuple(res.proxy) == dev and not res.active


def test_a_fast_finger_over_a_fine_mesh_ends_on_the_projection():
    # 2 cm per tick over an icosphere of 3.3 cm radius (1280 faces):
    # the proxy slides off a face and re-enters the next several times in one update, and
    # must still end at the device's projection onto the face that holds it.
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3, radius=0.033)
    N = m.face_normals
    off = np.einsum("ij,ij->i", N, m.vertices[m.faces[:, 0]])
    normals, offsets = N, off
    proxy = Proxy([(normals, offsets)])
    rng = np.random.default_rng(4)
    u = np.array([1.0, 0.0, 0.0])
    p = (0.05, 0.0, 0.0)
    for _ in range(400):
        u = u + rng.normal(size=3) * 0.02 / 0.03
        u /= np.linalg.norm(u)
        dev = u * (off.min() - 0.002)  # 2 mm inside every face
        res = proxy.step(p, dev)
        p = res.proxy
        assert len(res.active) == 1
        i = res.active[0][1]
        n = np.array(normals[i])
        want = dev + (offsets[i] - n @ dev) * n
        np.testing.assert_allclose(p, want, rtol=0, atol=1e-15)


# -- the Gram systems' closed forms (kernels._gram_mu, compiled into contact_step) --------


def gram(ns, rhs) -> list[float]:
    """mu (k,) solving N N^T mu = rhs for k = 1-3 unit normals ``ns`` (kernels._gram_mu)."""
    k = len(ns)
    planes = np.zeros((k, kernels.PLANE_COLUMNS))
    planes[:, 0:3] = ns
    state = np.zeros((1, kernels.CONTACT_STATE))
    state[0, kernels._C_ACTIVE : kernels._C_ACTIVE + k] = range(k)
    state[0, kernels._C_RHS : kernels._C_RHS + k] = rhs
    # As the uncompiled kernel runs it: on memoryviews (Python floats, not numpy scalars).
    kernels._gram_mu(items(planes), items(state), 0, k, kernels._C_ACTIVE)
    return state[0, kernels._C_MU : kernels._C_MU + k].tolist()


def project(dev, ns, offsets) -> tuple[np.ndarray, list[float]]:
    """The closest point x to ``dev`` on the planes n . x = d (all of them) and the
    multipliers, x - dev = sum mu n: contact_step's projection."""
    N, d = np.asarray(ns, dtype=float), np.asarray(offsets, dtype=float)
    mu = gram(N, d - N @ np.asarray(dev, dtype=float))
    return np.asarray(dev, dtype=float) + N.T @ np.array(mu), mu


@st.composite
def plane_sets(draw, singular: bool) -> tuple[list, list, tuple]:
    """2 or 3 unit normals, offsets (m) and a device point. ``singular``: two of them
    (nearly) parallel or antiparallel, or three (nearly) in one plane; else well apart."""
    from tests.strategies import unit_vectors

    k = draw(st.integers(2, 3))
    ns = [draw(unit_vectors()) for _ in range(k)]
    if singular:
        tilt = draw(st.sampled_from([0.0, 1e-15, 1e-9]) | st.floats(0.0, 1e-5))
        if k == 2 or draw(st.booleans()):
            sign = draw(st.sampled_from([1.0, -1.0]))
            ns[1] = sign * ns[0] + tilt * draw(unit_vectors())
        else:  # the third in the plane of the first two
            a, b = draw(st.floats(-1.0, 1.0)), draw(st.floats(-1.0, 1.0))
            ns[2] = a * ns[0] + b * ns[1] + tilt * draw(unit_vectors())
            assume(np.linalg.norm(ns[2]) > 0.1)
        ns = [n / np.linalg.norm(n) for n in ns]
    else:
        N = np.array(ns)
        assume(np.linalg.det(N @ N.T) > 0.05)
    offsets = [draw(st.floats(-0.05, 0.05)) for _ in range(k)]
    dev = tuple(draw(st.floats(-0.05, 0.05)) for _ in range(3))
    return [tuple(map(float, n)) for n in ns], offsets, dev


@given(plane_sets(singular=False))
def test_the_closed_form_projection_is_lstsqs_on_well_conditioned_planes(case):
    ns, offsets, dev = case
    x, mu = project(dev, ns, offsets)
    N = np.array(ns)
    r = np.array(offsets) - N @ np.array(dev)
    want, *_ = np.linalg.lstsq(N @ N.T, r, rcond=1e-12)
    np.testing.assert_allclose(mu, want, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(x, np.array(dev) + N.T @ want, rtol=0, atol=1e-12)
    # On every plane, and the multipliers decompose x - dev (least squares, the same
    # solution for a point on the planes).
    np.testing.assert_allclose(N @ np.array(x), offsets, rtol=0, atol=1e-12)
    got = gram(N, N @ (np.array(x) - np.array(dev)))
    lsq, *_ = np.linalg.lstsq(N.T, np.array(x) - np.array(dev), rcond=1e-12)
    np.testing.assert_allclose(got, lsq, rtol=1e-9, atol=1e-12)


@given(plane_sets(singular=True))
def test_singular_plane_sets_take_a_finite_rule_on_the_planes_they_keep(case):
    """(Nearly) parallel or coplanar normals: finite multipliers, at most two planes kept
    (multiplier not zero) and the projection on those; two near-parallel planes keep the
    one with the larger right-hand side."""
    ns, offsets, dev = case
    x, mu = project(dev, ns, offsets)
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(mu))
    N = np.array(ns)
    r = np.array(offsets) - N @ np.array(dev)
    G = N @ N.T
    c = float(N[0] @ N[1])
    if len(ns) == 2 and 1.0 - c**2 <= kernels._GRAM_MIN:
        # G's pseudo-inverse without its small eigenvalue: lstsq's for parallel planes.
        assert mu[1] == math.copysign(1.0, c) * mu[0]
        if abs(c) == 1.0:
            want, *_ = np.linalg.lstsq(G, r, rcond=1e-9)
            np.testing.assert_allclose(mu, want, rtol=1e-9, atol=1e-15)
    if np.linalg.det(G) <= 0.5 * kernels._GRAM_MIN:
        # No inverse of the singular system: multipliers bounded by the right-hand sides
        # over the determinant of the pair the rule solves (> _GRAM_MIN).
        assert np.max(np.abs(mu)) <= 2.0 * np.max(np.abs(r)) / kernels._GRAM_MIN


@st.composite
def near_degenerate_scenes(draw) -> tuple[list, list]:
    """A box (half size 2-4 cm, turned) and one to three half-space obstacles (a ground, a
    wall) whose planes are nearly parallel or antiparallel (0 to 1e-5 rad) to the box's
    faces, some flush with them: a box sunk to its top in the ground, a finger squeezed
    between the box's bottom and the ground; and a device path around the box's edges and
    corners, in and out."""
    from tests.strategies import unit_vectors

    half = draw(st.floats(0.02, 0.04))
    rot = rpy_matrix(tuple(draw(st.floats(-3.0, 3.0)) for _ in range(3)))
    cube = box(np.zeros(3), rot, np.full(3, 2 * half))
    obstacles = [cube]
    for _ in range(draw(st.integers(1, 3))):
        base = cube[0][draw(st.integers(0, 5))]
        sign = draw(st.sampled_from([1.0, -1.0]))
        tilt = draw(st.sampled_from([0.0, 1e-12]) | st.floats(0.0, 1e-5))
        n = sign * base + tilt * draw(unit_vectors())
        n = n / np.linalg.norm(n)
        # Flush with the face (sign +1), or just past it (the gap under the box: -1).
        offset = sign * half + draw(st.sampled_from([0.0]) | st.floats(-0.002, 0.002))
        obstacles.append(([tuple(map(float, n))], [float(offset)]))
    path = []
    for _ in range(draw(st.integers(2, 12))):
        signs = np.array([draw(st.sampled_from([-1.0, 0.0, 1.0])) for _ in range(3)])
        scale = draw(st.floats(0.6, 1.2))
        noise = np.array([draw(st.floats(-0.003, 0.003)) for _ in range(3)])
        path.append(tuple(map(float, rot @ (signs * half * scale) + noise)))
    return obstacles, path


@given(near_degenerate_scenes())
def test_near_degenerate_creases_keep_the_proxy_finite_and_outside(case):
    obstacles, path = case
    proxy = Proxy(obstacles)
    p = path[0]
    outside = False  # a start inside nested obstacles may take more than one push-out
    for dev in path:
        res = proxy.step(p, dev)
        p = res.proxy
        assert np.all(np.isfinite(p)) and np.all(np.isfinite(res.mu))
        assert len(res.active) <= 3
        depth = min(
            float(np.max(np.array(normals) @ np.array(p) - offsets))
            for normals, offsets in obstacles
        )
        # Once outside every obstacle, the proxy stays outside.
        assert not outside or depth >= -1e-12
        outside = outside or depth >= 0.0


def test_a_finger_between_two_faces_that_face_each_other_is_pushed_by_one():
    """The box's bottom (solid above z = 0) and the ground (solid below z = -1 mm),
    antiparallel: the device 0.2 mm inside the box gets opposite multipliers (the
    ground's negative: released), not a blown-up inverse."""
    planes = [(0.0, 0.0, -1.0), (0.0, 0.0, 1.0)]
    x, mu = project((0.0, 0.0, 0.0002), planes, [0.0, -0.001])
    assert mu[0] == pytest.approx(0.00035, abs=1e-15) and mu[1] == -mu[0]
    assert tuple(x) == pytest.approx((0.0, 0.0, -0.0005), abs=1e-18)  # the gap's middle
