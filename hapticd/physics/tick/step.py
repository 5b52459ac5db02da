"""The tick as one call (``tick_step``): the stages' kernels in order, on views of the
frame's record, the carried state and the plan cut out at offsets the layout generates from
the stages' declarations (``STAGES``; hapticd.physics.tick.layout). Nothing of the call's
interface is written by hand: the frame fields' offsets, the state's blocks, the plan's
blocks, the stages' indices, the switches and the parameter slots all follow from them.

Units: those of each stage's module.
"""

from __future__ import annotations

import numpy as np

from hapticd.allocation.kernels import ACCURACY, _axes
from hapticd.physics.tick import (
    allocation,
    contact,
    dynamics,
    environment,
    forces,
    friction,
    layout,
    loop,
    output,
    passivity,
    safety,
    views,
)
from hapticd.physics.tick.allocation import allocation_stage
from hapticd.physics.tick.contact import (
    CONTACT_DONE,
    CONTACT_STATE,
    PLANE_COLUMNS,
    contact_step,
    world_planes,
)
from hapticd.physics.tick.dynamics import (
    SCRATCH_COLUMNS,
    SURFACE_COLUMNS,
    free_body_step,
    object_bounded,
)
from hapticd.physics.tick.environment import environment_step
from hapticd.physics.tick.forces import forces_step
from hapticd.physics.tick.friction import FRICTION_COLUMNS, friction_step
from hapticd.physics.tick.loop import send, take_samples, watch_changes
from hapticd.physics.tick.output import scene_step, sum_step
from hapticd.physics.tick.passivity import PASSIVITY_STATE, passivity_step
from hapticd.physics.tick.safety import safety_step
from hapticd.physics.tick.views import _block, _bytes, _rows

# The stages of a tick, in the order the call runs them (hapticd.physics.stages names each
# stage's), the safety chain's tick last (when the call makes it).
STAGES = (
    contact.DECLARATION,
    friction.DECLARATION,
    forces.DECLARATION,
    allocation.DECLARATION,
    environment.DECLARATION,
    passivity.DECLARATION,
    output.OUTPUT,
    dynamics.DECLARATION,
    output.SCENE,
    safety.DECLARATION,
)
# What the call does for the loop besides the stages (its samples, its watcher).
EXTRAS = (loop.DECLARATION,)
STAGE = {s.name: i for i, s in enumerate(STAGES)}
STAGE_END = len(STAGES)

# The frame fields the call addresses, each one's offset in the record in float64 items at
# plan[FIELDS.index(name)]. With friction contact writes the frictionless ones and friction
# the final three; without, the frictionless ones are the final ones (the same offsets).
# residual_internal is followed by residual_external, residual_total, amplification and
# alpha; object_pos by object_vel, object_omega and object_rot (STATE floats).
FIELDS = layout.fields((*STAGES, *EXTRAS))
# The carried state's blocks (hapticd.physics.frame.STATE), the renderer's one array.
STATE_BLOCKS = layout.state_blocks((*STAGES, *EXTRAS))
# The plan's blocks (with their rows where they vary).
PLAN = layout.plan_blocks(STAGES)
# The call's params: the switches (1.0 or 0.0: what the plan has, and the first and past-
# last stage this call runs), then each stage's parameters in these blocks (the renderer
# fills neighbouring blocks in one slice: keep this order).
FLAG = layout.flags(STAGES, ("first", "last"))
PARAM_ORDER = ("passivity", "friction", "forces", "allocation", "dynamics")
PARAMS_AT = layout.param_slots(STAGES, PARAM_ORDER, len(FLAG))
N_PARAMS = max(hi for _, hi in PARAMS_AT.values())


def state_layout(n_fingers: int, n_directions: int) -> dict[str, tuple[int, tuple[int, ...]]]:
    """Each STATE_BLOCKS block's (offset in float64 items, shape) for F fingers with D
    actuated directions in all."""
    shapes = layout.state_shapes((*STAGES, *EXTRAS), n_fingers, n_directions)
    return layout.layout_of(STATE_BLOCKS, shapes)


