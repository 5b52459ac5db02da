"""Friction and the contact forces (hapticd.physics.kernels.friction_step, forces_step: the Friction
and Forces stages' part of the tick's one call) compiled against the same call uncompiled:
the same bits for generated contacts (sticking, slipping, new contacts, fingers pulled out
of the face), normals, anchors, fixed and free objects, damping on and off, over several
ticks; the anchors are the Friction stage's carried state, so a run may switch between
the paths between ticks; the call reads and writes the object's one state array; hostile
values through either end in zero force and a latched fault.

Contact's results come from a stage inserted after contact (tests/ticks.py: the call in
parts). Whole runs of the bundled profiles both ways are compared with the stored
reference in tests/test_reference_output.py (the compiled runs use this call: checked
below)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hapticd.daemon.session import build_session
from hapticd.physics import kernels
from hapticd.physics.render import Renderer
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject
from hapticd.physics.stages import FRICTIONLESS, HELD
from hapticd.profile import load_profile
from tests import ticks
from tests.conftest import ROOT, capture_writes
from tests.strategies import unit_vectors
from tests.test_dynamics import floats, rotations, vec

LIFT = ROOT / "configs" / "lift-weight.yaml"
GRASP = ROOT / "configs" / "grasp-stiffness.yaml"
# What friction and forces write (the frame's fields), and the anchors friction keeps.
OUTPUTS = ("surface_point", "proxy_pos", "contact_point", "contact_force")
# Contact's results as the cases give them (its HELD fields), put in after contact as its
# frictionless ones, with in_contact and the normal.
CONTACT = ("in_contact", "contact_normal", *FRICTIONLESS)


def with_contacts(r: Renderer) -> ticks.Put:
    """A stage after ``r``'s contact that puts in contact's results (``CONTACT``)."""
    put = ticks.Put(CONTACT)
    r.insert(put, after="contact")
    return put


def contact_values(fields: dict) -> dict:
    """A case's fields as ``with_contacts`` puts them: its HELD ones as contact's FRICTIONLESS."""
    values = {name: np.array(fields[name]) for name in ("in_contact", "contact_normal")}
    for plain, held in zip(FRICTIONLESS, HELD, strict=True):
        values[plain] = np.array(fields[held])
    return values


@st.composite
def contacts(draw, n_fingers: int, mu_s: float, R: np.ndarray, x: np.ndarray) -> dict:
    """One tick's frame fields as contact writes them, and the anchors friction holds."""
    fields: dict[str, list] = {
        name: []
        for name in (
            "in_contact",
            "device_pos",
            "device_vel",
            "surface_point",
            "contact_normal",
            "proxy_pos",
            "contact_point",
        )
    }
    anchors = np.zeros((n_fingers, kernels.FRICTION_COLUMNS))
    for i in range(n_fingers):
        n = draw(unit_vectors())
        p = x + draw(vec(-0.05, 0.05))
        # The device below the face (a contact), on it, or above it (depth <= 0: the
        # friction proxy does not move).
        depth = draw(st.sampled_from([0.0, -1e-3]) | floats(0.0, 0.01))
        dev = p - depth * n + draw(st.just(0.0) | floats(0.0, 1e-3)) * draw(unit_vectors())
        fields["in_contact"].append(draw(st.booleans()))
        fields["device_pos"].append(dev)
        fields["device_vel"].append(draw(vec(-0.5, 0.5)))
        fields["surface_point"].append(p)
        fields["contact_normal"].append(n)
        fields["proxy_pos"].append(p + draw(vec(-1e-3, 1e-3)))
        fields["contact_point"].append(p - 0.008 * n)
        if draw(st.booleans()):  # an anchor from the last tick: within the cone or beyond
            t = draw(unit_vectors())
            t = t - (t @ n) * n
            reach = draw(
                st.sampled_from([0.0, 1.0])
                | floats(0.0, 0.999 * mu_s)
                | floats(1.001 * mu_s, 3.0 * mu_s)
            ) * max(depth, 0.0)
            world = p + reach * t + draw(st.just(0.0) | floats(-1e-3, 1e-3)) * n
            anchors[i, :3] = R.T @ (world - x)
            anchors[i, kernels.ANCHOR_SET] = 1.0
        else:
            anchors[i, :3] = draw(vec(-0.05, 0.05))  # stale numbers behind a cleared flag
    return {"fields": fields, "anchors": anchors}


