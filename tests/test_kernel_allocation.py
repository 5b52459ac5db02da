"""The compiled allocation kernel (hapticd.kernels.allocation_step) against the Allocation
stage's Python code: the same bits for generated grasps, near-singular ones included
(coincident and nearly coincident contacts, directions along the grasp line or nearly
parallel, forces at contact onset, a vertical grasp line in the grasp frame); the cases it
does not take run the Python code; non-finite input raises the same error."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from hapticd import jit, kernels
from hapticd.actuation import Actuation
from hapticd.allocation import AdaptiveState, AllocationError, Robustness
from hapticd.allocation.contacts import ContactAllocator
from hapticd.frame import Frame
from hapticd.scene import ConvexShape, Material, Scene, SceneObject
from hapticd.stages import Allocation
from tests.strategies import unit_vectors
from tests.test_dynamics import floats, vec

OUTPUTS = (
    "lam_a",
    "rendered_force",
    "residual_internal",
    "residual_external",
    "residual_total",
    "amplification",
    "alpha",
)


@pytest.fixture(scope="module")
def compiled():
    """The compiled allocation kernel (numba is a dependency: no skip without it)."""
    return jit.compile_kernels(["allocation_step"])["allocation_step"]


@st.composite
def directions(draw, other: np.ndarray | None) -> np.ndarray:
    """A unit direction: any, or (near-singular) nearly parallel to ``other``."""
    d = draw(unit_vectors())
    if other is not None and draw(st.booleans()):
        d = other + draw(floats(0.0, 1e-3)) * d
        d = d / np.linalg.norm(d)
    return d


@st.composite
def grasps(draw) -> dict:
    """A tick's frame for 2 or 3 fingers with one direction each, the allocator's method and
    robustness, the object's position. Contacts are often close (below min_separation_m,
    down to coincident), forces often below the contact onset, directions often along the
    grasp line or nearly parallel: the allocators' singular configurations."""
    n_fingers = draw(st.integers(2, 3))
    rb = Robustness(
        draw(st.sampled_from([0.01, 0.05]) | floats(0.01, 0.9)),
        draw(floats(1e-3, 0.02)),
        draw(st.just(0.0) | floats(1e-3, 0.5)),
    )
    center = draw(vec(-0.05, 0.05))
    first = center + draw(vec(-0.05, 0.05))
    points = [first]
    for _ in range(n_fingers - 1):
        gap = draw(
            st.sampled_from([0.0, 1e-12, 1e-6])
            | floats(0.0, 2.0 * rb.min_separation_m)
            | floats(0.0, 0.1)
        )
        points.append(first + gap * draw(unit_vectors()))
    line = points[1] - points[0]
    along = line / np.linalg.norm(line) if np.linalg.norm(line) > 0 else None
    local = []
    for _ in range(n_fingers):
        previous = local[-1] if local else along
        local.append(draw(directions(previous)))
    if draw(st.booleans()):
        # Axis-aligned, in the world frame: directions exactly across the grasp line (B = 0,
        # IF's projector P = I) or exactly along it.
        axes = np.vstack([np.eye(3), -np.eye(3)])
        points[1] = points[0] + draw(floats(0.0, 0.05)) * np.array([1.0, 0.0, 0.0])
        local = [axes[draw(st.integers(0, 5))] for _ in range(n_fingers)]
    forces = []
    for _ in range(n_fingers):
        scale = draw(st.sampled_from([0.0, 1e-9]) | floats(0.0, 2.0 * rb.contact_onset_n + 0.01))
        forces.append(draw(st.just(scale) | floats(0.0, 10.0)) * draw(unit_vectors()))
    device = [p + draw(vec(-0.01, 0.01)) for p in points]
    if draw(st.booleans()):  # a vertical grasp line: the grasp frame's other branch
        device[1] = device[0] + np.array([0.0, 0.0, draw(floats(0.0, 0.05))])
    return {
        "n": n_fingers,
        "robust": rb,
        "method": draw(st.sampled_from(kernels.ALLOCATION_METHODS)),
        "frame": draw(st.sampled_from(["world", "grasp"])),
        "local": local,
        "center": center,
        "frame_fields": {
            "in_contact": [draw(st.booleans()) for _ in range(n_fingers)],
            "device_pos": device,
            "contact_point": points,
            "contact_force": forces,
        },
    }