# tick_step's plan: one float64 array: where things are (TICK_AT items: each FIELDS
# field's offset in the frame's record, then each PLAN block's, then each STATE_BLOCKS
# block's in the state and the allocator's workspace's rows and columns, then in_contact's
# and buttons' offsets in the record's bytes, and the number of fingers), the params
# (N_PARAMS), then the PLAN blocks.
_AT_PLAN = len(FIELDS)
_AT_STATE = _AT_PLAN + len(PLAN)
_AT_WORK_SHAPE = _AT_STATE + len(STATE_BLOCKS)
_AT_IN_CONTACT = _AT_WORK_SHAPE + 2
_AT_BUTTONS = _AT_IN_CONTACT + 1
_AT_FINGERS = _AT_BUTTONS + 1
TICK_AT = _AT_FINGERS + 1

# tick_step's outcomes: done; stopped at contact, a non-finite input (nothing of it
# written: the contact stage names it); allocation refused a non-finite input or produced
# a non-finite output (nothing after it written); with the safety chain's tick: a free
# object's state beyond MAX_OBJECT_* (the chain not run: the loop latches the fault);
# TICK_SAFE + safety_step's outcome: done, the safety chain's tick too (a trip zeroed
# device_force; the chain latches it). From TICK_FINISHED on, every stage of the plan
# has run. TICK_SAMPLES: the devices' samples the call was to check (the loop's block
# says they wait) hold one no hand makes (non-finite, too fast or too far): nothing
# written, the device bank checks them itself, with its messages.
TICK_FROM_CONTACT, TICK_SAMPLES, TICK_NON_FINITE_INPUT, TICK_NON_FINITE_OUTPUT = 1, 2, 3, 4
TICK_FINISHED = TICK_DONE = 5
TICK_OBJECT = 6
TICK_SAFE = 16

# Constants the compiled call folds in: the fields', blocks', stages' and slots' indices.
_F = {name: i for i, name in enumerate(FIELDS)}
_POS, _VEL, _SAMPLE, _T = _F["device_pos"], _F["device_vel"], _F["device_sample"], _F["t"]
_PLAIN_PROXY, _PLAIN_SURFACE = _F["frictionless_proxy"], _F["frictionless_point"]
_PLAIN_POINT, _NORMAL, _ENV = (
    _F["frictionless_contact_point"],
    _F["contact_normal"],
    _F["env_force"],
)
_PROXY, _SURFACE, _POINT = _F["proxy_pos"], _F["surface_point"], _F["contact_point"]
_FORCE, _LAM, _ALLOCATED = _F["contact_force"], _F["lam_a"], _F["allocated_force"]
_SCALARS, _ENV_RENDERED = _F["residual_internal"], _F["env_rendered"]
_DAMPING_FORCE, _ENERGY = _F["passivity_force"], _F["passivity_energy"]
_DAMPING, _RENDERED = _F["passivity_damping"], _F["rendered_force"]
_OBJECT, _DEVICE_FORCE = _F["object_pos"], _F["device_force"]
_B = {name: _AT_PLAN + PLAN.index(name) for name in PLAN if name != "rows"}
_PLANES, _BODY, _SURF, _NORMALS = _B["planes"], _B["body"], _B["surf"], _B["normals"]
_OFFSETS, _SCRATCH, _DIRECTIONS, _COUNTS = (
    _B["offsets"],
    _B["scratch"],
    _B["directions"],
    _B["counts"],
)
_S = {name: _AT_STATE + i for i, name in enumerate(STATE_BLOCKS)}
_S_CONTACT, _S_ANCHORS, _S_PASSIVE = _S["contact"], _S["anchors"], _S["passive"]
_S_ALLOC, _S_WORK, _S_LOOP = _S["alloc"], _S["work"], _S["loop"]
_CONTACT, _FRICTION, _FORCES = STAGE["contact"], STAGE["friction"], STAGE["forces"]
_ALLOCATION, _ENVIRONMENT, _PASSIVITY = (
    STAGE["allocation"],
    STAGE["environment"],
    STAGE["passivity"],
)
_SUM, _DYNAMICS, _SCENE, _SAFETY = (
    STAGE["output"],
    STAGE["dynamics"],
    STAGE["scene"],
    STAGE["safety"],
)
_FIRST, _LAST = FLAG["first"], FLAG["last"]
_ON_FRICTION, _ON_FREE, _ON_SURFACES = FLAG["friction"], FLAG["free"], FLAG["surfaces"]
_ON_SUM, _ON_SAFETY, _ON_PASSIVITY = FLAG["sum"], FLAG["safety"], FLAG["passivity"]
_PASSIVITY_AT, _PASSIVITY_END = PARAMS_AT["passivity"]
_FRICTION_AT, _FRICTION_END = PARAMS_AT["friction"]
_FORCES_AT, _FORCES_END = PARAMS_AT["forces"]
_ALLOCATION_AT, _ALLOCATION_END = PARAMS_AT["allocation"]
_BODY_AT, _BODY_END = PARAMS_AT["dynamics"]
_GRASP_FRAME = _ALLOCATION_AT + allocation.GRASP_FRAME_AT


