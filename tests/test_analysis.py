"""hapticd.analysis: the seed's (Barbagli & Salisbury) examples reproduced from the pipeline,
the indices, bad input, and ``hapticd analyze``."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from hapticd import recording
from hapticd.allocation.actuation import Actuation
from hapticd.analysis import Pipeline, examples
from hapticd.analysis.pipeline import asymmetry, loop_work_rate, null_directions
from hapticd.cli import main
from hapticd.daemon.build import build_renderer, builtin_trajectory
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject, rpy_matrix
from hapticd.profile import load_profile

ROOT = Path(__file__).resolve().parent.parent
GRASP = ROOT / "configs" / "grasp-stiffness.yaml"
LIFT = ROOT / "configs" / "lift-weight.yaml"
REL = 1e-6


def _close(got: np.ndarray, want: np.ndarray, rel: float = REL) -> None:
    """Equal to ``rel`` relative to the expected matrix's largest entry."""
    scale = max(float(np.max(np.abs(want))), 1e-300)
    assert float(np.max(np.abs(got - want))) <= rel * scale, f"\n{got}\n!=\n{want}"


def _finite(obj) -> bool:
    if isinstance(obj, dict):
        return all(_finite(v) for v in obj.values())
    if isinstance(obj, list | tuple):
        return all(_finite(v) for v in obj)
    if isinstance(obj, float):
        return math.isfinite(obj)
    return True


@pytest.fixture(scope="module")
def grasp() -> Pipeline:
    return Pipeline.from_profile(GRASP)


# -- seed section 4.1: a single point on a tilted wall ------------------------------------------


@pytest.mark.parametrize("deg", [0.0, 10.0, 30.0, 60.0, 85.0])
def test_tilted_wall_reproduces_the_seeds_f_l_and_rendered_matrix(deg):
    a = math.radians(deg)
    wall = examples.tilted_wall(a, k=60.0)
    res = wall.pipeline.linearize_coordinates(wall.coords, wall.inside(0.002), labels=["x", "y"])
    for name in ("pinv", "if"):  # one contact, one direction: both are the projection M_A
        lin = res[name]
        _close(lin.K_full, examples.wall_f_l(a, 60.0))
        _close(lin.K_rendered, examples.wall_rendered(a, 60.0))
        assert (lin.n, lin.s, lin.r) == (2, 2, 1)
        assert (lin.controllability, lin.observability) == (1.0, 0.5)
        assert lin.asymmetry == pytest.approx(math.sin(a) / math.sqrt(2.0), abs=1e-9)
        # The rendered stiffness's antisymmetric part: k sin cos of work per unit loop area.
        assert lin.work_per_area == pytest.approx(60.0 * math.sin(a) * math.cos(a), abs=1e-6)
    assert asymmetry(examples.wall_f_l(a, 60.0)) < 1e-12  # F_L is symmetric: conservative


def test_tilted_wall_at_ninety_degrees_renders_nothing():
    wall = examples.tilted_wall(math.pi / 2)
    lin = wall.pipeline.linearize_coordinates(wall.coords, wall.inside(0.002))["pinv"]
    assert np.all(np.abs(lin.K_rendered) < 1e-9)
    assert lin.asymmetry < 1e-9
    assert lin.null_directions.shape == (2, 2)
    assert np.abs(lin.K_full).max() == pytest.approx(60.0)


@pytest.mark.parametrize("deg", [10.0, 30.0, 45.0, 60.0, 80.0])
def test_tilted_wall_closed_loop_work_is_the_seeds(deg):
    a = math.radians(deg)
    wall = examples.tilted_wall(a, k=60.0)
    path = wall.triangle(0.002)
    want = examples.wall_work(a, 60.0, 0.002)
    work = wall.pipeline.loop_work(path)
    assert work["pinv"].rendered == pytest.approx(want, rel=1e-9)
    assert work["pinv"].rendered > 0  # the seed's path: the wall feels active
    assert abs(work["pinv"].full) < 1e-12 * want  # the full force is conservative
    # The other way round the display absorbs the same energy.
    assert wall.pipeline.loop_work(path[::-1])["pinv"].rendered == pytest.approx(-want, rel=1e-9)


