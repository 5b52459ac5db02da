"""The passivity observer and controller: the energy it observes, what it adds, where it runs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from hapticd.allocation.actuation import Actuation
from hapticd.analysis import Pipeline, examples
from hapticd.cli import format_status
from hapticd.daemon.build import build_renderer
from hapticd.daemon.session import build_session
from hapticd.daemon.summary import status
from hapticd.physics import kernels
from hapticd.physics.passivity import PassivityParams, authority, control, observe
from hapticd.physics.render import Renderer
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject
from hapticd.profile import ProfileError, load_profile, parse_profile
from tests.conftest import ROOT


def step(energy, force, dx, dx_actuated, dt, params):
    """One tick of one finger's observer and controller, as the tick's one call composes
    them (hapticd.physics.kernels._passivity): (E(n) J, alpha(n) N s/m) for E(n-1) ``energy`` (J),
    the rendered force (3,) N, the finger's motion dx (3,) m and P_a dx (3,) m over ``dt``
    s. Non-finite input leaves E unchanged and adds no damping."""
    observed = observe(energy, force, dx)
    if not math.isfinite(observed):
        return energy, 0.0
    return control(observed, dx_actuated, dt, params.velocity_threshold, params.max_damping)


DT = 1e-3
PARAMS = PassivityParams(velocity_threshold=0.002, max_damping=50.0)


# -- the pure math ------------------------------------------------------------------------------


def test_the_observer_and_controller_on_a_hand_computed_tick():
    # The display pushes +x with 1 N while the finger moves 1 mm along +x in 1 ms: it
    # delivers 1 mJ, so E(n) = E(n-1) - f . dx = 0.0004 - 0.001 = -0.0006 J before the
    # controller. Actuated along x, |P_a v| = 1 m/s, far above twice the threshold:
    # alpha = 0.0006 J / (1 ms (1 m/s)^2) = 0.6 N s/m brings E back to exactly 0.
    e, alpha = step(4e-4, (1.0, 0.0, 0.0), (1e-3, 0.0, 0.0), (1e-3, 0.0, 0.0), DT, PARAMS)
    assert alpha == pytest.approx(0.6, rel=1e-12) and e == 0.0
    # Clamped at 0.25 N s/m, the damping dissipates 0.25 * 1 * 1e-3 = 0.25 mJ of the 0.6.
    clamped = PassivityParams(0.002, 0.25)
    e, alpha = step(4e-4, (1.0, 0.0, 0.0), (1e-3, 0.0, 0.0), (1e-3, 0.0, 0.0), DT, clamped)
    assert alpha == 0.25 and e == pytest.approx(-6e-4 + 2.5e-4, rel=1e-12)
    # The finger pushing into the force: the display absorbs 2 mJ, nothing added.
    e, alpha = step(0.0, (-2.0, 0.0, 0.0), (1e-3, 0.0, 0.0), (1e-3, 0.0, 0.0), DT, PARAMS)
    assert (e, alpha) == (pytest.approx(2e-3, rel=1e-12), 0.0)


def test_authority_ramps_from_the_threshold_to_twice_it():
    assert authority(0.0, 0.01) == 0.0 and authority(0.01, 0.01) == 0.0
    assert authority(0.015, 0.01) == pytest.approx(0.5) and authority(0.02, 0.01) == 1.0
    assert authority(5.0, 0.01) == 1.0
    # At 1.5 thresholds the damping is capped at half the maximum.
    dx = (0.015 * DT, 0.0, 0.0)
    e, alpha = step(0.0, (1.0, 0.0, 0.0), dx, dx, DT, PassivityParams(0.01, 10.0))
    assert alpha == pytest.approx(5.0) and e == pytest.approx(-0.015e-3 + 5.0 * 0.015**2 * DT)


def _project(directions, v) -> tuple[float, float, float]:
    """``v`` projected onto the span of ``directions`` (world frame), as the call does it."""
    d = np.array(directions, dtype=float).reshape(-1, 3)
    world = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    return kernels._span_project(d, 0, len(d), world, *map(float, v))


def test_the_projector_onto_the_actuated_directions():
    s = math.sqrt(0.5)
    np.testing.assert_allclose(
        _project([(s, 0.0, s)], (1.0, 2.0, 0.0)), (0.5, 0.0, 0.5), atol=1e-15
    )
    # Not unit: the span is the same.
    np.testing.assert_allclose(
        _project([(3.0, 0.0, 3.0)], (1.0, 2.0, 0.0)), (0.5, 0.0, 0.5), atol=1e-15
    )
    # Two directions span a plane; a third dependent one adds nothing.
    planar = [(1.0, 0.0, 0.0), (1.0, 1.0, 0.0), (2.0, 1.0, 0.0)]
    np.testing.assert_allclose(_project(planar, (1.0, 2.0, 3.0)), (1.0, 2.0, 0.0), atol=1e-15)
    assert _project([], (1.0, 2.0, 3.0)) == (0.0, 0.0, 0.0)
    assert _project([(0.0, 0.0, 0.0)], (1.0, 2.0, 3.0)) == (0.0, 0.0, 0.0)
    assert _project(np.eye(3), (1.0, 2.0, 3.0)) == (1.0, 2.0, 3.0)
    # A direction in a grasp frame (its axes, by rows x, y, z, given as _axes gives them).
    yz = (0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0)  # x -> world y, y -> z, z -> x
    got = kernels._span_project(np.array([[1.0, 0.0, 0.0]]), 0, 1, yz, 1.0, 2.0, 3.0)
    np.testing.assert_allclose(got, (0.0, 2.0, 0.0), atol=1e-15)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"velocity_threshold": 0.0, "max_damping": 1.0}, "velocity_threshold"),
        ({"velocity_threshold": math.nan, "max_damping": 1.0}, "velocity_threshold"),
        ({"velocity_threshold": 0.01, "max_damping": -1.0}, "max_damping"),
        ({"velocity_threshold": 0.01, "max_damping": math.inf}, "max_damping"),
    ],
)
def test_bad_parameters_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        PassivityParams(**kw)


finite = st.floats(-1e3, 1e3, allow_nan=False)
# Motions from exactly zero through the numerically awkward to a few cm per tick.
tiny_to_large = st.one_of(
    st.just(0.0),
    st.floats(-1e-12, 1e-12),
    st.floats(-1e-6, 1e-6),
    st.floats(-0.05, 0.05),
)


@given(
    energy=st.floats(-10.0, 10.0),
    force=st.tuples(finite, finite, finite),
    dx=st.tuples(tiny_to_large, tiny_to_large, tiny_to_large),
    threshold=st.floats(1e-4, 1.0),
    max_damping=st.floats(1e-3, 100.0),
    dt=st.sampled_from([1.25e-4, 1e-3, 1e-2]),
)
def test_damping_is_bounded_idle_below_the_threshold_and_never_nan(
    energy, force, dx, threshold, max_damping, dt
):
    p = PassivityParams(threshold, max_damping)
    e, alpha = step(energy, force, dx, dx, dt, p)
    assert math.isfinite(e) and math.isfinite(alpha)
    assert 0.0 <= alpha <= max_damping
    speed = math.sqrt(sum(c * c for c in dx)) / dt
    before = energy - sum(f * d for f, d in zip(force, dx, strict=True))
    if speed <= threshold:
        assert alpha == 0.0 and e == before
    # The controller only ever dissipates: E never below the observer's own value, and
    # back to zero unless the clamp held it.
    assert e >= before - 1e-12 * max(1.0, abs(before))
    if alpha < max_damping * authority(speed, threshold):
        assert e >= 0.0
    # The damping force is finite and at most max_damping times the speed.
    assert alpha * speed <= max_damping * speed * (1 + 1e-12) + 1e-300


@given(v=st.floats(0.0, 1e-9), energy=st.floats(-1.0, 0.0))
def test_as_v_goes_to_zero_the_stage_adds_nothing_and_no_nan(v, energy):
    assume(energy < 0.0)  # a deficit the controller would like to pay back
    r = _wall_renderer(PARAMS)
    r.passivity.energy[0] = energy
    x = np.array([[0.0, -0.002, 0.0]])
    r.step(x, np.zeros((1, 3)))
    f = r.step(x + np.array([[v * DT, 0.0, 0.0]]), np.zeros((1, 3)))
    assert np.all(np.isfinite(f.rendered_force)) and float(f.passivity_damping[0]) == 0.0
    assert np.isfinite(f.passivity_energy[0])


def test_non_finite_positions_add_no_damping_and_leave_the_energy():
    r = _wall_renderer(PARAMS)
    r.passivity.energy[0] = -1e-3
    x = np.array([[0.0, -0.002, 0.0]])
    r.step(x, np.zeros((1, 3)))
    r.passivity.last_pos = [[math.nan, 0.0, 0.0]]  # as after a NaN read
    f = r.step(x, np.zeros((1, 3)))
    assert float(f.passivity_damping[0]) == 0.0 and float(f.passivity_energy[0]) == -1e-3
    assert np.all(np.isfinite(f.rendered_force))


# -- the stage on renderings --------------------------------------------------------------------


def _wall_renderer(params: PassivityParams | None, alpha_deg: float = 30.0) -> Renderer:
    """The seed's tilted wall (one actuator, asymmetric), as a renderer."""
    w = examples.tilted_wall(math.radians(alpha_deg))
    p = w.pipeline
    return Renderer(p.scene, [0.0], p.actuation, "pinv", passivity=params, dt=DT)