@st.composite
def cases(draw, min_ticks: int = 1) -> dict:
    """A fixed or free box in any pose, its material (damping on or off), 1-3 fingers and
    ``min_ticks``-3 ticks of contacts, the object moving between them when it is free."""
    n_fingers = draw(st.integers(1, 3))
    mu_d = draw(floats(0.05, 1.2))
    material = Material(
        draw(floats(50.0, 2000.0)),
        draw(st.just(0.0) | floats(0.01, 10.0)),
        mu_static=mu_d * draw(st.just(1.0) | floats(1.0, 1.5)),
        mu_dynamic=mu_d,
    )
    fixed = draw(st.booleans())
    obj = {
        "fixed": fixed,
        "position": draw(vec(-0.05, 0.05)),
        "rotation": draw(rotations()),
        "velocity": np.zeros(3) if fixed else draw(vec(-1.0, 1.0)),
        "omega": np.zeros(3) if fixed else draw(vec(-10.0, 10.0)),
    }
    ticks = []
    R, x = obj["rotation"], obj["position"]
    for _ in range(draw(st.integers(min_ticks, 3))):
        ticks.append(draw(contacts(n_fingers, material.mu_static, R, x)))
        if not fixed:  # the object moved (as Dynamics would move it) before the next tick
            x = x + draw(vec(-1e-3, 1e-3))
            R = draw(rotations()) if draw(st.booleans()) else R
        ticks[-1]["pose"] = (x, R)
    return {"n": n_fingers, "material": material, "object": obj, "ticks": ticks}


def _scene(case: dict) -> Scene:
    o = case["object"]
    obj = SceneObject(
        ConvexShape.box(np.full(3, 0.05)),
        case["material"],
        o["position"].copy(),
        o["rotation"].copy(),
        fixed=o["fixed"],
        mass=0.0 if o["fixed"] else 0.1,
        velocity=o["velocity"].copy(),
        omega=o["omega"].copy(),
    )
    return Scene(obj, [], None)


def _run(case: dict, modes: list[str]) -> list[dict[str, np.ndarray]]:
    """Run the one call on each tick of ``case`` with contact's results put in, tick k
    compiled or not as ``modes[k]`` says; what friction and forces wrote, the anchors and
    the object's state, tick by tick."""
    scene = _scene(case)
    n = case["n"]
    radii = [0.008 + 0.001 * i for i in range(n)]
    r = ticks.renderer(scene, radii, modes[0])
    put = with_contacts(r)
    friction = ticks.stage(r, "friction")
    friction.anchors[:, :4] = case["ticks"][0]["anchors"][:, :4]
    out = []
    for tick, mode in zip(case["ticks"], modes, strict=True):
        ticks.use(r, mode)
        fields = tick["fields"]
        put.values = contact_values(fields)
        r.frame.contact_force[...] = 7.0  # yesterday's numbers: a path that forgets to write
        r.step(np.array(fields["device_pos"]), np.array(fields["device_vel"]))
        got = {name: getattr(r.frame, name).copy() for name in OUTPUTS}
        got["anchors"] = friction.anchors.copy()
        got["state"] = scene.object.state.copy()
        out.append(got)
        # The object moves between ticks (a free one also by its own step): in place or by
        # new arrays, as others move it.
        x, R = tick["pose"]
        obj = scene.object
        if len(out) % 2:
            obj.position[:] = x
            obj.rotation[:] = R
        else:
            obj.position, obj.rotation = x.copy(), R.copy()
    return out


def _assert_same(ref: list, got: list) -> None:
    assert len(ref) == len(got)
    for k, (a, b) in enumerate(zip(ref, got, strict=True)):
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"tick {k}: {name}")


@given(cases())
def test_friction_and_forces_compiled_and_uncompiled_agree_bit_for_bit(case):
    """numba neither fuses multiply-adds nor reorders without fastmath, and sqrt is
    correctly rounded: the same bits on every output, the anchors and the object's state."""
    ticks_ = len(case["ticks"])
    _assert_same(_run(case, ["uncompiled"] * ticks_), _run(case, ["compiled"] * ticks_))


@given(cases(min_ticks=2), st.data())
def test_switching_paths_between_ticks_keeps_the_anchors(case, data):
    """The anchors are the stage's one array, which both paths read and write: any mix of
    compiled and uncompiled ticks over a run gives the uncompiled run's numbers."""
    # Every case made to switch (2-3 ticks, both paths), not filtered with assume(): 60 %
    # of the cases drawn were thrown away so, and drawing them was most of the test's time.
    ticks_ = len(case["ticks"])
    modes = [data.draw(st.sampled_from(ticks.MODES), label="mode") for _ in range(ticks_)]
    if len(set(modes)) == 1:  # one path throughout: a drawn tick takes the other
        k = data.draw(st.integers(0, ticks_ - 1), label="switched tick")
        modes[k] = next(m for m in ticks.MODES if m != modes[k])
    assert ticks_ >= 2 and set(modes) == set(ticks.MODES)
    _assert_same(_run(case, ["uncompiled"] * ticks_), _run(case, modes))


