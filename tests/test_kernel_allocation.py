"""The compiled allocation kernel (hapticd.allocation.kernels.allocation_step) against the same
function uncompiled: the same bits for generated grasps of two to five fingers, near-singular ones
included (coincident and nearly coincident contacts, directions along the grasp line or
nearly parallel, forces at contact onset, a vertical grasp line in the grasp frame); and
against allocate() with contact onset; the cases it does not take run allocate();
non-finite input raises the same error and leaves alpha as it was."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hapticd.allocation import (
    AdaptiveState,
    AllocationError,
    Robustness,
    allocate,
    kernels,
    smoothstep,
)
from hapticd.allocation.actuation import Actuation
from hapticd.allocation.contacts import ContactAllocator
from hapticd.allocation.grasp import grasp_matrix
from hapticd.physics import jit
from hapticd.physics.frame import Frame
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject
from hapticd.physics.stages import Allocation
from tests.strategies import unit_vectors
from tests.test_allocation_robust import bound
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
def grasps(draw, max_fingers: int = 5) -> dict:
    """A tick's frame for 2 to ``max_fingers`` fingers with one direction each, the method and
    robustness, the object's position. Contacts are often close (below min_separation_m,
    down to coincident), forces often below the contact onset, directions often along the
    grasp line or nearly parallel: the allocators' singular configurations."""
    n_fingers = draw(st.integers(2, max_fingers))
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


def _actuation(case: dict) -> Actuation:
    """The case's actuation: each finger's direction, or its list of directions."""
    return Actuation([d if isinstance(d, list) else [d] for d in case["local"]], case["frame"])


def _stage(case: dict, kernel) -> tuple[Allocation, Frame]:
    obj = SceneObject(ConvexShape.box(np.full(3, 0.05)), Material(100.0), case["center"], np.eye(3))
    act = _actuation(case)
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


