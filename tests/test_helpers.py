"""The test suite's own helpers: a wait that fails at its deadline, and says why."""

import pytest

from tests.conftest import wait_for


def test_wait_for_returns_the_value_that_satisfied_it():
    values = iter([1, 2, 3])
    assert wait_for(lambda: next(values), "3", until=lambda v: v == 3, poll_s=0) == 3


def test_wait_for_fails_at_its_deadline_naming_what_and_the_last_value():
    with pytest.raises(pytest.fail.Exception, match=r"waiting for the answer; last seen: 41$"):
        wait_for(lambda: 41, "the answer", until=lambda v: v == 42, timeout_s=0.05, poll_s=0.01)


TIMED = """
import pytest

@pytest.mark.timing("the test measures a rate")
def test_with_a_reason():
    pass

@pytest.mark.timing
def test_without_one():
    pass

@pytest.mark.timing("")
def test_with_an_empty_one():
    pass
"""


def test_a_timing_mark_without_a_reason_fails_collection(pytester):
    pytester.makeconftest("from tests.conftest import pytest_collection_modifyitems  # noqa")
    pytester.makepyfile(test_timed=TIMED)
    result = pytester.runpytest_inprocess("-p", "no:cacheprovider")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*mark.timing needs one reason string*"])
    err = result.stderr.str()
    assert "test_without_one" in err and "test_with_an_empty_one" in err
    assert "test_with_a_reason" not in err


def test_not_timing_deselects_the_timing_tests(pytester):
    pytester.makeconftest("from tests.conftest import pytest_collection_modifyitems  # noqa")
    pytester.makeini("[pytest]\nmarkers =\n    timing(reason): wall clock\n")
    pytester.makepyfile(
        test_timed="""
import pytest

@pytest.mark.timing("measures a rate")
def test_timed():
    pass

def test_plain():
    pass
"""
    )
    result = pytester.runpytest_inprocess("-p", "no:cacheprovider", "-m", "not timing")
    result.assert_outcomes(passed=1, deselected=1)