def _pressed(obj: SceneObject, mode: str) -> tuple[Renderer, ticks.Put]:
    """A renderer of ``obj`` for one fingertip (8 mm), contact's results put in after it."""
    r = ticks.renderer(Scene(obj, [], None), [0.008], mode)
    return r, with_contacts(r) if obj.material.has_friction else _put_held(r)


def _put_held(r: Renderer) -> ticks.Put:
    put = ticks.Put(("in_contact", "contact_normal", "surface_point"))
    r.insert(put, after="contact")
    return put


@pytest.mark.parametrize("mode", ticks.MODES)
@pytest.mark.parametrize(("reach", "expected"), [(0.5, 0.5), (1.0, 1.0), (2.0, 0.8)])
def test_an_anchor_within_the_static_cone_sticks_and_one_beyond_slips(mode, reach, expected):
    """mu_s 0.5, mu_d 0.4, 15.625 mm deep: an anchor ``reach`` x mu_s depth along the face
    holds the friction proxy there (on the cone's edge too: the numbers are exact in binary);
    beyond, the proxy slips to the dynamic cone's edge (0.8 x mu_s depth), toward the
    anchor. The force's tangential part follows."""
    depth, mu_s, top = 0.015625, 0.5, 0.03125
    obj = SceneObject(
        ConvexShape.box(np.full(3, 0.05)), Material(100.0, 0.0, mu_s, 0.4), np.zeros(3), np.eye(3)
    )
    r, put = _pressed(obj, mode)
    friction = ticks.stage(r, "friction")
    put.values = contact_values(
        {
            "in_contact": [1],
            "contact_normal": [(0.0, 0.0, 1.0)],
            "proxy_pos": [(0.0, 0.0, top)],
            "surface_point": [(0.0, 0.0, top)],
            "contact_point": [(0.0, 0.0, top - 0.008)],
        }
    )
    friction.anchors[0, :4] = (-reach * mu_s * depth, 0.0, top, 1.0)
    device = np.array([[0.0, 0.0, top - depth]])
    frame = r.step(device, np.zeros((1, 3)))
    x = -expected * mu_s * depth
    np.testing.assert_allclose(frame.surface_point[0], (x, 0.0, top), atol=1e-15)
    np.testing.assert_allclose(frame.proxy_pos[0], (x, 0.0, top), atol=1e-15)
    np.testing.assert_allclose(frame.contact_point[0], (x, 0.0, top - 0.008), atol=1e-15)
    np.testing.assert_allclose(frame.contact_force[0], (100.0 * x, 0.0, 100.0 * depth), atol=1e-12)
    # The new anchor is the proxy, in the body frame; a finger that leaves clears it.
    np.testing.assert_allclose(friction.anchors[0], (x, 0.0, top, 1.0, 0.008), atol=1e-15)
    put.values["in_contact"] = np.zeros(1)
    r.step(device, np.zeros((1, 3)))
    assert friction.anchors[0, kernels.ANCHOR_SET] == 0.0
    assert np.all(frame.contact_force == 0.0)


def test_a_free_objects_damping_is_relative_to_its_motion():
    """A finger resting on a face that moves and spins: the damping sees the finger's
    velocity less the material's at the surface point (v + w x r), on both paths."""
    out = []
    for mode in ticks.MODES:
        obj = SceneObject(
            ConvexShape.box(np.full(3, 0.05)),
            Material(100.0, 2.0),
            np.zeros(3),
            np.eye(3),
            fixed=False,
            mass=0.1,
            velocity=np.array([0.1, 0.0, 0.0]),
            omega=np.array([0.0, 0.0, 1.0]),
        )
        r, put = _pressed(obj, mode)
        put.values = {
            "in_contact": np.ones(1),
            "surface_point": np.array([0.0, 0.025, 0.0]),
            "contact_normal": np.array([0.0, 1.0, 0.0]),
        }
        frame = r.step(np.array([[0.0, 0.025, 0.0]]), np.zeros((1, 3)))
        out.append(frame.contact_force[0].copy())
    # The material at (0, 0.025, 0) moves at v + w x r = (0.1 - 0.025, 0, 0) m/s.
    np.testing.assert_allclose(out[0], (2.0 * 0.075, 0.0, 0.0), atol=1e-15)
    np.testing.assert_array_equal(out[0], out[1])