def _allocate_with_onset(case: dict, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """lam_a and M_a lam_a per finger by allocate() on the contacts, with contact onset: the
    weakest contact blended in by smoothstep(|force| / contact_onset_n)."""
    fields, rb = case["frame_fields"], case["robust"]
    act = _actuation(case)
    world = act.world_directions(np.asarray(fields["device_pos"], dtype=float).tolist())
    points = np.asarray(fields["contact_point"], dtype=float)
    forces = np.asarray(fields["contact_force"], dtype=float)

    def solve(contacts: list[int]) -> np.ndarray:
        out = np.zeros(act.n_actuators)
        if contacts:
            M, cols = act.submatrix(world, contacts)
            G = grasp_matrix(points[contacts], case["center"])
            lam = forces[contacts].reshape(-1)
            out[cols] = allocate(case["method"], G, M, lam, robust=rb, alpha=alpha)
        return out

    contacts = [i for i, on in enumerate(fields["in_contact"]) if on]
    x = solve(contacts)
    if len(contacts) >= 2 and rb.contact_onset_n > 0.0:
        norms = np.linalg.norm(forces[contacts], axis=1)
        weakest = int(np.argmin(norms))
        beta = smoothstep(float(norms[weakest]) / rb.contact_onset_n)
        if beta < 1.0:
            rest = contacts[:weakest] + contacts[weakest + 1 :]
            x = beta * x + (1.0 - beta) * solve(rest)
    rendered = np.zeros((case["n"], 3))
    for i in contacts:
        for j, d in zip(act.columns[i], world[i], strict=True):
            rendered[i] += x[j] * np.asarray(d)
    return x, rendered


def _against_allocate(case: dict, alpha: float) -> tuple[Allocation, Frame, bool]:
    """The stage (uncompiled, adaptive starting at ``alpha``) against allocate() on the
    contacts with contact onset: the same forces to 1e-9 of the force scale, or both refuse
    the tick (allocate() refusing or giving a non-finite force). Whether it allocated."""
    stage, frame = _stage(case, None)
    stage.allocator.adaptive = AdaptiveState(alpha=alpha, time_constant_s=1e9)
    try:
        stage.run(frame)
    except AllocationError:
        with np.errstate(all="ignore"):
            try:
                x, _ = _allocate_with_onset(case, stage.allocator.alpha)
            except AllocationError:
                return stage, frame, False
        assert not np.all(np.isfinite(x))
        return stage, frame, False
    x, rendered = _allocate_with_onset(case, stage.allocator.alpha)
    lam = np.abs(np.array(case["frame_fields"]["contact_force"])).max()
    for k, g in ((frame.lam_a, x), (frame.rendered_force, rendered)):
        scale = max(lam, np.abs(g).max(initial=0.0), 1e-300)
        np.testing.assert_allclose(k, g, rtol=0, atol=1e-9 * scale)
    return stage, frame, True


@given(grasps(), st.sampled_from(kernels.ALLOCATION_METHODS), st.floats(0.0, 1.0))
def test_the_kernel_equals_allocate_with_contact_onset(case, method, alpha):
    """The kernel's closed forms and general path, grasp frame and contact onset against
    allocate() (with the world directions of hapticd.allocation.actuation) on the contacts, blended
    at onset: the same forces to rounding, near singular configurations too; adaptive with
    the kernel's alpha of the tick; within the documented bounds (compiled, the same bits:
    the tests above)."""
    case = {**case, "method": method}
    stage, frame, allocated = _against_allocate(case, alpha)
    # A tick both refused is checked; one allocated moved alpha by the task alone.
    assert not allocated or abs(stage.allocator.alpha - alpha) <= 1e-11
    # Finite, and within docs/allocation.md's bound (adaptive: the larger of IF's and EF's)
    # of the whole grasp: the onset blend, a mix of two allocations, stays within it too.
    contacts = [i for i, on in enumerate(case["frame_fields"]["in_contact"]) if on]
    if allocated and contacts:
        fields = case["frame_fields"]
        G = grasp_matrix(np.asarray(fields["contact_point"], dtype=float)[contacts], case["center"])
        M = np.eye(3 * len(contacts))  # sigma_max of one unit direction per finger: 1
        forces = np.asarray(fields["contact_force"], dtype=float)[contacts]
        names = ["if", "ef"] if method == "adaptive" else [method]
        eps = case["robust"].eps
        limit = max(bound(name, G, M, eps) for name in names) * np.linalg.norm(forces)
        assert np.all(np.isfinite(frame.lam_a))
        assert np.linalg.norm(frame.rendered_force) <= limit * (1 + 1e-9) + 1e-300


@given(grasps(max_fingers=3), st.sampled_from(["pinv_exact", "if_exact"]))
def test_methods_the_kernel_does_not_compute_run_the_general_path(compiled, case, method):
    case = {**case, "method": method}
    _assert_same(_outputs(case, None), _outputs(case, compiled))


def test_three_contacts_and_several_directions_on_a_finger_run_in_the_kernel(compiled):
    """Three contacts: the kernel allocates them (the squeeze along x whole, nothing for
    the third finger's vertical actuator to render), compiled and not alike; two directions
    on a finger: the kernel too."""
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
    assert not isinstance(ref, str)
    np.testing.assert_allclose(ref["lam_a"], [1.0, 1.0, 0.0], rtol=0, atol=1e-12)
    _assert_same(ref, _outputs(case, compiled))
    case["local"][:2] = [[np.array([1.0, 0, 0]), np.array([0.0, 1, 0])], np.array([1.0, 0, 0])]
    case["frame_fields"]["in_contact"] = [1, 1, 0]
    calls = []
    stage, frame = _stage(case, lambda *a: calls.append(a) or kernels.ALLOCATED)
    stage.run(frame)
    assert len(calls) == 1
    ref = _outputs(case, None)
    assert not isinstance(ref, str)
    _assert_same(ref, _outputs(case, compiled))
    # thumb x, thumb y, index x, the third finger (not in contact): the squeeze whole, no
    # y force to render, nothing for a finger out of contact.
    np.testing.assert_allclose(ref["lam_a"], [1.0, 0.0, -1.0, 0.0], rtol=0, atol=1e-12)


@st.composite
def several_directions(draw) -> dict:
    """A grasp of ``grasps()`` whose fingers have none to three actuated directions each (a
    fully actuated finger, one with a redundant pair, one with none)."""
    case = draw(grasps(max_fingers=4))
    local = []
    for d in case["local"]:
        k = draw(st.integers(0, 3))
        local.append([d, *(draw(directions(d)) for _ in range(k - 1))][:k])
    return {**case, "local": local}


@given(several_directions())
def test_several_directions_a_finger_compiled_and_not_give_the_same_bits(compiled, case):
    _assert_same(_outputs(case, None), _outputs(case, compiled))


@given(several_directions(), st.floats(0.0, 1.0))
def test_several_directions_a_finger_equal_allocate_with_contact_onset(case, alpha):
    """The kernel's general path on any actuation against allocate() on the contacts,
    blended at onset: the same forces to rounding."""
    _against_allocate(case, alpha)


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
@pytest.mark.parametrize("fingers", [2, 3])
def test_forces_that_overflow_raise_the_python_stages_error(compiled, method, size, fingers):
    """Finite forces whose products overflow: the same error (or the same numbers) on both,
    for two contacts (the closed forms) and three (the general path; uncompiled, a force's
    square once raised OverflowError there)."""
    case = {
        "n": fingers,
        "robust": Robustness(eps=0.05),
        "method": method,
        "frame": "world",
        "local": [np.array([0.8660254, 0, 0.5]), np.array([-0.8660254, 0, 0.5])],
        "center": np.zeros(3),
        "frame_fields": {
            "in_contact": [1] * fingers,
            "device_pos": [[-0.03, 0, 0], [0.03, 0, 0]],
            "contact_point": [[-0.025, 0, 0], [-0.0249, 0, 0]],
            "contact_force": [[size, 0, size], [-size, 0, size]],
        },
    }
    if fingers == 3:
        case["local"].append(np.array([0.0, -0.8660254, 0.5]))
        for name, row in (("device_pos", [0, 0.03, 0]), ("contact_point", [0, 0.025, 0])):
            case["frame_fields"][name].append(row)
        case["frame_fields"]["contact_force"].append([0, -size, size])
    ref, got = _outputs(case, None), _outputs(case, compiled)
    _assert_same(ref, got)
    if fingers == 3:
        assert isinstance(ref, str) or np.all(np.isfinite(ref["lam_a"]))
    elif size > 1e307:
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


@settings(max_examples=30)  # an early return: few cases cover it
@given(grasps(), st.sampled_from([math.nan, math.inf]), st.floats(0.0, 1.0))
def test_the_kernels_refusals_leave_the_frame_and_alpha_untouched(compiled, case, bad, alpha):
    """A non-finite contact force refused (two to five contacts, adaptive): nothing written,
    alpha as it was."""
    fields = {**case["frame_fields"], "in_contact": [1] * case["n"]}
    stage, frame = _stage({**case, "method": "adaptive", "frame_fields": fields}, compiled)
    frame.contact_force[-1, 0] = bad
    for name in OUTPUTS:
        getattr(frame, name)[...] = 7.0
    alloc = stage.allocator
    alloc.alpha = alpha
    local, counts, params = alloc.kernel_inputs()
    outcome = compiled(
        frame.in_contact,
        frame.device_pos,
        frame.contact_point,
        frame.contact_force,
        local,
        counts,
        params,
        alloc.state,
        frame.lam_a,
        frame.rendered_force,
        np.zeros(kernels.ACCURACY),
        alloc.work,
    )
    assert outcome == kernels.NON_FINITE_INPUT
    assert np.all(frame.lam_a == 7.0) and np.all(frame.rendered_force == 7.0)
    assert alloc.alpha == alpha


def _three_finger_sweep(name: str, t: float) -> dict:
    """Three fingers on a 50 mm grasp through a rank change at t = 0: the third contact
    crossing the line of the other two ("collinear": the soft internal projector blends),
    or every direction turning vertical ("vertical": B = P_int M_a loses rank)."""
    points = [[-0.025, 0.0, 0.0], [0.025, 0.0, 0.0], [0.0, 0.02, 0.0]]
    inward = [(1.0, 0.0), (-1.0, 0.0), (0.0, -1.0)]
    tilt = 0.6
    if name == "collinear":
        points[2][1] = t
    else:
        tilt = np.sin(t)
    local = [np.array([tilt * x, tilt * y, np.sqrt(1.0 - tilt * tilt)]) for x, y in inward]
    return {
        "n": 3,
        "robust": Robustness(),
        "method": "if",
        "frame": "world",
        "local": local,
        "center": np.zeros(3),
        "frame_fields": {
            "in_contact": [1, 1, 1],
            "device_pos": points,
            "contact_point": points,
            "contact_force": [[1.0, 0.2, 0.3], [-1.0, 0.1, 0.3], [0.1, -0.8, 0.3]],
        },
    }


@pytest.mark.parametrize("method", ["if", "ef", "adaptive"])  # pinv: no G, one M per finger
@pytest.mark.parametrize("name", ["collinear", "vertical"])
def test_the_kernel_is_continuous_through_rank_changes_of_three_contacts(compiled, name, method):
    """Compiled, through t = 0 on a coarse grid and one ten times finer around it: a
    continuous map's largest step shrinks with the grid, a jump would not; uncompiled, the
    same bits on every tenth point."""

    def sweep(ts, kernel) -> np.ndarray:
        stage, frame = _stage({**_three_finger_sweep(name, 0.0), "method": method}, kernel)
        local, counts, params = stage.allocator.kernel_inputs()
        params[5:8] = 0.0  # the grasp's reference point
        rows = []
        for t in ts:
            case = _three_finger_sweep(name, float(t))
            frame.contact_point[...] = case["frame_fields"]["contact_point"]
            local[...] = case["local"]
            stage.allocator.alpha = 0.0  # each point its own first tick
            outcome = stage.kernel(
                frame.in_contact, frame.device_pos, frame.contact_point, frame.contact_force,
                local, counts, params, stage.allocator.state, frame.lam_a, frame.rendered_force,
                np.zeros(kernels.ACCURACY), stage.allocator.work,
            )  # fmt: skip
            assert outcome == kernels.ALLOCATED
            rows.append(frame.lam_a.copy())
        return np.array(rows)

    coarse = np.linspace(-0.05, 0.05, 1001)
    fine = np.linspace(-0.005, 0.005, 1001)
    vals, near = sweep(coarse, compiled), sweep(fine, compiled)
    assert np.all(np.isfinite(vals)) and np.abs(vals).max() < 10.0
    jump_coarse = np.abs(np.diff(vals, axis=0)).max()
    jump_fine = np.abs(np.diff(near, axis=0)).max()
    assert jump_fine < 0.2 * jump_coarse + 1e-12
    assert jump_coarse < 0.05
    np.testing.assert_array_equal(sweep(fine[::10], kernels.allocation_step), near[::10])
