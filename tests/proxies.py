"""The tests' way to step a god-object proxy: contact's one source (hapticd.physics.kernels.
contact_step) in the tick's one call, compiled or not, on obstacles given as plane lists.

An obstacle is (unit normals (m, 3), offsets (m,)), the half-space n . x <= d, already
inflated by the fingertip's radius (the fingertip's radius is 0). Obstacle 0 is the object
(a fixed object of those planes at the origin: its planes in the world are the same,
every bit); each other is one plane, a surface (the call's env_force is theirs)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hapticd.physics import kernels
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject, Surface
from tests import ticks

Obstacle = tuple[Sequence[Sequence[float]], Sequence[float]]

MODES = ticks.MODES


@dataclass
class Step:
    """One proxy update: the proxy (3,) m, its active (obstacle, plane) pairs and their
    multipliers mu (m; proxy - device = sum mu n), whether it touches obstacle 0 and the
    unit contact normal there (zeros when it does not)."""

    proxy: np.ndarray
    active: list[tuple[int, int]]
    mu: list[float]
    in_contact: bool
    normal: np.ndarray

    @property
    def n_active(self) -> int:
        return len(self.active)


def scene_of(obstacles: Sequence[Obstacle]) -> Scene:
    """Obstacle 0 as a fixed object at the origin, each other as a surface (stiffness 1 N/m,
    no damping)."""
    normals, offsets = obstacles[0]
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    shape = ConvexShape(n, np.asarray(offsets, dtype=float), np.zeros((1, 3)), 1.0, np.eye(3))
    obj = SceneObject(shape, Material(1.0), np.zeros(3), np.eye(3))
    surfaces = []
    for j, (normals, offsets) in enumerate(obstacles[1:], start=1):
        if len(offsets) != 1:
            raise ValueError(f"obstacle {j}: a surface is one plane, not {len(offsets)}")
        normal = tuple(float(x) for x in np.ravel(normals))
        surfaces.append(Surface(f"obstacle {j}", normal, float(offsets[0]), Material(1.0)))
    return Scene(obj, surfaces, None)


class Proxy:
    """One fingertip's proxy against ``obstacles`` by the one call, compiled (``mode``) or
    not ("uncompiled")."""

    def __init__(self, obstacles: Sequence[Obstacle], mode: str = "compiled"):
        self.renderer = ticks.renderer(scene_of(obstacles), [0.0], mode)
        contact = ticks.stage(self.renderer, "contact")
        contact.start(self.renderer.frame)  # the proxy is ours to set, tick by tick
        self.state = contact.state
        self.n_object = len(obstacles[0][1])
        self.still = np.zeros((1, 3))

    def step(self, proxy_prev: Sequence[float], device: Sequence[float]) -> Step:
        """The proxy moved from ``proxy_prev`` toward ``device`` (m)."""
        st = self.state
        st[0, :3] = proxy_prev
        frame = self.renderer.step(np.asarray(device, dtype=float).reshape(1, 3), self.still)
        row = st[0].tolist()
        a = kernels._C_ACTIVE
        rows = [int(q) for q in row[a : a + 3] if q >= 0]
        mu = row[kernels._C_MU : kernels._C_MU + len(rows)]
        m = self.n_object
        active = [(0, q) if q < m else (q - m + 1, 0) for q in rows]
        return Step(
            st[0, :3].copy(), active, mu, bool(frame.in_contact[0]), frame.contact_normal[0].copy()
        )

    def walk(self, start: Sequence[float], devices: Sequence[Sequence[float]]) -> list[Step]:
        """Steps along ``devices`` from a proxy at ``start``."""
        p, out = start, []
        for x in devices:
            res = self.step(p, x)
            p = res.proxy
            out.append(res)
        return out


def box(center, rotation, size, inflate: float = 0.0) -> Obstacle:
    """A box's planes (+x, +y, +z, -x, -y, -z faces of its axes, the columns of ``rotation``)
    with edge lengths ``size`` (3,) m at ``center``, grown by ``inflate`` (m)."""
    shape = ConvexShape.box(np.asarray(size, dtype=float))
    poly = SceneObject(shape, Material(1.0), np.asarray(center, dtype=float), rotation).polytope
    return poly.normals, poly.offsets + inflate