def _stage(case: dict, kernel) -> tuple[Allocation, Frame]:
    obj = SceneObject(ConvexShape.box(np.full(3, 0.05)), Material(100.0), case["center"], np.eye(3))
    act = Actuation([[d] for d in case["local"]], case["frame"])
    alloc = ContactAllocator(act, case["method"], case["robust"], AdaptiveState(), 1e-3)
    frame = Frame(case["n"], act.n_actuators)
    for name, value in case["frame_fields"].items():
        getattr(frame, name)[...] = value
    return Allocation(Scene(obj, [], None), alloc, kernel), frame


def _outputs(case: dict, kernel) -> dict[str, np.ndarray] | str:
    """The stage's outputs, or the message of the AllocationError it raised."""
    stage, frame = _stage(case, kernel)
    # Yesterday's numbers in the outputs: a path that forgets to write one is caught.
    for name in OUTPUTS:
        getattr(frame, name)[...] = 7.0
    try:
        stage.run(frame)
    except AllocationError as e:
        return str(e)
    return {name: getattr(frame, name).copy() for name in OUTPUTS}


def _assert_same(ref, got) -> None:
    if isinstance(ref, str) or isinstance(got, str):
        assert ref == got
        return
    for name in OUTPUTS:
        np.testing.assert_array_equal(ref[name], got[name], err_msg=name)


@given(grasps())
def test_the_compiled_allocation_equals_the_python_stage_bit_for_bit(compiled, case):
    """The kernel evaluates the closed forms' sums in the same order (numba neither fuses
    multiply-adds nor reorders without fastmath; sqrt is correctly rounded): the same bits,
    near singular configurations too."""
    _assert_same(_outputs(case, None), _outputs(case, compiled))


@given(grasps())
def test_the_allocation_kernel_as_plain_python_is_the_stage_bit_for_bit(case):
    _assert_same(_outputs(case, None), _outputs(case, kernels.allocation_step))


@given(grasps(), st.sampled_from(kernels.ALLOCATION_METHODS), st.floats(0.0, 1.0))
def test_the_kernel_equals_the_general_path(case, method, alpha):
    """The kernel's closed forms, grasp frame and contact onset against allocate() (the
    Gram-matrix general path, with the world directions of hapticd.actuation), which runs
    when the kernel declines (a kernel that always returns MANY_CONTACTS): the same forces
    to rounding, near singular configurations too."""
    case = {**case, "method": method}
    got = {}
    for name, kernel in (("kernel", None), ("general", lambda *a: kernels.MANY_CONTACTS)):
        stage, frame = _stage(case, kernel)
        stage.allocator.adaptive = AdaptiveState(alpha=alpha, time_constant_s=1e9)
        try:
            stage.run(frame)
        except AllocationError as e:
            got[name] = str(e)
            continue
        got[name] = (frame.lam_a.copy(), frame.rendered_force.copy())
    if isinstance(got["kernel"], str) or isinstance(got["general"], str):
        assert got["kernel"] == got["general"]
        return
    lam = np.abs(np.array(case["frame_fields"]["contact_force"])).max()
    for k, g in zip(got["kernel"], got["general"], strict=True):
        scale = max(lam, np.abs(g).max(), 1e-300)
        np.testing.assert_allclose(k, g, rtol=0, atol=1e-9 * scale)


@given(grasps(), st.sampled_from(["pinv_exact", "if_exact"]))
def test_methods_the_kernel_does_not_compute_run_the_general_path(compiled, case, method):
    case = {**case, "method": method}
    _assert_same(_outputs(case, None), _outputs(case, compiled))