def test_work_per_loop_area_predicts_a_small_loops_work():
    wall = examples.tilted_wall(math.radians(30.0))
    q0 = wall.inside(0.002)
    lin = wall.pipeline.linearize_coordinates(wall.coords, q0)["pinv"]
    u, v = lin.work_plane.T
    side = 1e-4
    corners = [q0, q0 + side * u, q0 + side * (u + v), q0 + side * v, q0]
    qs = [c0 + (c1 - c0) * (i / 10) for c0, c1 in itertools.pairwise(corners) for i in range(10)]
    path = np.array([wall.coords(q) for q in [*qs, q0]])
    work = wall.pipeline.loop_work(path)["pinv"].rendered
    assert work == pytest.approx(lin.work_per_area * side * side, rel=1e-9)


def _rotated_wall(a: float) -> Pipeline:
    """The seed's wall literally: a box turned by alpha about z, the actuator along world y."""
    R = rpy_matrix((0.0, 0.0, a))
    box = SceneObject(
        ConvexShape.box(np.array([0.4, 0.2, 0.4])),
        Material(60.0),
        R @ np.array([0.0, -0.1, 0.0]),
        R,
        fixed=True,
    )
    return Pipeline(
        Scene(box, [], None), [0.0], Actuation([[(0.0, 1.0, 0.0)]]), allocators=["pinv"]
    )


def _plane(q: np.ndarray) -> np.ndarray:
    return np.array([[q[0], q[1], 0.0]])


@pytest.mark.parametrize("deg", [30.0, 60.0])
def test_a_literally_rotated_wall_gives_the_same_matrices(deg):
    a = math.radians(deg)
    lin = _rotated_wall(a).linearize_coordinates(
        _plane, 0.002 * np.array([math.sin(a), -math.cos(a)])
    )
    _close(lin["pinv"].K_full, examples.wall_f_l(a, 60.0))
    _close(lin["pinv"].K_rendered, examples.wall_rendered(a, 60.0))


@pytest.mark.parametrize("deg", [30.0, 60.0])
def test_a_literally_rotated_wall_gives_the_seeds_loop_work(deg):
    a = math.radians(deg)
    qs = examples.tilted_wall(a).triangle_q(0.002)
    work = _rotated_wall(a).loop_work(np.array([_plane(q) for q in qs]))["pinv"]
    assert work.rendered == pytest.approx(examples.wall_work(a, 60.0, 0.002), rel=1e-9)


# -- seed section 4.2: two points on a static rod ---------------------------------------------


@pytest.mark.parametrize(("L", "deg"), [(0.062, 0.0), (0.062, 17.0), (0.0645, -8.0), (0.06, 30.0)])
def test_rod_reproduces_the_seeds_matrices(L, deg):
    a = math.radians(deg)
    r = examples.rod(k=60.0)
    res = r.pipeline.linearize_coordinates(r.coords, [L, a], labels=["L", "alpha"])
    lin = res["pinv"]
    _close(lin.Q_full, examples.rod_forces(L, a, 60.0, r.x_r))
    _close(lin.K_full, examples.rod_f_l(L, a, 60.0, r.x_r))
    _close(lin.K_rendered, examples.rod_rendered(L, a, 60.0, r.x_r))
    assert (lin.n, lin.s, lin.r) == (2, 2, 1)
    assert lin.observability == 0.5
    assert asymmetry(lin.K_full) < 1e-7  # eq. (16) is symmetric
    if deg != 0.0:
        assert lin.asymmetry > 0.0  # eq. (18) is not
    # The seed prints the lower-right entry in N, not N m / rad; the pipeline agrees with
    # the derivative of eq. (14) instead.
    printed = examples.rod_f_l_printed(L, a, 60.0, r.x_r)
    assert not math.isclose(lin.K_full[1, 1], printed[1, 1], rel_tol=1e-3)


# -- the indices ------------------------------------------------------------------------------


