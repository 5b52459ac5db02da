"""One tick's allocation for F fingertips on the frame's arrays: which contacts, which
definition, contact onset. A robust method runs the kernel allocation_step, an exact one
``hapticd.allocation.allocate``; docs/allocation.md says where each is defined.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import numpy as np

from hapticd.allocation import allocate, kernels, plugins
from hapticd.allocation.accuracy import accuracy
from hapticd.allocation.actuation import Actuation
from hapticd.allocation.adaptive import AdaptiveState
from hapticd.allocation.grasp import grasp_matrix
from hapticd.allocation.robust import AllocationError, Robustness

V3 = tuple[float, float, float]
T = TypeVar("T")


class _Input(Generic[T]):
    """An allocator's attribute whose setting remakes the kernel's inputs."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.attr = "_" + name

    def __get__(self, obj: Any, owner: type | None = None) -> T:
        return self if obj is None else getattr(obj, self.attr)  # type: ignore[return-value]

    def __set__(self, obj: ContactAllocator, value: T) -> None:
        setattr(obj, self.attr, value)
        obj._refresh()


class ContactAllocator:
    """Allocates contact forces onto ``actuation``'s directions with ``method``, ticks of
    ``dt`` s apart. Carries the adaptive allocator's alpha (``state``); ``kernel`` is
    allocation_step, compiled or (set to None) not, ``work`` its workspace.
    """

    actuation: _Input[Actuation] = _Input()  # the actuated directions
    method: _Input[str] = _Input()  # a name in hapticd.allocation.METHODS
    robust: _Input[Robustness] = _Input()  # the robust allocators' parameters

    def __init__(
        self,
        actuation: Actuation,
        method: str,
        robust: Robustness,
        adaptive: AdaptiveState,
        dt: float,
        kernel: Callable[..., int] | None = None,
    ) -> None:
        self.dt = dt
        self.state = np.zeros(kernels.ALLOCATION_STATE)  # alpha
        self.accuracy = np.zeros(kernels.ACCURACY)  # the last tick's (N, N, N, 1)
        self.work = np.zeros((0, 0))  # the kernel's workspace
        self._params = np.zeros(kernels.ALLOCATION_PARAMS)
        self._local = np.zeros((0, 3))  # the kernel's directions (D, 3), in their frame
        self._counts = np.zeros(actuation.n_fingers)  # and how many each finger has
        self._actuation, self._method, self._robust = actuation, method, robust
        self._compiled = False  # whether ``kernel`` is compiled (an allocator plugin's form)
        self.native_problem: str | None = None  # why a plugin runs as Python, compiled kernels
        self.adaptive = adaptive  # sets alpha, and the kernel's inputs for all four
        self.kernel = kernel

    @property
    def adaptive(self) -> AdaptiveState:
        """The adaptive allocator's parameters; setting it starts alpha at its alpha."""
        return self._adaptive

    @adaptive.setter
    def adaptive(self, value: AdaptiveState) -> None:
        self._adaptive = value
        self.state[0] = value.alpha
        self._refresh()

    @property
    def alpha(self) -> float:
        """The adaptive allocator's external weight (0..1) after the last tick."""
        return float(self.state[0])

    @alpha.setter
    def alpha(self, value: float) -> None:
        self.state[0] = value

    @property
    def kernel(self) -> Callable[..., int]:
        """allocation_step, compiled or not."""
        return self._kernel

    @kernel.setter
    def kernel(self, fn: Callable[..., int] | None) -> None:
        self._kernel = kernels.uncompiled("allocation_step") if fn is None else fn
        if self._compiled != (fn is not None):
            self._compiled = fn is not None
            self._refresh()  # an allocator plugin's compiled form, or its Python one

    def allocate(
        self,
        in_contact: np.ndarray,
        device_pos: np.ndarray,
        points: np.ndarray,
        forces: np.ndarray,
        center: np.ndarray,
        lam_a: np.ndarray,
        rendered: np.ndarray,
    ) -> np.ndarray:
        """Write lam_a (r,) N and ``rendered`` (F, 3) N, M_a lam_a per finger (zero out of
        contact); return the accuracy (internal, external, total N, amplification).

        ``in_contact`` (F,) u1, ``device_pos`` (F, 3) m (the grasp frame follows fingers 0
        and 1), ``points`` (F, 3) m, ``forces`` (F, 3) N, ``center`` (3,) m the grasp's
        reference point; C-contiguous float64, the kernel's types. Moves ``alpha`` (a
        refused tick leaves it). AllocationError for a non-finite input or result.
        """
        params = self._params
        params[5:8] = center
        if self._takes or self._plugin is not None:
            # A plugin without its compiled form runs in the kernel's Python form.
            kernel = self._kernel if self._takes else kernels.uncompiled("allocation_step")
            outcome = kernel(
                in_contact, device_pos, points, forces, self._local, self._counts, params,
                self.state,
                lam_a, rendered, self.accuracy, self.work,
            )  # fmt: skip
            if outcome == kernels.ALLOCATED:
                return self.accuracy
            raise self.refusal(bad_input=outcome == kernels.NON_FINITE_INPUT)
        with np.errstate(over="ignore"):  # finite forces whose residuals overflow: inf
            self._exact(in_contact, device_pos, points, forces, center, lam_a, rendered)
        return self.accuracy

    def replay(
        self,
        in_contact: np.ndarray,
        device_pos: np.ndarray,
        points: np.ndarray,
        forces: np.ndarray,
        centers: np.ndarray,
    ) -> np.ndarray:
        """lam_a (N, r) N over N recorded ticks, allocated tick by tick as the loop does
        (alpha from its value now). ``in_contact`` (N, F); ``device_pos``, ``points`` (m)
        and ``forces`` (N) (N, F, 3); ``centers`` (N, 3) m, the object's position before
        each tick's dynamics moved it."""
        touching = np.ascontiguousarray(in_contact, dtype=np.uint8)
        pos, pts, lam, ctr = (
            np.ascontiguousarray(a, dtype=float) for a in (device_pos, points, forces, centers)
        )
        out = np.zeros((len(touching), self.actuation.n_actuators))
        rendered = np.zeros((self.actuation.n_fingers, 3))
        for k in range(len(touching)):
            self.allocate(touching[k], pos[k], pts[k], lam[k], ctr[k], out[k], rendered)
        return out

    def refusal(self, *, bad_input: bool, params: np.ndarray | None = None) -> AllocationError:
        """The error of a refused tick: a non-finite input (``bad_input``) or result (a
        plugin's: what it did, by its name, package and entry point). ``params``: the
        kernel's params of the refused tick (the one call's copy; default the allocator's)."""
        if bad_input:
            return AllocationError("non-finite contact geometry or force; refusing to allocate")
        plugin = self._plugin
        status = int((self._params if params is None else params)[kernels.PLUGIN_STATUS])
        if plugin is not None and status != kernels.PLUGIN_OK:
            what = _PLUGIN_FAILURES.get(status, f"failed (status {status})")
            return AllocationError(
                f"allocator plugin {plugin.name!r} (package {plugin.package!r}, entry point "
                f"{plugin.value}) {what}; refusing to allocate"
            )
        return AllocationError(f"allocator {self._method!r} produced a non-finite force")

    @property
    def in_kernel(self) -> bool:
        """Whether allocation_step allocates for the method (a robust one; not the seed's
        exact formulas)."""
        return self._takes

    def changed(
        self, *, method: str | None = None, actuation: Actuation | None = None
    ) -> ContactAllocator:
        """A copy with another ``method`` or ``actuation`` (as many directions), for a plan
        prepared beside the running one: it carries this one's state (alpha) and workspace,
        the same arrays; its kernel inputs are its own."""
        new = copy.copy(self)
        new._params = self._params.copy()
        new.accuracy = self.accuracy.copy()
        if method is not None:
            new._method = method
        if actuation is not None:
            new._actuation = actuation
        new._refresh()
        return new

    def kernel_inputs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """allocation_step's ``local`` (D, 3), ``counts`` (F,) and ``params`` as the allocator
        is now (params[5:8], the object's position, the caller's)."""
        return self._local, self._counts, self._params

    def _refresh(self) -> None:
        """Remake the kernel's inputs, and whether it takes the method (a robust one)."""
        act, rb, ad = self._actuation, self._robust, self._adaptive
        self._takes = self._method in _CODES
        params = self._params
        params[0] = _CODES.index(self._method) if self._method in _CODES else -1
        self._plugin = None if self._takes else plugins.get(self._method)
        params[kernels.PLUGIN_HANDLE : kernels.PLUGIN_STATUS + 1] = 0.0
        self.native_problem = None
        if self._plugin is not None:
            handle = plugins.handle(self._method)
            params[0], params[kernels.PLUGIN_HANDLE] = kernels.PLUGIN, handle
            if self._compiled:  # the tick calls its compiled form, else its Python one
                address, self.native_problem = plugins.native_address(handle)
                params[kernels.PLUGIN_ADDRESS] = address
            self._takes = not self._compiled or self.native_problem is None
        grasp = 1.0 if act.frame == "grasp" else 0.0
        params[1:5] = (rb.eps, rb.min_separation_m, rb.contact_onset_n, grasp)
        gain = 1.0 if ad.time_constant_s <= 0 else min(1.0, self.dt / ad.time_constant_s)
        params[8:11] = (ad.ratio_low, ad.ratio_high, gain)
        shape = kernels.allocation_work_shape(act.n_fingers, act.n_actuators)
        if self.work.shape != shape:
            self.work = np.zeros(shape)
        self._local = np.array([d for ds in act.local for d in ds], dtype=float).reshape(-1, 3)
        self._counts = np.array(act.counts, dtype=float)

    def _exact(self, *tick: np.ndarray) -> None:
        """``allocate`` by the seed's exact formulas."""
        in_contact, device_pos, points, forces, center, lam_a, rendered = tick
        contacts = np.flatnonzero(in_contact).tolist()
        lam_a.fill(0.0)
        rendered.fill(0.0)
        self.accuracy.fill(0.0)
        if not contacts:
            return
        world = self._actuation.world_directions(device_pos.tolist())
        x, G, M, cols, lam = self._solve(contacts, world, points, forces, center)
        norms = np.linalg.norm(forces[contacts], axis=1)  # allocation_step's contact onset
        beta = kernels.onset_beta(norms.min(), len(contacts), self._robust.contact_onset_n)
        if beta < 1.0:
            weakest = int(norms.argmin())
            rest = contacts[:weakest] + contacts[weakest + 1 :]
            x = beta * x + (1.0 - beta) * self._solve(rest, world, points, forces, center)[0]
        if not np.all(np.isfinite(x)):
            raise self.refusal(bad_input=False)
        lam_a[...] = x
        rendered[contacts] = (M @ x[cols]).reshape(-1, 3)
        a = accuracy(G, M, lam, x[cols])
        self.accuracy[:] = (a.internal, a.external, a.total, a.amplification)

    def _solve(
        self,
        contacts: list[int],
        world: list[list[V3]],
        points: np.ndarray,
        forces: np.ndarray,
        center: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int], np.ndarray]:
        """lam_a over all r actuators (zero for fingers not in ``contacts``), and the
        contacts' G (6, 3p), M_a (3p, c), the actuators of its c columns and lam (3p,) N."""
        M, cols = self._actuation.submatrix(world, contacts)
        pts, lam = points[contacts], forces[contacts].reshape(-1)
        if not all(np.all(np.isfinite(a)) for a in (pts, lam, center, M)):
            raise self.refusal(bad_input=True)
        G = grasp_matrix(pts, center)
        out = np.zeros(self._actuation.n_actuators)
        if cols:
            out[cols] = allocate(self._method, G, M, lam, robust=self._robust)
        return out, G, M, cols, lam


_CODES = kernels.ALLOCATION_METHODS
# What a plugin's status says it did (allocation_step's PLUGIN_*).
_PLUGIN_FAILURES = {
    kernels.PLUGIN_RAISED: "raised an exception",
    kernels.PLUGIN_SHAPE: "returned a result of the wrong shape (one force per actuated "
    "direction expected)",
    kernels.PLUGIN_NON_FINITE: "returned a NaN or infinite force",
    kernels.PLUGIN_ABSURD: (
        f"returned an absurd force (beyond {kernels.PLUGIN_GAIN:g} x |lam| + "
        f"{kernels.PLUGIN_SLACK_N:g} N)"
    ),
    kernels.PLUGIN_UNAVAILABLE: "has no compiled form in the compiled tick",
}