def test_three_contacts_and_several_directions_run_the_general_path(compiled):
    """Three contacts: the kernel returns without writing and the stage's Python code runs;
    two directions on a finger: the kernel is not even called."""
    case = {
        "n": 3,
        "robust": Robustness(),
        "method": "if",
        "frame": "world",
        "local": [np.array([1.0, 0, 0]), np.array([-1.0, 0, 0]), np.array([0.0, 0, 1])],
        "center": np.zeros(3),
        "frame_fields": {
            "in_contact": [1, 1, 1],
            "device_pos": np.zeros((3, 3)),
            "contact_point": [[-0.02, 0, 0], [0.02, 0, 0], [0, 0.02, 0]],
            "contact_force": [[1.0, 0, 0.1], [-1.0, 0, 0.1], [0, -0.5, 0]],
        },
    }
    ref = _outputs(case, None)
    # The squeeze along x is rendered whole; the third finger's vertical actuator has no
    # vertical force to render (0 within rounding: its exact value is the library's).
    assert not isinstance(ref, str)
    np.testing.assert_allclose(ref["lam_a"], [1.0, 1.0, 0.0], rtol=0, atol=1e-12)
    _assert_same(ref, _outputs(case, compiled))
    calls = []
    stage, three = _stage(case, lambda *a: calls.append(a) or kernels.ALLOCATED)
    stage.allocator.actuation = Actuation([[(1, 0, 0), (0, 1, 0)], [(1, 0, 0)], [(0, 0, 1)]])
    frame = Frame(3, 4)
    for name in case["frame_fields"]:
        getattr(frame, name)[...] = getattr(three, name)
    frame.in_contact[2] = 0
    stage.run(frame)
    assert calls == []
    # thumb x, thumb y, index x, the third finger (not in contact): the squeeze whole, no
    # y force to render, nothing for a finger out of contact.
    np.testing.assert_allclose(frame.lam_a, [1.0, 0.0, -1.0, 0.0], rtol=0, atol=1e-12)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("field", ["contact_force", "contact_point", "device_pos"])
def test_non_finite_input_raises_the_python_stages_error(compiled, field, bad):
    case = {
        "n": 2,
        "robust": Robustness(),
        "method": "if",
        "frame": "grasp",
        "local": [np.array([0.8660254, 0, 0.5]), np.array([-0.8660254, 0, 0.5])],
        "center": np.zeros(3),
        "frame_fields": {
            "in_contact": [1, 1],
            "device_pos": [[-0.03, 0, 0], [0.03, 0, 0]],
            "contact_point": [[-0.025, 0, 0], [0.025, 0, 0]],
            "contact_force": [[1.0, 0, 0.1], [-1.0, 0, 0.1]],
        },
    }
    case["frame_fields"][field] = np.array(case["frame_fields"][field], dtype=float)
    case["frame_fields"][field][1, 2] = bad
    ref, got = _outputs(case, None), _outputs(case, compiled)
    if field == "device_pos" and bad is math.nan:
        # A NaN grasp line fails grasp_axes' length test: world x stands in (the safety
        # chain faults on the device's NaN position itself); both paths alike.
        assert not isinstance(ref, str)
    else:
        assert isinstance(ref, str) and "non-finite" in ref
    _assert_same(ref, got)


@pytest.mark.parametrize("method", kernels.ALLOCATION_METHODS)
@pytest.mark.parametrize("size", [1e300, 1e307, 1.7e308])
def test_forces_that_overflow_raise_the_python_stages_error(compiled, method, size):
    """Finite forces whose products overflow: the same error (or the same numbers) on both."""
    case = {
        "n": 2,
        "robust": Robustness(eps=0.05),
        "method": method,
        "frame": "world",
        "local": [np.array([0.8660254, 0, 0.5]), np.array([-0.8660254, 0, 0.5])],
        "center": np.zeros(3),
        "frame_fields": {
            "in_contact": [1, 1],
            "device_pos": [[-0.03, 0, 0], [0.03, 0, 0]],
            "contact_point": [[-0.025, 0, 0], [-0.0249, 0, 0]],
            "contact_force": [[size, 0, size], [-size, 0, size]],
        },
    }
    ref, got = _outputs(case, None), _outputs(case, compiled)
    _assert_same(ref, got)
    if size > 1e307:
        assert isinstance(ref, str) and "produced a non-finite force" in ref
    else:  # finite forces; the residuals may overflow (inf), as in the Python code
        assert not isinstance(ref, str) and np.all(np.isfinite(ref["lam_a"]))