def test_full_actuation_renders_a_symmetric_stiffness():
    """Three directions per finger: the device renders every contact force, K_rendered =
    K_full, which is symmetric (a conservative display)."""
    prof = load_profile(GRASP)
    r = build_renderer(prof)
    eye = [[(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]] * 2
    pipe = Pipeline(
        r.scene, r.radii, Actuation(eye, "world"), allocators=["pinv", "if", "ef", "adaptive"]
    )
    # An off-centre grasp: one finger near an edge, pressing two faces' worth of geometry.
    x = np.array([[-0.031, 0.004, 0.01], [0.0305, -0.006, 0.002]])
    res = pipe.linearize(x)
    for name in ("pinv", "if"):
        lin = res[name]
        _close(lin.K_rendered, lin.K_full)
        assert lin.asymmetry < 1e-8
        assert (lin.r, lin.observability) == (6, 1.0)
    wall = examples.tilted_wall(math.radians(30.0))
    point = Pipeline(wall.pipeline.scene, [0.0], Actuation([eye[0]], "world"))
    for lin in point.linearize_coordinates(wall.coords, wall.inside(0.002)).values():
        _close(lin.K_rendered, lin.K_full)
        assert lin.asymmetry < 1e-8


def test_the_grasp_profile_default_configuration(grasp):
    x, how = grasp.grasp_configuration()
    np.testing.assert_allclose(x, [[-0.031, 0.0, 0.0], [0.031, 0.0, 0.0]], atol=1e-15)
    assert "2 mm inside" in how
    res = grasp.linearize(x)
    assert set(res) == {"pinv", "if", "ef", "adaptive"}
    lin = res["pinv"]
    np.testing.assert_allclose(np.diag(lin.K_full), [-60, 0, 0, -60, 0, 0], atol=1e-6)
    assert (lin.n, lin.s, lin.r) == (6, 6, 2)
    assert lin.fd_error < 1e-6
    # Squeezing a fixed cube: the adaptive allocator stays at IF; EF renders nothing.
    _close(res["adaptive"].K_rendered, res["if"].K_rendered, 1e-9)
    np.testing.assert_allclose(res["ef"].rendered_force, 0.0, rtol=0, atol=1e-12)
    # Moving both fingers together sideways changes no rendered force.
    N = lin.null_directions
    side = np.array([0, 1, 0, 0, 1, 0]) / math.sqrt(2.0)
    assert np.linalg.norm(N @ (N.T @ side) - side) < 1e-9


def test_null_directions_are_orthonormal_and_span_the_null_space():
    rng = np.random.default_rng(3)
    B = rng.normal(size=(6, 3))
    K = B @ rng.normal(size=(3, 6))
    N = null_directions(K)
    assert N.shape == (6, 3)
    np.testing.assert_allclose(N.T @ N, np.eye(3), atol=1e-12)
    assert np.abs(K @ N).max() < 1e-9
    np.testing.assert_array_equal(null_directions(np.zeros((6, 6))), np.eye(6))
    assert loop_work_rate(np.zeros((6, 6)))[0] == 0.0


def test_friction_sticks_and_a_given_state_is_honoured():
    pipe = Pipeline.from_profile(LIFT, allocators=["ef"])
    x, _ = pipe.grasp_configuration()
    lin = pipe.linearize(x)["ef"]
    # A sticking fingertip is a spring in every direction.
    np.testing.assert_allclose(lin.K_full, -200.0 * np.eye(6), atol=1e-5)
    state = pipe.settle(x)
    moved = x + np.array([[0.0, 0.0, 0.0005], [0.0, 0.0, 0.0005]])
    full = pipe.forces(moved, state)["ef"].full
    np.testing.assert_allclose(full[:, 2], [-0.1, -0.1], atol=1e-9)  # dragged: friction holds
    fresh = pipe.forces(moved)["ef"].full
    np.testing.assert_allclose(fresh[:, 2], [0.0, 0.0], atol=1e-12)  # pressed straight in


def test_no_contact_gives_zero_matrices_and_no_nan(grasp):
    far = np.array([[-0.2, 0.0, 0.0], [0.2, 0.0, 0.0]])
    for name, lin in grasp.linearize(far).items():
        assert np.all(lin.K_full == 0.0) and np.all(lin.K_rendered == 0.0), name
        assert lin.asymmetry == 0.0 and lin.work_per_area == 0.0
        assert not lin.in_contact.any()
        np.testing.assert_array_equal(lin.null_directions, np.eye(6))
        assert _finite(lin.to_dict())
    for f in grasp.forces(far).values():
        assert np.all(f.full == 0.0) and np.all(f.rendered == 0.0)


def test_the_analysis_leaves_a_live_renderer_alone():
    prof = load_profile(GRASP)
    live, twin = build_renderer(prof), build_renderer(prof)
    x = np.array([[-0.0315, 0.001, 0.0], [0.031, 0.0, 0.0]])
    still = np.zeros((2, 3))
    live.step(x, still)
    twin.step(x, still)
    pipe = Pipeline.from_renderer(live, finger_names=prof.finger_names)
    pipe.linearize(x + 0.001)
    pipe.loop_work(np.array([x, x + 0.0005, x]), state=pipe.settle(x))
    assert pipe.scene is not live.scene
    y = x + np.array([[0.0002, 0.0, 0.0], [-0.0003, 0.0, 0.0]])
    a, b = live.step(y, still), twin.step(y, still)
    assert a.record.tobytes() == b.record.tobytes()


def test_a_state_carries_the_frame_intact():
    pipe = Pipeline.from_profile(LIFT, allocators=["ef"])
    x, _ = pipe.grasp_configuration()
    state = pipe.settle(x)
    again = pipe.settle(x + 1e-4, state)
    frame = again.frame
    np.testing.assert_array_equal(frame.record["device_pos"], x + 1e-4)
    assert frame.device_pos.base is not None  # still a view into the record


def test_from_profile_path_parsed_profile_and_renderer_agree():
    prof = load_profile(GRASP)
    x = np.array([[-0.0305, 0.002, 0.003], [0.031, -0.001, 0.0]])
    a = Pipeline.from_profile(GRASP, allocators=["if"]).linearize(x)["if"]
    b = Pipeline.from_profile(prof, allocators=["if"]).linearize(x)["if"]
    c = Pipeline.from_renderer(build_renderer(prof), allocators=["if"]).linearize(x)["if"]
    np.testing.assert_array_equal(a.K_rendered, b.K_rendered)
    np.testing.assert_array_equal(a.K_rendered, c.K_rendered)
    assert a.labels[:3] == ("thumb.x", "thumb.y", "thumb.z")


# -- bad input --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("x", "match"),
    [
        (np.zeros(6), r"shape \(2, 3\)"),
        (np.zeros((3, 3)), r"shape \(2, 3\)"),
        ([[0, 0], [1, 1]], r"shape \(2, 3\)"),
        ([[-0.03, 0.0, float("nan")], [0.03, 0.0, 0.0]], "non-finite.*thumb"),
        ([[-0.03, 0.0, 0.0], [float("inf"), 0.0, 0.0]], "non-finite.*index"),
        ([[0.03, 0.0, 0.0], [0.03, 0.0, 0.0]], "thumb and index coincide"),
        ("abc", "finger positions"),
    ],
)
def test_bad_configurations_are_value_errors(grasp, x, match):
    with pytest.raises(ValueError, match=match):
        grasp.forces(x)
    with pytest.raises(ValueError, match=match):
        grasp.linearize(x)