def _loops(center, e1, e2, radius, period_s, n_loops, outside):
    """Positions (N, 3) m at DT: from ``outside`` into a circle of ``radius`` about ``center``
    in the plane (e1, e2), ``n_loops`` times round, and back out: a closed path."""
    start = center + radius * e1
    ramp = np.linspace(0.0, 1.0, 200)[:, None]
    into = outside + ramp * (start - outside)
    t = np.arange(1, round(n_loops * period_s / DT) + 1) * DT
    ph = 2 * np.pi * t / period_s
    circle = center + radius * (np.cos(ph)[:, None] * e1 + np.sin(ph)[:, None] * e2)
    return np.vstack([into, circle, into[::-1]])


def _run(r: Renderer, path: np.ndarray) -> dict[str, np.ndarray]:
    """Positions (N, p, 3) through ``r``; the frame's fields per tick."""
    names = ("rendered_force", "passivity_energy", "passivity_damping", "in_contact")
    out = {n: [] for n in names}
    vel = np.zeros(path.shape[1:])
    for k in range(path.shape[0]):
        if k:
            vel = (path[k] - path[k - 1]) / DT
        f = r.step(path[k], vel)
        for n in names:
            out[n].append(f.get(n).copy())
    return {n: np.array(v) for n, v in out.items()}


