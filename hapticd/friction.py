"""Coulomb friction at a fingertip as a stick/slip proxy (after CHAI3D's finger proxy).

The frictionless proxy p0 lies on a face with unit normal n, at depth
d = n . (p0 - device) >= 0. A sticking contact keeps an anchor point on the
face; the friction proxy stays at the anchor while it lies within mu_s d of
p0 (the static cone) and otherwise slips to the dynamic cone's edge, mu_d d
from p0 toward the anchor. The force k (proxy - device) then has normal part
k d and tangential part at most mu k d. Units: m. Pure: floats in, floats out.
"""

from __future__ import annotations

import math

Vec = tuple[float, float, float]


def friction_proxy(
    p0: Vec, device: Vec, normal: Vec, anchor: Vec | None, mu_s: float, mu_d: float
) -> tuple[Vec, bool]:
    """(friction proxy, sticking) for the frictionless proxy ``p0`` and the previous ``anchor``.

    The anchor is first projected onto the face plane through p0. With no
    anchor (a new contact) the contact sticks at p0.
    """
    if anchor is None:
        return p0, True
    n = normal
    depth = (p0[0] - device[0]) * n[0] + (p0[1] - device[1]) * n[1] + (p0[2] - device[2]) * n[2]
    if depth <= 0.0:
        return p0, True
    off = (anchor[0] - p0[0], anchor[1] - p0[1], anchor[2] - p0[2])
    s = off[0] * n[0] + off[1] * n[1] + off[2] * n[2]
    t = (off[0] - s * n[0], off[1] - s * n[1], off[2] - s * n[2])
    tn = math.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
    if tn <= mu_s * depth:
        return (p0[0] + t[0], p0[1] + t[1], p0[2] + t[2]), True
    k = mu_d * depth / tn
    return (p0[0] + k * t[0], p0[1] + k * t[1], p0[2] + k * t[2]), False