def _field(record: np.ndarray, plan: np.ndarray, at: int, n: int) -> np.ndarray:
    """The (n, 3) field whose offset is plan[at] as a view of ``record``."""
    return _rows(record, int(plan[at]), n)


def tick_step(
    record: np.ndarray,
    state: np.ndarray,
    plan: np.ndarray,
    obj_state: np.ndarray,
    safety_params: np.ndarray,
    out_prev: np.ndarray,
) -> int:
    """The renderer's plan as one call, stage by stage (STAGES' indices params[first] to
    before params[last]): the waiting device samples checked, the object's planes,
    contact, friction, forces, allocation, environment, passivity, their sum, the free
    object's step, the scene's state; with params[safety], the object checked and the
    safety chain's tick into ``device_force``. Returns a TICK_ outcome.

    ``record``: the frame's record as float64 items (``plan`` says where each field is);
    ``state``: the carried state (STATE_BLOCKS); ``plan``: offsets, params and the PLAN
    blocks; ``obj_state`` (STATE,); ``safety_params`` and ``out_prev``: the chain's arrays
    (safety_step).
    """
    n = int(plan[_AT_FINGERS])
    lp = int(plan[_S_LOOP])
    if state[lp + loop.LOOP_SAMPLES] != 0.0:
        # A sample no hand makes refuses the tick before anything is written.
        at_pos, at_vel = int(plan[_POS]), int(plan[_VEL])
        if not take_samples(record, state, lp, int(plan[_SAMPLE]), at_pos, at_vel, n):
            return TICK_SAMPLES
    ic, bt = int(plan[_AT_IN_CONTACT]), int(plan[_AT_BUTTONS])
    in_contact = _bytes(record)[ic : ic + n]
    params = plan[TICK_AT : TICK_AT + N_PARAMS]
    first, last = params[_FIRST], params[_LAST]
    n_dirs = int(plan[_DIRECTIONS + 1])
    directions = _rows(plan, int(plan[_DIRECTIONS]), n_dirs)
    counts = plan[int(plan[_COUNTS]) : int(plan[_COUNTS]) + n]
    device_pos = _field(record, plan, _POS, n)
    device_vel = _field(record, plan, _VEL, n)
    plain_proxy = _field(record, plan, _PLAIN_PROXY, n)
    plain_surface = _field(record, plan, _PLAIN_SURFACE, n)
    plain_point = _field(record, plan, _PLAIN_POINT, n)
    normal = _field(record, plan, _NORMAL, n)
    env_force = _field(record, plan, _ENV, n)
    surface_point = _field(record, plan, _SURFACE, n)
    contact_point = _field(record, plan, _POINT, n)
    contact_force = _field(record, plan, _FORCE, n)
    allocated = _field(record, plan, _ALLOCATED, n)
    env_rendered = _field(record, plan, _ENV_RENDERED, n)
    damping_force = _field(record, plan, _DAMPING_FORCE, n)
    rendered = _field(record, plan, _RENDERED, n)
    if first <= _CONTACT < last:
        planes = _block(plan, int(plan[_PLANES]), int(plan[_PLANES + 1]), PLANE_COLUMNS)
        m = int(plan[_NORMALS + 1])
        body_normals = _rows(plan, int(plan[_NORMALS]), m)
        body_offsets = plan[int(plan[_OFFSETS]) : int(plan[_OFFSETS]) + m]
        world_planes(_rows(obj_state, 9, 3), obj_state[0:3], body_normals, body_offsets, planes)
        contact_state = _block(state, int(plan[_S_CONTACT]), n, CONTACT_STATE)
        found = contact_step(
            device_pos,
            device_vel,
            planes,
            contact_state,
            plain_proxy,
            in_contact,
            plain_surface,
            plain_point,
            normal,
            env_force,
        )
        if found != CONTACT_DONE:
            return TICK_FROM_CONTACT
    if params[_ON_FRICTION] != 0.0 and first <= _FRICTION < last:
        friction_step(
            in_contact,
            device_pos,
            plain_surface,
            plain_proxy,
            plain_point,
            surface_point,
            normal,
            _field(record, plan, _PROXY, n),
            contact_point,
            _block(state, int(plan[_S_ANCHORS]), n, FRICTION_COLUMNS),
            obj_state,
            params[_FRICTION_AT:_FRICTION_END],
        )
    if first <= _FORCES < last:
        forces_step(
            in_contact,
            device_pos,
            device_vel,
            surface_point,
            normal,
            contact_force,
            obj_state,
            params[_FORCES_AT:_FORCES_END],
        )
    if first <= _ALLOCATION < last:
        at = int(plan[_S_ALLOC])
        outcome = allocation_stage(
            in_contact,
            device_pos,
            contact_point,
            contact_force,
            directions,
            counts,
            params[_ALLOCATION_AT:_ALLOCATION_END],
            state[at : at + allocation.ALLOCATION_STATE],
            record[int(plan[_LAM]) : int(plan[_LAM]) + n_dirs],
            allocated,
            record[int(plan[_SCALARS]) : int(plan[_SCALARS]) + ACCURACY + 1],
            _block(
                state, int(plan[_S_WORK]), int(plan[_AT_WORK_SHAPE]), int(plan[_AT_WORK_SHAPE + 1])
            ),
            obj_state,
        )
        if outcome == allocation.STOPPED_INPUT:
            return TICK_NON_FINITE_INPUT
        if outcome == allocation.STOPPED_OUTPUT:
            return TICK_NON_FINITE_OUTPUT
    surfaces, passive = params[_ON_SURFACES] != 0.0, params[_ON_PASSIVITY] != 0.0
    # The actuation frame's axes in the world (the grasp's moves with the fingers).
    ax = _axes(device_pos, params[_GRASP_FRAME] != 0.0 and (surfaces or passive))
    if surfaces and first <= _ENVIRONMENT < last:
        environment_step(env_force, directions, counts, ax, env_rendered)
    if passive and first <= _PASSIVITY < last:
        passivity_step(
            device_pos,
            allocated,
            env_rendered,
            surfaces,
            directions,
            counts,
            ax,
            params[_PASSIVITY_AT:_PASSIVITY_END],
            _block(state, int(plan[_S_PASSIVE]), n, PASSIVITY_STATE),
            damping_force,
            record[int(plan[_ENERGY]) : int(plan[_ENERGY]) + n],
            record[int(plan[_DAMPING]) : int(plan[_DAMPING]) + n],
        )
    if params[_ON_SUM] != 0.0 and first <= _SUM < last:
        sum_step(allocated, env_rendered, damping_force, surfaces, passive, rendered)
    if params[_ON_FREE] != 0.0 and first <= _DYNAMICS < last:
        free_body_step(
            in_contact,
            contact_point,
            contact_force,
            normal,
            params[_BODY_AT:_BODY_END],
            obj_state,
            _rows(plan, int(plan[_BODY]), int(plan[_BODY + 1])),
            _block(plan, int(plan[_SURF]), int(plan[_SURF + 1]), SURFACE_COLUMNS),
            _block(plan, int(plan[_SCRATCH]), n, SCRATCH_COLUMNS),
        )
    if first <= _SCENE < last:
        scene_step(obj_state, record, int(plan[_OBJECT]))
    watch = state[lp + loop.LOOP_WATCH] != 0.0
    if watch and first <= _SAFETY < last:
        watch_changes(_bytes(record), state, lp, ic, bt, n)
    if params[_ON_SAFETY] == 0.0 or not first <= _SAFETY < last:
        return TICK_DONE
    if params[_ON_FREE] != 0.0 and not object_bounded(obj_state):
        return TICK_OBJECT
    t = record[int(plan[_T])]
    outcome = safety_step(
        rendered, device_pos, _bytes(record)[bt : bt + 4 * n], safety_params, out_prev, t
    )
    send(out_prev, _field(record, plan, _DEVICE_FORCE, n), state, lp, watch, n)
    return TICK_SAFE + outcome


DECLARATIONS = (*STAGES, *EXTRAS)
# The files whose code the call compiles in (hapticd.physics.kernels.SOURCES).
_MODULES = (allocation, contact, dynamics, environment, forces, friction, layout, loop, output)
SOURCES = (*(m.__file__ for m in (*_MODULES, passivity, safety, views)), __file__)
