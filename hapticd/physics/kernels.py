"""The tick's physics under the names the renderer, the loop and the tests use: a thin
front of the stage modules of hapticd.physics.tick (one module a stage: its declaration,
its parameters' packing and its kernel; the call's interface generated from them).

``tick_step`` is the renderer's whole tick as one call; the stages' physics
(``contact_step``, ``friction_step``, ``forces_step``, ``allocation_step``,
``free_body_step``, ``safety_step``) are compiled into it with ``KERNEL_HELPERS``.
hapticd.physics.jit compiles the entry points (its ``SIGNATURES``); ``uncompiled``
runs the same functions as plain Python. The tick as a picture: docs/architecture.md.

Units: positions m, velocities m/s, angular velocities rad/s, forces N, torques
N m, stiffness N/m, damping N s/m, mass kg, inertia kg m^2, times s.
"""

from __future__ import annotations

from collections.abc import Callable

from hapticd.allocation import kernels as allocation
from hapticd.allocation.kernels import (  # noqa: F401 (the old names)
    ACCURACY,
    ALLOCATION_PARAMS,
    ALLOCATION_STATE,
    NON_FINITE_INPUT,
    NON_FINITE_OUTPUT,
    _axes,
    allocation_step,
    allocation_work_shape,
    python_form,
)
from hapticd.physics.passivity import authority, control, observe
from hapticd.physics.tick import step
from hapticd.physics.tick.allocation import allocation_stage  # noqa: F401
from hapticd.physics.tick.contact import (  # noqa: F401
    _C_ACTIVE,
    _C_MU,
    _C_PUSHED,
    _C_RADIUS,
    _C_RHS,
    _FREE_TOL,
    _GRAM_MIN,
    _MAX_CONSTRAINTS,
    _MAX_ITER,
    _ON_PLANE,
    _T_EPS,
    CONTACT_DONE,
    CONTACT_NOT_TAKEN,
    CONTACT_STATE,
    PLANE_COLUMNS,
    _along,
    _deepest,
    _entry,
    _finite,
    _first_entry,
    _gap,
    _gram_mu,
    _on_object,
    _project,
    _push_out,
    _pushing,
    _slide,
    _solve2,
    _still_held,
    _surfaces_force,
    contact_step,
    world_planes,
)
from hapticd.physics.tick.dynamics import (  # noqa: F401
    BODY_HEAD,
    MAX_OBJECT_DISTANCE_M,
    MAX_OBJECT_SPEED_M_PER_S,
    MAX_OBJECT_SPIN_RAD_PER_S,
    PARAMS,
    SCRATCH_COLUMNS,
    STATE,
    SURFACE_COLUMNS,
    free_body_step,
    object_bounded,
)
from hapticd.physics.tick.environment import _span_project, environment_step  # noqa: F401
from hapticd.physics.tick.forces import FORCES_PARAMS, forces_step  # noqa: F401
from hapticd.physics.tick.friction import (  # noqa: F401
    ANCHOR_SET,
    FINGER_RADIUS,
    FRICTION_COLUMNS,
    FRICTION_PARAMS,
    friction_step,
)
from hapticd.physics.tick.loop import (  # noqa: F401
    LOOP_CHANGED,
    LOOP_HEAD,
    LOOP_MAX_DISTANCE,
    LOOP_MAX_SPEED,
    LOOP_SAMPLES,
    LOOP_WATCH,
    plausible,
    send,
    take_samples,
    watch_changes,
)
from hapticd.physics.tick.output import scene_step, sum_step  # noqa: F401
from hapticd.physics.tick.passivity import (  # noqa: F401
    PASSIVITY_PARAMS,
    PASSIVITY_STATE,
    passivity_step,
)
from hapticd.physics.tick.safety import (  # noqa: F401
    SAFETY_BUTTON,
    SAFETY_BUTTON_RAMP,
    SAFETY_CENTRE,
    SAFETY_CLAMPED,
    SAFETY_CLAMPED_TICKS,
    SAFETY_COLUMNS,
    SAFETY_DISTANCE,
    SAFETY_DOWN_S,
    SAFETY_FINGERS,
    SAFETY_GATE,
    SAFETY_LATCHED,
    SAFETY_LIMIT,
    SAFETY_LIMITED,
    SAFETY_LIMITED_TICKS,
    SAFETY_NON_FINITE,
    SAFETY_PARAMS,
    SAFETY_PRESSED,
    SAFETY_RADIUS,
    SAFETY_RAMP_S,
    SAFETY_RATE,
    SAFETY_T_DOWN,
    SAFETY_T_ENABLED,
    SAFETY_WORKSPACE,
    _gates,
    _limited,
    _norm3,
    _ramp,
    _trips,
    ramp_down_factor,
    safety_step,
)
from hapticd.physics.tick.step import (  # noqa: F401
    TICK_AT,
    TICK_DONE,
    TICK_FINISHED,
    TICK_FROM_CONTACT,
    TICK_NON_FINITE_INPUT,
    TICK_NON_FINITE_OUTPUT,
    TICK_OBJECT,
    TICK_SAFE,
    TICK_SAMPLES,
    _field,
    state_layout,
    tick_step,
)
from hapticd.physics.tick.views import (  # noqa: F401
    COMPILED_FORMS,
    _block,
    _block_compiled,
    _bytes,
    _bytes_compiled,
    _rows,
)

