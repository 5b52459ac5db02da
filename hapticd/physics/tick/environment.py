"""The Environment stage: the ground's and walls' force on each finger (contact's
``env_force``) projected onto the span of the finger's own actuated directions, what the
device can render of it. Its declaration and its kernel (``environment_step``), with the
projection passivity shares (``_span_project``).

Units: forces N.
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.physics.passivity import DEPENDENT
from hapticd.physics.tick.layout import Declaration


def environment_step(
    env_force: np.ndarray,
    directions: np.ndarray,
    counts: np.ndarray,
    ax: tuple[float, ...],
    env_rendered: np.ndarray,
) -> None:
    """Each finger's ``env_force`` (F, 3) N projected onto the span of its ``counts[i]``
    actuated directions (``directions`` (D, 3) in the actuation's frame, finger by finger;
    its axes in the world ``ax``) into ``env_rendered`` (F, 3) N."""
    start = 0
    for i in range(env_force.shape[0]):
        c = int(counts[i])
        e0, e1, e2 = env_force[i, 0], env_force[i, 1], env_force[i, 2]
        p0 = p1 = p2 = 0.0
        if e0 != 0.0 or e1 != 0.0 or e2 != 0.0:
            p0, p1, p2 = _span_project(directions, start, c, ax, e0, e1, e2)
        env_rendered[i, 0], env_rendered[i, 1], env_rendered[i, 2] = p0, p1, p2
        start += c


def _span_project(
    directions: np.ndarray,
    start: int,
    count: int,
    ax: tuple[float, ...],
    v0: float,
    v1: float,
    v2: float,
) -> tuple[float, float, float]:
    """(v0, v1, v2) projected onto the span of a finger's ``count`` actuated directions
    (rows ``start`` on of ``directions``, in the actuation's frame, whose axes in the world
    are ``ax``: _axes'), by Gram-Schmidt in order: a direction whose part orthogonal to the
    ones before is shorter than DEPENDENT of it adds nothing; three independent ones span
    everything (v itself)."""
    k = 0
    b0 = b1 = b2 = c0 = c1 = c2 = 0.0  # the first two unit vectors of the basis
    p0 = p1 = p2 = 0.0
    for j in range(start, start + count):
        l0, l1, l2 = directions[j, 0], directions[j, 1], directions[j, 2]
        x = ax[0] * l0 + ax[3] * l1 + ax[6] * l2
        y = ax[1] * l0 + ax[4] * l1 + ax[7] * l2
        z = ax[2] * l0 + ax[5] * l1 + ax[8] * l2
        n0 = math.sqrt(x * x + y * y + z * z)
        if not n0 > 0.0:  # also false for NaN
            continue
        if k > 0:
            d = x * b0 + y * b1 + z * b2
            x, y, z = x - d * b0, y - d * b1, z - d * b2
        if k > 1:
            d = x * c0 + y * c1 + z * c2
            x, y, z = x - d * c0, y - d * c1, z - d * c2
        m = math.sqrt(x * x + y * y + z * z)
        if not m > DEPENDENT * n0:
            continue
        if k == 2:
            return v0, v1, v2
        x, y, z = x / m, y / m, z / m
        d = v0 * x + v1 * y + v2 * z
        p0, p1, p2 = p0 + d * x, p1 + d * y, p2 + d * z
        if k == 0:
            b0, b1, b2 = x, y, z
        else:
            c0, c1, c2 = x, y, z
        k += 1
    return p0, p1, p2


DECLARATION = Declaration(
    "environment",
    reads=("env_force", "device_pos"),
    writes=("env_rendered",),
    fields=("env_rendered",),
    flag="surfaces",
    helpers=("environment_step", "_span_project"),
)
