"""Frictionless god-object contact is exactly conservative, in any orientation.

On a face the force is k x depth along the face normal whatever the tangential motion;
near edges and corners the proxy is the device's projection onto the active planes (in
a concave corner: onto the free region) and the force k (projection - device); a closed
loop of the finger does no work. Friction on a rotated face still sticks and slips.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hapticd.allocation.actuation import Actuation
from hapticd.daemon.build import mesh_shape
from hapticd.physics.render import Renderer
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject, rpy_matrix
from tests.proxies import Obstacle, Proxy

K = 200.0  # N/m
RADIUS = 0.008  # m
REL = 1e-9  # the force's error relative to k x depth

rpy = arrays(float, (3,), elements=st.floats(-np.pi, np.pi))
position = arrays(float, (3,), elements=st.floats(-0.05, 0.05))
# Up to 8 barycentric weights per point (a face has 3 or more vertices); 12 points per path:
# consecutive points anywhere on the face, so the tangential steps are large.
weights = arrays(float, (12, 8), elements=st.floats(0.0, 1.0))


@pytest.fixture(scope="module")
def meshes(tmp_path_factory) -> dict[str, ConvexShape]:
    """Convex shapes read by hapticd.daemon.build.mesh_shape: 80 planes, 1280 planes and an
    irregular hull."""
    d = tmp_path_factory.mktemp("meshes")
    rng = np.random.default_rng(7)
    made = {
        "icosphere-80": trimesh.creation.icosphere(subdivisions=1, radius=0.03),
        "icosphere-1280": trimesh.creation.icosphere(subdivisions=3, radius=0.03),
        "hull": trimesh.convex.convex_hull(rng.normal(size=(40, 3)) * [0.03, 0.02, 0.025]),
    }
    shapes = {}
    for name, mesh in made.items():
        mesh.export(d / f"{name}.stl")
        shapes[name] = mesh_shape(d / f"{name}.stl")
    assert len(shapes["icosphere-80"].normals) == 80
    assert len(shapes["icosphere-1280"].normals) == 1280
    return shapes


def _face_points(obj: SceneObject, face: int, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points on the inflated face ``face`` of ``obj`` (convex combinations of its vertices,
    shrunk toward its centroid so they stay off its edges) and its unit normal."""
    poly = obj.polytope
    n, d = poly.normals[face], poly.offsets[face]
    verts = obj.vertices_world()
    on = verts[np.abs(verts @ n - d) < 1e-9]
    assert len(on) >= 3
    w = w[:, : len(on)]
    assume(np.all(w.sum(axis=1) > 0.05))
    q = (w / w.sum(axis=1, keepdims=True)) @ on
    c = on.mean(axis=0)
    return c + 0.9 * (q - c) + RADIUS * n, n


def _inflated(obj: SceneObject) -> Obstacle:
    """The object's planes grown by the fingertip's radius."""
    poly = obj.polytope
    return poly.normals, poly.offsets + RADIUS


def _check_face(obj: SceneObject, face: int, w: np.ndarray, depth: float) -> None:
    normals, offsets = _inflated(obj)
    pts, n = _face_points(obj, face, w)
    devices = pts - depth * n
    # Every device point inside every plane: the contact is with this face alone.
    assume(np.all(devices @ normals.T - offsets < -1e-6))
    start = pts.mean(axis=0) + 0.02 * n  # outside, above the face: enters through it
    for x, res in zip(devices, Proxy([(normals, offsets)]).walk(start, devices), strict=True):
        f = K * (res.proxy - x)
        assert res.n_active == 1
        assert np.linalg.norm(f - K * depth * n) <= REL * K * depth


@given(rpy, position, st.integers(0, 5), weights, st.floats(1e-4, 0.006))
def test_a_face_of_a_box_in_any_orientation_pushes_k_depth_along_its_normal(
    angles, pos, face, w, depth
):
    box = ConvexShape.box(np.array([0.05, 0.03, 0.04]))
    _check_face(SceneObject(box, Material(K), pos, rpy_matrix(tuple(angles))), face, w, depth)