def test_the_stage_books_every_tick_as_the_observer_says():
    path = _loops(np.array([0.0, -0.002, 0.0]), np.eye(3)[0], np.eye(3)[1], 0.0015, 0.3, 2,
                  np.array([0.0, 0.004, 0.0]))[:, None, :]  # fmt: skip
    got = _run(_wall_renderer(PARAMS), path)
    # E(n) = E(n-1) - f_out(n) . (x(n) - x(n-1)), f_out the force the stage let through.
    dx = np.diff(path, axis=0, prepend=path[:1])
    expected = -np.cumsum(np.sum(got["rendered_force"] * dx, axis=2), axis=0)
    np.testing.assert_allclose(got["passivity_energy"], expected, atol=1e-15)
    assert got["passivity_damping"].max() > 0.0


def test_the_controller_keeps_the_observed_energy_non_negative_on_the_tilted_wall():
    # Round the loop the way the wall delivers energy: into the wall, then up its normal.
    center, outside = np.array([0.0, -0.0025, 0.0]), np.array([0.0, 0.004, 0.0])
    path = _loops(center, np.eye(3)[0], np.eye(3)[1], 0.002, 0.5, 3, outside)[:, None, :]
    on = _run(_wall_renderer(PARAMS), path)
    off = _run(_wall_renderer(None), path)
    dx = np.diff(path, axis=0, prepend=path[:1])
    # Without the controller the observer sees the wall generate energy every loop.
    uncontrolled = -np.cumsum(np.sum(off["rendered_force"] * dx, axis=2), axis=0)[:, 0]
    assert uncontrolled[-1] < -5e-4  # about 3e-4 J per loop, examples.wall_work's field
    # With it, the only energy let through is what passed where the controller had less
    # than the authority it needed (near the threshold, at the clamp): the tolerance.
    f_in = off["rendered_force"][:, 0]
    alpha = on["passivity_damping"][:, 0]
    speed = np.linalg.norm(dx[:, 0] @ np.outer(*[_wall_dir()] * 2), axis=1) / DT
    cap = PARAMS.max_damping * np.array([authority(s, PARAMS.velocity_threshold) for s in speed])
    limited = alpha >= cap
    delivered = np.sum(f_in * dx[:, 0], axis=1)
    tol = float(np.sum(np.maximum(delivered[limited], 0.0)))
    assert tol < 0.02 * -uncontrolled[-1]
    assert on["passivity_energy"][:, 0].min() >= -tol - 1e-15
    assert on["passivity_energy"][-1, 0] >= -1e-15
    # Out of contact and where the wall absorbs energy, the force is the wall's own.
    idle = alpha == 0.0
    np.testing.assert_array_equal(on["rendered_force"][idle], off["rendered_force"][idle])
    # The damping acts along the actuated direction only.
    d = _wall_dir()
    diff = on["rendered_force"][:, 0] - f_in
    assert np.abs(diff - np.outer(diff @ d, d)).max() < 1e-15


