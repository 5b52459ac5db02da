"""The tests' way to step a god-object proxy: contact's one source
(hapticd.kernels.contact_step), compiled or not, on obstacles given as plane lists.

An obstacle is (unit normals (m, 3), offsets (m,)), the half-space n . x <= d, already
inflated by the fingertip's radius (the kernel's radius is 0). Obstacle 0 is the object;
the others are surfaces (the kernel's env_force is theirs)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from hapticd import jit, kernels

Obstacle = tuple[Sequence[Sequence[float]], Sequence[float]]


def compiled() -> Callable[..., int]:
    """contact_step compiled (loaded from the run's cache; numba is a dependency)."""
    return jit.compile_kernels(["contact_step"])["contact_step"]


def uncompiled() -> Callable[..., int]:
    """contact_step as plain Python (what ``rendering.kernels=python`` runs)."""
    return kernels.uncompiled("contact_step")


KERNELS = {"compiled": compiled, "uncompiled": uncompiled}


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


def planes_of(obstacles: Sequence[Obstacle]) -> np.ndarray:
    """The kernel's planes (P, kernels.PLANE_COLUMNS) of ``obstacles`` (surfaces' stiffness
    1 N/m, no damping)."""
    rows, lo = [], 0
    for j, (normals, offsets) in enumerate(obstacles):
        n = np.asarray(normals, dtype=float).reshape(-1, 3)
        block = np.zeros((len(n), kernels.PLANE_COLUMNS))
        block[:, 0:3] = n
        block[:, 3] = offsets
        block[:, 4:7] = (j, lo, lo + len(n))
        block[:, 7] = 0.0 if j == 0 else 1.0
        rows.append(block)
        lo += len(n)
    return np.ascontiguousarray(np.vstack(rows))


class Proxy:
    """One fingertip's proxy against ``obstacles`` by ``kernel`` (default: compiled)."""

    def __init__(self, obstacles: Sequence[Obstacle], kernel: Callable[..., int] | None = None):
        self.kernel = compiled() if kernel is None else kernel
        self.planes = planes_of(obstacles)
        self.state = np.zeros((1, kernels.CONTACT_STATE))
        self.device = np.zeros((1, 3))
        self.touch = np.zeros(1, dtype=np.uint8)
        self.normal = np.zeros((1, 3))
        # contact_step's arguments: the device (position, velocity), the planes, the state,
        # then the frame's fields it writes (proxy, in_contact, surface point, contact
        # point, normal, env_force).
        self.args = (
            self.device, np.zeros((1, 3)), self.planes, self.state, np.zeros((1, 3)),
            self.touch, np.zeros((1, 3)), np.zeros((1, 3)), self.normal, np.zeros((1, 3)),
        )  # fmt: skip

    def step(self, proxy_prev: Sequence[float], device: Sequence[float]) -> Step:
        """The proxy moved from ``proxy_prev`` toward ``device`` (m)."""
        st = self.state
        st[0, :3] = proxy_prev
        self.device[0] = device
        assert self.kernel(*self.args) == kernels.CONTACT_DONE
        row = st[0].tolist()
        a = kernels._C_ACTIVE
        rows = [int(q) for q in row[a : a + 3] if q >= 0]
        mu = row[kernels._C_MU : kernels._C_MU + len(rows)]
        pl = self.planes
        active = [(int(pl[q, 4]), q - int(pl[q, 5])) for q in rows]
        return Step(st[0, :3].copy(), active, mu, bool(self.touch[0]), self.normal[0].copy())

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
    from hapticd.scene import ConvexShape, Material, SceneObject

    shape = ConvexShape.box(np.asarray(size, dtype=float))
    poly = SceneObject(shape, Material(1.0), np.asarray(center, dtype=float), rotation).polytope
    return poly.normals, poly.offsets + inflate