def test_a_path_that_does_not_close_says_how_far(grasp):
    x, _ = grasp.grasp_configuration()
    path = np.array([x, x + 0.0005, x + 0.001])
    with pytest.raises(ValueError, match=r"not closed: .*0\.00173 m from its first .*1e-06 m"):
        grasp.loop_work(path)
    assert grasp.loop_work(path, closure_tol_m=0.002)  # within a looser tolerance
    bad = np.array([x, x + np.array([[np.nan, 0, 0], [0, 0, 0]]), x])
    with pytest.raises(ValueError, match=r"path\[1\] holds non-finite"):
        grasp.loop_work(bad)
    with pytest.raises(ValueError, match=r"shape \(N, 2, 3\)"):
        grasp.loop_work(x)


def test_unknown_allocators_are_rejected():
    with pytest.raises(ValueError, match="unknown allocator"):
        Pipeline.from_profile(GRASP, allocators=["best"])


def test_along_a_motion_skips_bad_ticks_and_carries_friction():
    pipe = Pipeline.from_profile(GRASP, allocators=["pinv"])
    x, _ = pipe.grasp_configuration()
    P = np.array([x, x, x])
    P[1, 0, 0] = np.nan
    samples = pipe.along(P)
    assert [s.skipped is None for s in samples] == [True, False, True]
    assert "non-finite" in samples[1].skipped
    lift = Pipeline.from_profile(LIFT, allocators=["ef"])
    y, _ = lift.grasp_configuration()
    dragged = np.array([y + np.array([0.0, 0.0, 1e-5 * k]) for k in range(40)])
    last = lift.along(dragged, every=39)[-1].result["ef"]
    assert last.full_force[0, 2] < -0.07  # the anchor stayed behind: friction carried along