def _wall_dir() -> np.ndarray:
    a = math.radians(30.0)
    return np.array([math.sin(a), math.cos(a), 0.0])


def _cube_renderer(params: PassivityParams | None) -> Renderer:
    """The grasp's 50 mm cube at 60 N/m, two fingers each actuated in all three directions."""
    cube = SceneObject(ConvexShape.box(np.full(3, 0.05)), Material(60.0), np.zeros(3), np.eye(3))
    act = Actuation([np.eye(3).tolist(), np.eye(3).tolist()], "world")
    return Renderer(Scene(cube, [], None), [0.008, 0.008], act, "pinv", passivity=params, dt=DT)


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_a_conservative_rendering_gets_nothing_added(direction):
    # Full actuation, frictionless: the rendering is the contact's own spring, conservative.
    # Each finger explores its face in closed loops (into the face and along it, and sideways),
    # both ways round; the observed energy is the spring's stored energy and never negative.
    x, y, z = np.eye(3)
    thumb = _loops(np.array([-0.0315, 0.0, 0.0]), x, direction * z, 0.002, 0.4, 3,
                   np.array([-0.04, 0.0, 0.0]))  # fmt: skip
    index = _loops(np.array([0.031, 0.001, 0.0]), -x, direction * (y + z) / math.sqrt(2),
                   0.0025, 0.4, 3, np.array([0.04, 0.0, 0.0]))  # fmt: skip
    path = np.stack([thumb, index], axis=1)
    on = _run(_cube_renderer(PARAMS), path)
    off = _run(_cube_renderer(None), path)
    assert on["in_contact"].all(axis=1).sum() > 1000  # both fingers pressing, most of the time
    assert np.all(on["passivity_damping"] == 0.0)
    np.testing.assert_array_equal(on["rendered_force"], off["rendered_force"])
    assert on["passivity_energy"].min() >= 0.0
    assert on["passivity_energy"].max() > 1e-5  # the spring's stored energy was observed


def test_at_rest_the_stage_adds_nothing_so_the_analysis_leaves_it_out():
    # The analysis linearizes at rest; there the stage adds no damping even with a deficit,
    # so a pipeline with or without it renders the same forces.
    r = _wall_renderer(PARAMS)
    r.passivity.energy[0] = -1.0
    x = np.array([[0.0, -0.002, 0.0]])
    for _ in range(3):
        f = r.step(x, np.zeros((1, 3)))
    assert float(f.passivity_damping[0]) == 0.0
    bare = _wall_renderer(None).step(x, np.zeros((1, 3)))
    np.testing.assert_array_equal(f.rendered_force, bare.rendered_force)
    pipe = Pipeline.from_renderer(r, allocators=["pinv"])
    assert "passivity" not in pipe.renderer("pinv").stage_names