@settings(max_examples=150)
@given(
    st.sampled_from(["icosphere-80", "icosphere-1280", "hull"]),
    rpy,
    position,
    st.integers(0, 10_000),
    weights,
    st.floats(1e-4, 0.003),
)
def test_a_face_of_a_convex_mesh_pushes_k_depth_along_its_normal(
    meshes, name, angles, pos, face, w, depth
):
    shape = meshes[name]
    obj = SceneObject(shape, Material(K), pos, rpy_matrix(tuple(angles)))
    _check_face(obj, face % len(shape.normals), w, depth)


@pytest.mark.parametrize("rpy_deg", [(0.0, 0.0, 30.0), (40.0, 25.0, -70.0)])
def test_the_renderer_sliding_on_a_rotated_face_pushes_k_depth_along_its_normal(rpy_deg):
    # The scene path: the contact stage's own multipliers, through forces and allocation.
    R = rpy_matrix(tuple(np.radians(rpy_deg)))
    box = SceneObject(ConvexShape.box(np.array([0.05, 0.05, 0.05])), Material(K), np.zeros(3), R)
    eye = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
    r = Renderer(Scene(box, [], None), [RADIUS], Actuation([eye], "world"), "pinv")
    n, t, u = R[:, 0], R[:, 1], R[:, 2]
    depth = 0.002
    surf = 0.025 + RADIUS
    press = np.linspace(n * (surf + 0.01), n * (surf - depth), 50)
    s = np.linspace(0.0, 2 * np.pi, 400)
    slide = n * (surf - depth) + np.outer(0.015 * np.sin(s), t) + np.outer(0.01 * np.sin(2 * s), u)
    for i, x in enumerate(np.concatenate([press, slide])):
        r.step(x[None], np.zeros((1, 3)))
        if i >= len(press):
            f = r.frame.contact_force[0]
            assert np.linalg.norm(f - K * depth * n) <= REL * K * depth
            np.testing.assert_allclose(r.frame.rendered_force[0], f, rtol=0, atol=1e-12)


# -- edges and corners ----------------------------------------------------------------------


