import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hapticd.safety import SafetyChain

wild = st.one_of(
    st.floats(-1e6, 1e6),
    st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 1e-300, 1e300]),
)


@given(st.lists(arrays(float, (2, 3), elements=wild), min_size=1, max_size=40))
def test_output_is_always_finite_within_limits_and_latches(stream):
    limits = [3.0, 5.0]
    chain = SafetyChain(limits)
    latched_at = None
    for k, forces in enumerate(stream):
        out = chain.apply(forces, k, k * 1e-3)
        assert np.all(np.isfinite(out))
        for i, lim in enumerate(limits):
            assert math.hypot(*out[i]) <= lim * (1 + 1e-12)
        if latched_at is None and not np.all(np.isfinite(forces)):
            latched_at = k
        if latched_at is not None:
            assert chain.latched and chain.fault.tick == latched_at
            assert np.all(out == 0.0)
        elif np.all(np.isfinite(forces)):
            for i, lim in enumerate(limits):
                f = forces[i]
                n = math.hypot(*f)
                if n <= lim:
                    np.testing.assert_array_equal(out[i], f)
                else:  # clamped: direction kept
                    np.testing.assert_allclose(out[i], f * (lim / n), rtol=1e-12)


def test_fault_cause_and_reset():
    chain = SafetyChain([1.0])
    chain.apply(np.array([[np.nan, 0, 0]]), 7, 0.007)
    assert chain.fault.tick == 7 and "non-finite" in chain.fault.cause
    assert np.all(chain.apply(np.array([[0.5, 0, 0]]), 8, 0.008) == 0)
    chain.reset()
    np.testing.assert_array_equal(chain.apply(np.array([[0.5, 0, 0]]), 9, 0.009), [[0.5, 0, 0]])


def test_bad_limits_rejected():
    with pytest.raises(ValueError):
        SafetyChain([1.0, 0.0])
    with pytest.raises(ValueError):
        SafetyChain([np.inf])