# -- the plan and the profile -------------------------------------------------------------------


def test_the_stage_is_planned_only_when_enabled(grasp_data, write_profile):
    r = build_renderer(parse_profile(grasp_data))
    assert "passivity" not in r.stage_names
    grasp_data["rendering"]["passivity"] = {"enabled": True}
    r = build_renderer(parse_profile(grasp_data))
    assert r.stage_names == ["contact", "forces", "allocation", "passivity", "output", "scene"]
    assert r.passivity.params == PassivityParams(0.005, 20.0)
    # With ground and walls it observes their force too: after the environment stage.
    lift = load_profile(ROOT / "configs" / "lift-weight.yaml")
    assert "passivity" not in build_renderer(lift).stage_names
    data = lift.model_dump(exclude={"source"})
    data["rendering"]["passivity"] = {"enabled": True, "max_damping_n_s_per_m": 10.0}
    names = build_renderer(parse_profile(data, lift.source)).stage_names
    assert names[names.index("environment") + 1] == "passivity"
    assert names.index("allocation") < names.index("passivity") < names.index("dynamics")


KEY = "rendering.passivity."


@pytest.mark.parametrize(
    ("cfg", "key", "expected"),
    [
        ({"velocity_threshold_m_per_s": 0.0}, "velocity_threshold_m_per_s", "greater than 0"),
        (
            {"velocity_threshold_m_per_s": 2.0},
            "velocity_threshold_m_per_s",
            "less than or equal to 1",
        ),
        ({"max_damping_n_s_per_m": -1.0}, "max_damping_n_s_per_m", "greater than 0"),
        ({"max_damping_n_s_per_m": 500.0}, "max_damping_n_s_per_m", "less than or equal to 100"),
        ({"enabled": "sometimes"}, "enabled", "valid boolean"),
        ({"max_damping": 5.0}, "max_damping", "unknown key; did you mean 'max_damping_n_s_per_m'?"),
    ],
)
def test_bad_passivity_keys_are_named(grasp_data, write_profile, cfg, key, expected):
    grasp_data["rendering"]["passivity"] = {"enabled": True, **cfg}
    path = write_profile(grasp_data)
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    msg = str(exc.value)
    assert str(path.resolve()) in msg
    line = next(ln for ln in msg.splitlines() if f"rendering.passivity.{key}: " in ln)
    assert expected in line


def test_a_run_records_and_reports_the_stage(grasp_data, tmp_path):
    # The sim finger feels the grasp through pinv, the stage on.
    for f in grasp_data["fingers"]:
        f["device"]["backend"] = "sim"
    grasp_data["rendering"].update(allocator="pinv", passivity={"enabled": True})
    s = build_session(
        parse_profile(grasp_data, tmp_path / "p.yaml"),
        paced=False,
        duration_s=4.0,
        record_path=tmp_path / "run.hrec",
    )
    s.run()
    full = status(s.loop)
    st = full["passivity"]
    assert st["enabled"] is True and len(st["energy_j"]) == 2
    line = next(ln for ln in format_status(full).splitlines() if ln.startswith("passivity"))
    assert " J; damping 0, 0 N s/m" in line
    full["passivity"] = {"enabled": False, "energy_j": [0.0, 0.0], "damping_n_s_per_m": [0.0] * 2}
    assert "passivity     off" in format_status(full)
    from hapticd import recording

    rec = recording.read(tmp_path / "run.hrec")
    assert rec.units()["passivity_energy"] == "J"
    assert rec.units()["passivity_damping"] == "N s/m"
    assert rec["passivity_energy"].shape == (rec.ticks, 2)
    assert np.all(np.isfinite(rec["passivity_energy"])) and np.all(rec["passivity_damping"] >= 0)
    # The bundled pinch presses straight in and out of the faces: it encloses no loop, the
    # display stays passive and the controller has nothing to add.
    assert rec["passivity_energy"].min() >= 0.0 and rec["passivity_energy"].max() > 1e-5
    assert np.all(rec["passivity_damping"] == 0.0)
    assert st["energy_j"] == rec["passivity_energy"][-1].tolist()
