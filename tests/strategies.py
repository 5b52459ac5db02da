"""Hypothesis strategies shared by the tests: generated cases that are valid by construction."""

import numpy as np
from hypothesis import strategies as st


@st.composite
def unit_vectors(draw) -> np.ndarray:
    """A unit vector (3,), uniform on the sphere: never degenerate, so no example is
    thrown away for a direction too short to normalise."""
    z = draw(st.floats(-1.0, 1.0))
    phi = draw(st.floats(0.0, 2 * np.pi))
    r = np.sqrt(max(0.0, 1.0 - z * z))
    return np.array([r * np.cos(phi), r * np.sin(phi), z])


@st.composite
def point_pairs(draw, extent: float, min_gap: float, max_gap: float) -> np.ndarray:
    """Two points (2, 3) m: the first in the cube [-extent, extent]^3, the second
    ``min_gap`` to ``max_gap`` m from it in any direction."""
    first = np.array([draw(st.floats(-extent, extent)) for _ in range(3)])
    gap = draw(st.floats(min_gap, max_gap))
    return np.stack([first, first + gap * draw(unit_vectors())])