@pytest.mark.parametrize("mode", ticks.MODES)
def test_the_call_shares_one_object_state_between_friction_forces_and_dynamics(mode):
    """Friction, Forces and Dynamics read (and Dynamics writes) the object's one state
    array, whose views are its position, velocity, omega and rotation; a value assigned
    from outside goes into that array, and the next tick reads it."""
    obj = SceneObject(
        ConvexShape.box(np.full(3, 0.05)),
        Material(100.0, 0.5, 1.0, 0.8),
        np.zeros(3),
        np.eye(3),
        fixed=False,
        mass=0.1,
    )
    r = ticks.renderer(Scene(obj, [], np.array([0.0, 0.0, -9.81])), [0.008], mode)
    assert [s.name for s in r.stages][:3] == ["contact", "friction", "forces"]
    put = with_contacts(r)
    put.values = contact_values(
        {
            "in_contact": [1],
            "contact_normal": [(0.0, 0.0, 1.0)],
            "proxy_pos": [(0.0, 0.0, 0.025)],
            "surface_point": [(0.0, 0.0, 0.025)],
            "contact_point": [(0.0, 0.0, 0.017)],
        }
    )
    device = np.array([[0.0, 0.0, 0.02]])
    state = obj.state
    for _ in range(2):
        r.step(device, np.zeros((1, 3)))
    assert obj.state is state
    assert obj.position.base is state and obj.velocity.base is state
    assert obj.rotation.base is state
    assert obj.velocity[2] < 0.0  # pushed down by the finger and gravity, written in place
    assert state[5] == obj.velocity[2]
    obj.position = np.array([0.0, 0.0, 0.5])  # a reset from outside: into the state
    assert state[2] == 0.5 and obj.position.base is state
    r.step(device, np.zeros((1, 3)))
    assert 0.49 < state[2] < 0.5 and obj.position[2] == state[2]  # moved on from there


@pytest.mark.parametrize("path", [LIFT, GRASP], ids=["lift", "grasp"])
def test_compiled_runs_of_the_bundled_profiles_use_these_kernels(path):
    """tests/test_reference_output.py's compiled runs (rendering.kernels=compiled) go
    through the compiled call, with friction (the lift has it) and forces (both)."""
    s = build_session(
        load_profile(path, ["rendering.kernels=compiled"]), paced=False, duration_s=0.01
    )
    r: Renderer = s.renderer
    assert r.one_call._fn is r.kernels["tick_step"]
    assert "forces" in r.stage_names and ("friction" in r.stage_names) is (path == LIFT)
    s.run()


class Poison:
    """A stage after ``contact`` that puts ``value`` into finger 0's ``field`` from ``at`` (s)
    on: what a broken contact model (frictionless_point, the surface point it hands to
    friction) or device (device_vel, which the damping reads) could hand to friction and
    forces."""

    name = "poison"

    def __init__(self, loop, field: str, value: float, at: float) -> None:
        self.loop, self.field, self.value, self.at = loop, field, value, at
        self.corrupts = (field, "in_contact")

    def run(self, frame) -> None:
        if self.loop.now() >= self.at:
            getattr(frame, self.field)[0] = self.value
            frame.in_contact[0] = 1


def _poisoned_run(mode: str, field: str, value: float) -> tuple[np.ndarray, dict, float]:
    """The lift for 3.2 s, poisoned from 3.0 s: the forces written to the devices (ticks x
    fingers, 3), the summary and the force limit."""
    profile = load_profile(LIFT, [f"rendering.kernels={mode}"])
    session = build_session(profile, paced=False, duration_s=3.2)
    renderer = session.renderer
    assert (renderer.one_call._fn is kernels.uncompiled("tick_step")) == (mode == "python")
    renderer.insert(Poison(session.loop, field, value, 3.0), after="contact")
    written = capture_writes(session)
    summary = session.run()
    return np.array(written), summary, max(session.safety.limits)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 1e300])
@pytest.mark.parametrize("field", ["frictionless_point", "device_vel"])
def test_a_poisoned_contact_ends_in_zero_force_and_a_latched_fault(field, value):
    """Through friction_step (its anchor takes a poisoned surface point) and forces_step, on
    the lift: every force written is finite and within the limit, the run latches a fault
    and writes only zero force from that tick on; the compiled run latches it on the same
    tick as the Python run, having written the same forces before it, bit for bit.

    The cause may differ: with a finite but huge velocity (1e300) the Python free-body step
    raises (math.cos of an infinite angle: ValueError) where the compiled one returns
    non-finite numbers that the object-state backstop catches, on the same tick."""
    forces, summary, limit = _poisoned_run("compiled", field, value)
    assert np.all(np.isfinite(forces))
    assert np.all(np.linalg.norm(forces, axis=1) <= limit + 1e-12)
    assert summary["fault"] is not None, summary
    tick = summary["fault"]["tick"]
    assert np.all(forces[2 * tick :] == 0.0) and len(forces) > 2 * tick
    ref, ref_summary, _ = _poisoned_run("python", field, value)
    assert ref_summary["fault"] is not None and ref_summary["fault"]["tick"] == tick
    np.testing.assert_array_equal(forces[: 2 * tick], ref[: 2 * tick])
    if math.isfinite(value) and field == "device_vel":
        return
    assert summary["fault"] == ref_summary["fault"]