# -- hapticd analyze ---------------------------------------------------------------------------


def test_cli_analyze_prints_matrices_and_indices(capsys, tmp_path):
    out_json = tmp_path / "a.json"
    assert main(["analyze", str(GRASP), "--allocators", "pinv,if,ef", "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    assert "2 mm inside the object" in out
    assert "K_full (N/m)" in out and "K_rendered (N/m)" in out
    assert "controllability k = s/n" in out and "observability o = r/n" in out
    for name in ("pinv", "if", "ef"):
        assert name in out
    assert "adaptive" not in out
    data = json.loads(out_json.read_text())
    assert set(data["results"]) == {"pinv", "if", "ef"}
    assert np.array(data["results"]["if"]["K_rendered"]).shape == (6, 6)


def test_cli_analyze_at_a_configuration_out_of_contact(capsys):
    at = ["-0.1", "0", "0", "0.1", "0", "0"]
    assert main(["analyze", str(GRASP), "--at", *at, "--allocators", "pinv"]) == 0
    out = capsys.readouterr().out
    assert "no contact" in out and "nan" not in out.lower()


@pytest.mark.parametrize(
    ("at", "match"),
    [
        (["0", "0", "0"], "needs 6 numbers"),
        (["0", "0", "0", "0", "0", "x"], "--at"),
        (["nan", "0", "0", "0.03", "0", "0"], "non-finite"),
        (["0.03", "0", "0", "0.03", "0", "0"], "coincide"),
    ],
)
def test_cli_analyze_rejects_bad_configurations(capsys, at, match):
    assert main(["analyze", str(GRASP), "--at", *at]) == 2
    assert match in capsys.readouterr().err


def test_cli_analyze_a_recording_with_plot_and_progress(capsys, tmp_path):
    rec = builtin_trajectory("grasp-stiffness")
    png, js = tmp_path / "a.png", tmp_path / "a.json"
    args = ["analyze", str(GRASP), "--recording", str(rec), "--every", "400", "--progress"]
    assert main([*args, "--plot", str(png), "--json", str(js)]) == 0
    captured = capsys.readouterr()
    assert "samples without contact omitted" in captured.out
    assert "over the" in captured.out
    assert "analyze [" in captured.err  # the progress bar, on stderr
    assert png.stat().st_size > 1000
    data = json.loads(js.read_text())
    assert len(data["samples"]) == 10 and data["every"] == 400


def test_cli_analyze_a_free_objects_recording(capsys):
    rec = builtin_trajectory("lift-weight")
    args = ["analyze", str(LIFT), "--recording", str(rec), "--every", "1000", "--allocators", "ef"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "recording" in out and "nan" not in out.lower()


def test_cli_analyze_bad_arguments(capsys, tmp_path):
    assert main(["analyze", str(GRASP), "--allocators", "pinv,best"]) == 2
    assert "unknown allocator" in capsys.readouterr().err
    assert main(["analyze", str(tmp_path / "missing.yaml")]) == 2
    with pytest.raises(SystemExit):
        main(["analyze", str(GRASP), "--every", "0"])


def test_a_kink_in_the_force_is_flagged_not_hidden():
    """Releasing the cube: both contacts weaker than contact_onset_n and equally strong, so
    which one the allocator fades out flips with the smallest motion; the rendered force
    jumps there, and the estimate with twice the step says so."""
    rec = recording.read(builtin_trajectory("grasp-stiffness"))
    pipe = Pipeline.from_profile(GRASP, allocators=["pinv"])
    release = pipe.linearize(rec["device_pos"][3020])["pinv"]
    assert np.abs(release.full_force).max() < 0.05
    assert not release.smooth
    assert pipe.linearize(rec["device_pos"][2000])["pinv"].smooth