def _projection(dev: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Closest point to ``dev`` on the intersection of the planes n . x = d (numpy solve)."""
    mu = np.linalg.solve(normals @ normals.T, offsets - normals @ dev)
    return dev + normals.T @ mu


steps = arrays(float, (80, 3), elements=st.floats(-0.004, 0.004))


@given(rpy, st.integers(0, 7), steps)
def test_around_a_convex_corner_the_proxy_is_the_projection_onto_its_active_plane(
    angles, corner, walk
):
    # A device wandering in and out around a corner of a rotated box, up to 4 mm per tick.
    R = rpy_matrix(tuple(angles))
    obj = SceneObject(ConvexShape.box(np.array([0.05, 0.03, 0.04])), Material(K), np.zeros(3), R)
    normals, offsets = _inflated(obj)
    proxy = Proxy([(normals, offsets)])
    c = obj.vertices_world()[corner]
    c = c + RADIUS * (c / np.linalg.norm(c))  # near the inflated corner
    x = c * 1.3
    p = tuple(x)
    for step in walk:
        x = c + np.clip(x + step - c, -0.008, 0.008)
        res = proxy.step(p, x)
        p = pa = res.proxy
        inside = float(np.max(normals @ x - offsets))
        assert float(np.max(normals @ pa - offsets)) >= -1e-13  # never inside
        if not res.active:
            assert inside >= -1e-13  # no contact only when the device is outside
            np.testing.assert_array_equal(pa, x)
            continue
        # A convex object holds the proxy with one plane; the force is k (projection - device).
        assert len(res.active) == 1 and res.mu[0] > 0.0
        i = res.active[0][1]
        want = _projection(x, normals[[i]], offsets[[i]])
        np.testing.assert_allclose(pa, want, rtol=0, atol=1e-15)
        np.testing.assert_allclose(x + res.mu[0] * normals[i], pa, rtol=0, atol=1e-15)


def _corner_scene(yaw: float, wall_turn: float) -> tuple[list[Obstacle], np.ndarray, np.ndarray]:
    """A cube turned by ``yaw`` about z standing on the ground, and a wall facing its +x face
    turned by ``wall_turn`` more: a concave corner of three planes (cube face, ground,
    wall), inflated by the radius. Returns the obstacles and the corner's three outward
    planes (normals (3, 3), offsets (3,)) whose intersection is the free region there."""
    R = rpy_matrix((0.0, 0.0, yaw))
    cube = SceneObject(ConvexShape.box(np.array([0.05] * 3)), Material(K), np.zeros(3), R)
    ground_z = -0.025 + RADIUS
    m = np.array([np.cos(yaw + wall_turn), np.sin(yaw + wall_turn), 0.0])
    w = 0.045 - RADIUS  # the wall's plane, m . x = w, solid beyond it
    obstacles = [_inflated(cube), ([(0.0, 0.0, 1.0)], [ground_z]), ([-m], [-w])]
    # Free: outside the cube's +x face, above the ground, before the wall.
    free_n = np.array([R[:, 0], [0.0, 0.0, 1.0], -m])
    free_d = np.array([0.025 + RADIUS, ground_z, -w])
    return obstacles, free_n, free_d


def _into_free(corner: np.ndarray, n: np.ndarray) -> np.ndarray:
    """A point 4 mm from ``corner`` into the free region (outside all three planes)."""
    u = np.linalg.solve(n, np.ones(3))
    return corner + 0.004 * u / np.linalg.norm(u)


def _project_on_free(dev: np.ndarray, n: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Projection of ``dev`` onto {x: n_i . x >= d_i}: the set of planes whose projection is
    feasible with multipliers >= 0 (the KKT point, unique for this convex region)."""
    for r in range(4):
        for S in itertools.combinations(range(3), r):
            S = list(S)
            if not S:
                x, mu = dev, np.zeros(0)
            else:
                mu = np.linalg.solve(n[S] @ n[S].T, d[S] - n[S] @ dev)
                x = dev + n[S].T @ mu
            if np.all(mu >= 0.0) and np.all(n @ x >= d - 1e-12):
                return x
    raise AssertionError("no KKT point")


wedge = st.floats(-0.5, 0.5)
corner_walk = arrays(float, (80, 3), elements=st.floats(-0.003, 0.003))


@settings(max_examples=100)  # 80 ticks each, with a KKT enumeration per tick
@given(st.floats(-np.pi, np.pi), wedge, corner_walk)
def test_in_a_concave_corner_the_proxy_is_the_projection_onto_the_free_region(yaw, turn, walk):
    obs, n, d = _corner_scene(yaw, turn)
    assume(abs(turn) > 0.05)  # the wall not parallel to the cube's face (det n = sin turn)
    corner = np.linalg.solve(n, d)
    R = rpy_matrix((0.0, 0.0, yaw))
    assume(abs(R[:, 1] @ corner) < 0.033 - 0.012)  # the corner well inside the cube's face
    x = _into_free(corner, n)
    p = x
    n_obs = [np.asarray(o[0], dtype=float) for o in obs]
    proxy = Proxy(obs)
    for step in walk:
        x = corner + np.clip(x + step - corner, -0.006, 0.006)
        res = proxy.step(p, x)
        p = res.proxy
        np.testing.assert_allclose(p, _project_on_free(x, n, d), rtol=0, atol=1e-15)
        # The force is the active planes' multipliers times their normals: k (proxy - device).
        assert all(m > 0.0 for m in res.mu)
        push = sum((m * n_obs[j][i] for (j, i), m in zip(res.active, res.mu, strict=True)), 0.0)
        np.testing.assert_allclose(x + push, p, rtol=0, atol=1e-15)


def test_a_proxy_inside_the_wall_of_an_acute_corner_is_pushed_out_of_everything():
    # A first tick with the proxy 0.9 mm inside the wall, 14 degrees from the cube's face:
    # a push out of the wall lands in the cube, the push out of the cube back in the wall,
    # and so on, shrinking by cos 14 deg a round; the pushes now go onto their crease.
    obs, n, d = _corner_scene(0.0, 0.25)
    corner = np.linalg.solve(n, d)
    dev = corner + np.array([0.0, 0.005, 0.0])
    start = dev + 0.01 * (n[0] + n[1] + n[2])
    wall_n, wall_d = np.array(obs[2][0]), np.array(obs[2][1])
    assert float(np.max(wall_n @ start - wall_d)) < -5e-4
    res = Proxy(obs).step(start, dev)
    for normals, offsets in obs:
        assert float(np.max(np.array(normals) @ np.array(res.proxy) - offsets)) >= -1e-13
    np.testing.assert_allclose(res.proxy, _project_on_free(dev, n, d), rtol=0, atol=1e-15)


# -- closed loops do no work ----------------------------------------------------------------


def _loop_work(step, path: np.ndarray) -> tuple[float, float]:
    """Work (J) of f = k (proxy - device) along the closed ``path`` (trapezoids), and its
    tolerance.

    Along a step whose two ends have the same active planes the force is affine in the
    position, so the trapezoid is exact and only rounding remains: the proxy is on its
    planes to ~1e-17 m, so each f . dx is off by at most k 1e-15 m |dx| (a margin of 100).
    A step on which the active set changes has a kink: f . dx along it has a slope between
    -k |dx|^2 and 0 (f = -grad of k/2 dist^2 to a convex region), so the trapezoid is off by
    at most k |dx|^2 / 8.
    """
    forces, sets = [], []
    for x in path:
        proxy, active = step(x)
        forces.append(K * (proxy - x))
        sets.append(active)
    f = np.array(forces)
    dx = np.diff(path, axis=0)
    work = float(np.sum(0.5 * (f[1:] + f[:-1]) * dx))
    length = np.linalg.norm(dx, axis=1)
    kinks = np.array([a != b for a, b in itertools.pairwise(sets)])
    tol = K * 1e-15 * float(length.sum()) + K / 8 * float(np.sum(length[kinks] ** 2))
    return work, tol


def _polygon(corners: np.ndarray, per_side: int) -> np.ndarray:
    """The closed polygon through ``corners``, each side cut into ``per_side`` steps."""
    ring = np.vstack([corners, corners[:1]])
    s = np.linspace(0.0, 1.0, per_side, endpoint=False)[:, None]
    sides = [a + s * (b - a) for a, b in itertools.pairwise(ring)]
    return np.vstack([*sides, corners[:1]])


def _stepper(obstacles: list[Obstacle], start: np.ndarray):
    """One step of a proxy carried from step to step: (proxy, its active planes)."""
    state = {"p": start}
    proxy = Proxy(obstacles)

    def step(x: np.ndarray) -> tuple[np.ndarray, tuple]:
        res = proxy.step(state["p"], x)
        state["p"] = res.proxy
        return res.proxy, tuple(sorted(res.active))

    return step


loop_corners = arrays(float, (5, 3), elements=st.floats(0.0, 1.0))


@settings(max_examples=100)
@given(rpy, st.integers(0, 5), loop_corners)
def test_a_closed_loop_inside_a_face_does_no_work(angles, face, c):
    R = rpy_matrix(tuple(angles))
    obj = SceneObject(ConvexShape.box(np.array([0.05, 0.03, 0.04])), Material(K), np.zeros(3), R)
    pts, n = _face_points(obj, face, np.column_stack([c[:, :2], 1 - c[:, :2]]))
    corners = pts - (0.0002 + 0.006 * c[:, 2:3]) * n  # 0.2 to 6.2 mm deep
    path = _polygon(corners, 200)
    step = _stepper([_inflated(obj)], path[0] + 0.01 * n)
    step(path[0])  # in through the face
    work, tol = _loop_work(step, path)
    assert abs(work) <= tol, (work, tol)


@settings(max_examples=100)
@given(rpy, st.integers(0, 11), st.booleans(), arrays(float, (4, 3), elements=st.floats(0.0, 1.0)))
def test_a_closed_loop_across_an_edge_does_no_work(angles, edge, swap, c):
    # A loop that enters face A near its edge with face B, passes under B (nearer to B than
    # to A: the proxy stays on A, the face it entered), along the edge, and leaves through A.
    R = rpy_matrix(tuple(angles))
    size = np.array([0.05, 0.03, 0.04])
    obj = SceneObject(ConvexShape.box(size), Material(K), np.zeros(3), R)
    a, b = [(0, 1), (1, 2), (2, 0)][edge % 3]
    if swap:
        a, b = b, a
    sa, sb = [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)][edge // 3]
    na, nb, along = sa * R[:, a], sb * R[:, b], R[:, 3 - a - b]
    half = 0.5 * size + RADIUS
    e = na * half[a] + nb * half[b]  # a point on the inflated edge
    alpha = np.array([-0.003, *(0.001 + 0.008 * c[1:, 0])])  # depth under A (outside first)
    beta = 0.0005 + 0.008 * c[:, 1]  # depth under B: always in, so never out through B
    beta[2] = 0.3 * alpha[2]  # nearer to B than to A
    gamma = (c[:, 2] - 0.5) * 0.02  # along the edge, clear of its ends
    corners = e - np.outer(alpha, na) - np.outer(beta, nb) + np.outer(gamma, along)
    path = _polygon(corners, 250)  # back to the first corner: out through A
    step = _stepper([_inflated(obj)], path[0])
    work, tol = _loop_work(step, path)
    assert abs(work) <= tol, (work, tol)


@settings(max_examples=100)
@given(st.floats(-np.pi, np.pi), wedge, arrays(float, (5, 3), elements=st.floats(-1.0, 1.0)))
def test_a_closed_loop_around_a_concave_corner_does_no_work(yaw, turn, c):
    obs, n, d = _corner_scene(yaw, turn)
    assume(abs(turn) > 0.05)  # the wall not parallel to the cube's face (det n = sin turn)
    corner = np.linalg.solve(n, d)
    R = rpy_matrix((0.0, 0.0, yaw))
    assume(abs(R[:, 1] @ corner) < 0.033 - 0.012)
    path = _polygon(corner + 0.005 * c, 300)  # in and out of the cube, ground and wall
    step = _stepper(obs, _into_free(corner, n))
    step(path[0])
    work, tol = _loop_work(step, path)
    assert abs(work) <= tol, (work, tol)


# -- friction on a rotated face ---------------------------------------------------------------


@pytest.mark.parametrize("rpy_deg", [(0.0, 0.0, 30.0), (25.0, -40.0, 65.0)])
def test_friction_on_a_rotated_face_sticks_then_slips_past_mu(rpy_deg):
    mu_s, mu_d, depth = 0.6, 0.4, 0.003
    R = rpy_matrix(tuple(np.radians(rpy_deg)))
    box = SceneObject(
        ConvexShape.box(np.array([0.05] * 3)), Material(K, 0.0, mu_s, mu_d), np.zeros(3), R
    )
    eye = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
    r = Renderer(Scene(box, [], None), [RADIUS], Actuation([eye], "world"), "pinv")
    n, t = R[:, 0], (R[:, 1] + R[:, 2]) / np.sqrt(2.0)
    surf = 0.025 + RADIUS
    for x in np.linspace(n * (surf + 0.01), n * (surf - depth), 50):
        r.step(x[None], np.zeros((1, 3)))
    base = n * (surf - depth)
    # Along t alone the friction proxy is one number: the anchor's place on t (m).
    anchor, sticks, slips = 0.0, 0, 0
    for s in np.linspace(0.0, 2.1 * mu_s * depth, 241)[1:]:  # no step on a threshold
        r.step((base + s * t)[None], np.zeros((1, 3)))
        f = r.frame.contact_force[0]
        assert abs(f @ n - K * depth) <= REL * K * depth  # the normal part: k depth
        if s - anchor <= mu_s * depth:
            sticks += 1  # the anchor stays: a spring of k
        else:
            anchor = s - mu_d * depth  # slips to mu_d k depth, against the motion
            slips += 1
        np.testing.assert_allclose(
            f - (f @ n) * n, -K * (s - anchor) * t, rtol=0, atol=REL * K * depth
        )
    assert sticks > 100 and slips > 3
