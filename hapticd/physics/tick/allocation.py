"""The Allocation stage in the one call: the contact forces onto the actuated directions by
hapticd.allocation.kernels' ``allocation_step`` (allocation owns its kernel, its params and
its state). Its declaration and its part of the call (``allocation_stage``).

Units: positions m, forces N.
"""

from __future__ import annotations

import numpy as np

from hapticd.allocation import kernels as allocation
from hapticd.allocation.kernels import (
    ACCURACY,
    ALLOCATED,
    ALLOCATION_PARAMS,
    ALLOCATION_STATE,
    NON_FINITE_INPUT,
    NON_FINITE_OUTPUT,
    allocation_step,
    allocation_work_shape,
)
from hapticd.physics.tick.layout import Declaration

# allocation_step's outcomes the call stops at (``allocation_stage``'s, besides ALLOCATED).
STOPPED_INPUT, STOPPED_OUTPUT = NON_FINITE_INPUT, NON_FINITE_OUTPUT
# Its params' items the call writes each tick: the object's position (3, m).
OBJECT_AT = 5
# Its params' item saying the actuation's frame is the grasp's (moves with the fingers).
GRASP_FRAME_AT = 4


def allocation_stage(
    in_contact: np.ndarray,
    device_pos: np.ndarray,
    contact_point: np.ndarray,
    contact_force: np.ndarray,
    directions: np.ndarray,
    counts: np.ndarray,
    params: np.ndarray,
    state: np.ndarray,
    lam_a: np.ndarray,
    allocated: np.ndarray,
    scalars: np.ndarray,
    work: np.ndarray,
    obj_state: np.ndarray,
) -> int:
    """allocation_step with the object's position (from ``obj_state``) in its params and the
    allocator's alpha after the accuracy in ``scalars`` (ACCURACY + 1,); its outcome."""
    params[OBJECT_AT], params[OBJECT_AT + 1] = obj_state[0], obj_state[1]
    params[OBJECT_AT + 2] = obj_state[2]
    outcome = allocation_step(
        in_contact,
        device_pos,
        contact_point,
        contact_force,
        directions,
        counts,
        params,
        state,
        lam_a,
        allocated,
        scalars,
        work,
    )
    if outcome == ALLOCATED:  # else nothing after the refusal is written
        scalars[ACCURACY] = state[0]
    return outcome


DECLARATION = Declaration(
    "allocation",
    reads=("in_contact", "device_pos", "contact_point", "contact_force"),
    fields=("contact_point", "contact_force", "lam_a", "allocated_force", "residual_internal"),
    state=(
        ("alloc", lambda n, d: (ALLOCATION_STATE,)),
        ("work", allocation_work_shape),
    ),
    blocks=(("directions", True), ("counts", False)),
    params=tuple(f"allocation_{i}" for i in range(ALLOCATION_PARAMS)),
    helpers=("allocation_stage",),
)
# Compiled into the call too: allocation's own helpers (functions of hapticd.allocation).
HELPERS = allocation.KERNEL_HELPERS
SOURCES = allocation.SOURCES
