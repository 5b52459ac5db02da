"""The test suite's own helpers: a wait that fails at its deadline, and says why."""

import pytest

from tests.conftest import wait_for


def test_wait_for_returns_the_value_that_satisfied_it():
    values = iter([1, 2, 3])
    assert wait_for(lambda: next(values), "3", until=lambda v: v == 3, poll_s=0) == 3


def test_wait_for_fails_at_its_deadline_naming_what_and_the_last_value():
    with pytest.raises(pytest.fail.Exception, match=r"waiting for the answer; last seen: 41$"):
        wait_for(lambda: 41, "the answer", until=lambda v: v == 42, timeout_s=0.05, poll_s=0.01)