_passivity = passivity_step  # its old name


def uncompiled(name: str) -> Callable[..., object]:
    """Kernel ``name`` of this module as plain Python (hapticd.allocation.kernels'
    ``python_form``: on memoryviews of its arrays). One function per name."""
    return python_form(globals()[name])


# The call's interface, generated from the stages' declarations (hapticd.physics.tick.step).
TICK_FIELDS = step.FIELDS
TICK_PLAN = step.PLAN
TICK_STATE = step.STATE_BLOCKS
TICK_PARAMS = step.N_PARAMS
TICK_FIRST, TICK_LAST = step.FLAG["first"], step.FLAG["last"]
TICK_FRICTION, TICK_FREE, TICK_SURFACES = (step.FLAG[k] for k in ("friction", "free", "surfaces"))
TICK_SUM, TICK_SAFETY, TICK_PASSIVITY = (step.FLAG[k] for k in ("sum", "safety", "passivity"))
TICK_PASSIVITY_AT = step.PARAMS_AT["passivity"][0]
TICK_FRICTION_AT = step.PARAMS_AT["friction"][0]
TICK_FORCES_AT = step.PARAMS_AT["forces"][0]
TICK_ALLOCATION_AT = step.PARAMS_AT["allocation"][0]
TICK_BODY_AT = step.PARAMS_AT["dynamics"][0]
# The stages of a tick, in order, as tick_step runs them (hapticd.physics.stages names each
# stage's), then the safety chain's tick (when the call makes it).
STAGE_CONTACT, STAGE_FRICTION, STAGE_FORCES = (
    step.STAGE[k] for k in ("contact", "friction", "forces")
)
STAGE_ALLOCATION, STAGE_ENVIRONMENT = step.STAGE["allocation"], step.STAGE["environment"]
STAGE_PASSIVITY, STAGE_SUM, STAGE_DYNAMICS = (
    step.STAGE[k] for k in ("passivity", "output", "dynamics")
)
STAGE_SCENE, STAGE_SAFETY, STAGE_END = step.STAGE["scene"], step.STAGE["safety"], step.STAGE_END

# Functions the kernels call (everything else a kernel does is inline): the stages' (their
# declarations name them), the call's own and the allocation's (hapticd.allocation.kernels',
# written once for the loop, allocate() and allocate_many). hapticd.physics.jit compiles
# them into the kernels that call them.
KERNEL_HELPERS = (
    *allocation.KERNEL_HELPERS,
    *dict.fromkeys(h for d in step.DECLARATIONS for h in d.helpers),
    "_field",
    "_rows",
    "_block",
    "_bytes",
)
# Helpers compiled inline into their callers (numba's IR inlining): the parts the stages'
# kernels were split into, so that the split costs the compiled tick no calls.
INLINED = frozenset(
    (
        *("_finite", "_deepest", "_push_out", "_entry", "_first_entry", "_still_held"),
        *("_slide", "_pushing", "_surfaces_force", "_on_object"),
        *("_gates", "_trips", "_ramp", "_limited", "object_bounded"),
        *("allocation_stage", "environment_step", "sum_step", "scene_step"),
        *("take_samples", "watch_changes", "send", "_field"),
    )
)
_missing = [h for h in (*KERNEL_HELPERS, *INLINED) if isinstance(h, str) and h not in globals()]
if _missing:
    raise RuntimeError(f"kernels: helpers the stages declare but this module lacks: {_missing}")
# The sources whose code or constants the kernels compile in: numba's cache knows only the
# entry point's file, so hapticd.physics.jit keys its record of compiled kernels on all of
# them.
SOURCES = (
    __file__,
    *step.SOURCES,
    *allocation.SOURCES,
    observe.__code__.co_filename,
    __file__.replace("kernels.py", "native.py"),  # an allocator plugin's call (numba's)
)
_ = (authority, control)  # compiled in through passivity's declaration
