"""Views of the tick's flat arrays: the frame's record, the plan and the carried state hold
every stage's arrays, and the one call cuts them out by offset (uncompiled as memoryviews,
compiled as numpy views)."""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import as_strided


def _rows(a: np.ndarray, start: int, n: int) -> np.ndarray:
    """Items ``start`` to ``start + 3 n`` of the flat ``a`` as an (n, 3) view (``_block``)."""
    return _block(a, start, n, 3)


def _block(a: np.ndarray, start: int, n: int, cols: int) -> np.ndarray:
    """Items ``start`` to ``start + n cols`` of the flat ``a`` as an (n, cols) view (a
    memoryview's, uncompiled; ``_block_compiled`` in compiled code)."""
    if n == 0:
        return np.zeros((0, cols))  # a memoryview has no empty shape
    return a[start : start + n * cols].cast("B").cast("d", (n, cols))  # type: ignore[attr-defined]


def _block_compiled(a: np.ndarray, start: int, n: int, cols: int) -> np.ndarray:
    # as_strided, not reshape: numba's reshape searches for strides at run time (about 40
    # ns a view, a third of a tick's unpacking); the range is checked here instead.
    if start < 0 or n < 0 or start + n * cols > a.shape[0]:
        raise IndexError("a block beyond its array")
    return as_strided(a[start:], shape=(n, cols), strides=(8 * cols, 8))


def _bytes(a: np.ndarray) -> np.ndarray:
    """The flat float64 ``a``'s memory as bytes (a memoryview's, uncompiled;
    ``_bytes_compiled`` in compiled code): the frame's one-byte fields."""
    return a.cast("B")  # type: ignore[attr-defined]


def _bytes_compiled(a: np.ndarray) -> np.ndarray:
    return a.view(np.uint8)


# Helpers whose compiled form is another function (hapticd.physics.jit compiles that one in).
COMPILED_FORMS = {_block: _block_compiled, _bytes: _bytes_compiled}