def _pair(method: str, local, points, forces, eps: float = 0.05, frame: str = "world") -> dict:
    return {
        "n": 2,
        "robust": Robustness(eps=eps),
        "method": method,
        "frame": frame,
        "local": [np.array(d, dtype=float) for d in local],
        "center": np.zeros(3),
        "frame_fields": {
            "in_contact": [1, 1],
            "device_pos": points,
            "contact_point": points,
            "contact_force": forces,
        },
    }


BRANCHES = {
    # Directions exactly across the grasp line: B = 0, P = I, F(P K_M P) well-conditioned.
    "if, across the line": _pair(
        "if", [(0, 0, 1), (0, 1, 0)], [[-0.02, 0, 0], [0.02, 0, 0]], [[1, 0, 1], [-1, 0, 1]]
    ),
    # Coincident contacts (w = 1): K_B well-conditioned for distinct directions.
    "if, coincident": _pair(
        "if", [(1, 0, 0), (0, 1, 0)], [[0.01, 0, 0], [0.01, 0, 0]], [[1, 0.5, 0], [-1, 0, 0]]
    ),
    "if, nearly coincident": _pair(
        "if", [(1, 0, 0), (0, 0.6, 0.8)], [[0, 0, 0], [1e-4, 0, 0]], [[1, 0.5, 0], [-1, 0, 2]]
    ),
    "ef, along the line": _pair(
        "ef", [(1, 0, 0), (-1, 0, 0)], [[-0.02, 0, 0], [0.02, 0, 0]], [[1, 0, 0], [-0.5, 0, 0]]
    ),
    "pinv, grasp frame, vertical line": _pair(
        "pinv",
        [(0.8660254, 0, 0.5), (-0.8660254, 0, 0.5)],
        [[0, 0, 0], [0, 0, 0.04]],
        [[0, 0, 1], [0, 0, -1]],
        frame="grasp",
    ),
    "if, onset": _pair(
        "if", [(1, 0, 0.2), (-1, 0, 0.2)], [[-0.02, 0, 0], [0.02, 0, 0]], [[1, 0, 0], [-0.01, 0, 0]]
    ),
    "ef, onset, first weaker": _pair(
        "ef", [(1, 0, 0.2), (-1, 0, 0.2)], [[-0.02, 0, 0], [0.02, 0, 0]], [[0.02, 0, 0], [-1, 0, 0]]
    ),
}


@pytest.mark.parametrize("name", list(BRANCHES))
def test_rare_branches_of_the_closed_forms_give_the_same_bits(compiled, name):
    """Configurations random grasps seldom reach exactly (each one a branch of the kernel)."""
    ref = _outputs(BRANCHES[name], None)
    assert not isinstance(ref, str) and np.any(ref["lam_a"])
    _assert_same(ref, _outputs(BRANCHES[name], compiled))


@given(grasps())
def test_the_kernels_outcomes_leave_the_frame_untouched_when_they_refuse(compiled, case):
    """MANY_CONTACTS and the non-finite outcomes write nothing: the Python code (or the
    error) has the frame as the stages before left it."""
    n = case["n"]
    assume(n == 3)
    fields = {**case["frame_fields"], "in_contact": [1, 1, 1]}
    _, frame = _stage({**case, "frame_fields": fields}, compiled)
    for name in OUTPUTS:
        getattr(frame, name)[...] = 7.0
    outcome = compiled(
        frame.in_contact,
        frame.device_pos,
        frame.contact_point,
        frame.contact_force,
        np.array(case["local"], dtype=float),
        np.zeros(kernels.ALLOCATION_PARAMS),
        frame.lam_a,
        frame.rendered_force,
        np.zeros(kernels.ACCURACY),
    )
    assert outcome == kernels.MANY_CONTACTS
    assert np.all(frame.lam_a == 7.0) and np.all(frame.rendered_force == 7.0)
