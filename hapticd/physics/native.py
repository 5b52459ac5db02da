"""An allocator plugin compiled with numba and called from the compiled tick.

The tick is compiled once and cached; a plugin is known only when a profile names it. So
the plugin is compiled on its own (``compile_plugin``: its function inside a wrapper of
numba's calling convention, which returns a status instead of raising) and the tick calls
the wrapper's machine code through its address (``call_native``), an item of the
allocation's params. A plugin that raises returns a status the tick sees; nothing of it is
printed or allocated on the servo thread but what the plugin itself allocates.

Imported only where numba is: hapticd.physics.jit registers ``plugin_call_compiled`` as the
compiled form of hapticd.allocation.kernels' ``plugin_call``, and hapticd.allocation.plugins
finds ``compile_plugin`` through the entry point group ``hapticd.plugin_compilers``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from hapticd.allocation import kernels

_P = types.CPointer(types.float64)
# The wrapper's signature: G, M_a, lam and lam_a's memory, then 3p and r.
WRAPPER_SIGNATURE = types.int64(_P, _P, _P, _P, types.int64, types.int64)


@dataclass(frozen=True)
class Native:
    """A plugin compiled: its wrapper's ``address`` (what the tick calls) and the objects
    that own the machine code (kept as long as the plugin is registered)."""

    address: int
    keep: tuple[Any, ...]


def compile_plugin(fn: Callable[..., Any]) -> Native:
    """``fn(G, M_a, lam) -> lam_a`` compiled into a wrapper the tick calls by address. Raises
    numba's error when ``fn`` is not Python numba compiles (the caller says so)."""
    jitted = fn if isinstance(fn, numba.core.registry.CPUDispatcher) else numba.njit(fn)
    ok, wrong_shape = kernels.PLUGIN_OK, kernels.PLUGIN_SHAPE

    def wrapper(g, m, lam_p, out_p, n, r):
        G = numba.carray(g, (6, n))
        M = numba.carray(m, (n, r))
        lam = numba.carray(lam_p, (n,))
        out = numba.carray(out_p, (r,))
        lam_a = np.asarray(jitted(G, M, lam), dtype=np.float64)
        if lam_a.ndim != 1 or lam_a.shape[0] != r:
            return wrong_shape
        for i in range(r):
            out[i] = lam_a[i]
        return ok

    compiled = numba.njit(WRAPPER_SIGNATURE, nogil=True)(wrapper)
    result = compiled.overloads[WRAPPER_SIGNATURE.args]
    address = result.library.get_pointer_to_function(result.fndesc.llvm_func_name)
    if not address:
        raise RuntimeError("numba gave the compiled wrapper no address")
    return Native(int(address), (compiled, result, jitted))


@intrinsic
def call_native(typingctx, address, work, start, n, r):
    """The wrapper at ``address`` on the scratch of ``work`` (a C-contiguous float64 2-D
    array) from flat item ``start``: G (6, n), M_a (n, r), lam (n,) then lam_a (r,), in that
    order; its status, or PLUGIN_RAISED when the plugin raised."""
    sig = types.int64(types.int64, work, types.int64, types.int64, types.int64)
    raised = kernels.PLUGIN_RAISED

    def codegen(context, builder, signature, args):
        addr, arr, at, nn, rr = args
        data = context.make_array(signature.args[1])(context, builder, arr).data
        g = builder.gep(data, [at])
        m = builder.gep(g, [builder.mul(nn, ir.Constant(nn.type, 6))])
        lam = builder.gep(m, [builder.mul(nn, rr)])
        out = builder.gep(lam, [nn])
        argtys = WRAPPER_SIGNATURE.args
        fnty = context.call_conv.get_function_type(types.int64, argtys)
        fn = builder.inttoptr(addr, fnty.as_pointer())
        status, res = context.call_conv.call_function(
            builder, fn, types.int64, argtys, (g, m, lam, out, nn, rr)
        )
        return builder.select(status.is_error, ir.Constant(res.type, raised), res)

    return sig, codegen


def plugin_call_compiled(
    work: np.ndarray, n: int, r: int, handle: float, address: float, scratch: int, xo: int
) -> int:
    """``plugin_call`` in compiled code: the grasp general's rows of ``work`` hold copied
    into the scratch from row ``scratch`` on, the plugin at ``address`` called on it, lam_a
    copied into row ``xo``."""
    cols = work.shape[1]
    if work.strides[0] != 8 * cols or work.strides[1] != 8 or address == 0.0:
        return kernels.PLUGIN_UNAVAILABLE
    start = scratch * cols
    k = start
    for i in range(6):
        for t in range(n):
            work[k // cols, k % cols] = work[i, t]
            k += 1
    for t in range(n):
        for j in range(r):
            work[k // cols, k % cols] = work[6 + t, j]
            k += 1
    for t in range(n):
        work[k // cols, k % cols] = work[6 + n, t]
        k += 1
    status = call_native(int(address), work, start, n, r)
    if status == kernels.PLUGIN_OK:
        for j in range(r):
            work[xo, j] = work[(k + j) // cols, (k + j) % cols]
    return status
