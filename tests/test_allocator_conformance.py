"""The allocators' conformance suite (hapticd.allocation.conformance, ``hapticd allocators
check``): every built-in passes what it claims; allocators broken in each way the suite
looks for fail it, each naming its case."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hapticd.allocation import METHODS, allocate
from hapticd.allocation import conformance as cf
from hapticd.cli import main


def failed(f, claims: cf.Claims | None = None) -> dict[str, str]:
    return {o.case: o.detail for o in cf.check(f, claims or cf.Claims()) if not o.passed}


@pytest.mark.parametrize("name", METHODS)
def test_every_built_in_passes_what_it_claims(name):
    f, claims = cf.allocator(name)
    outcomes = cf.check(f, claims)
    assert [o.case for o in outcomes] == [*cf.SINGULAR, *cf.CASES_ALWAYS], outcomes
    assert all(o.passed for o in outcomes), [o for o in outcomes if not o.passed]
    skipped = [o.case for o in outcomes if o.detail.startswith("skipped")]
    assert skipped == ([] if claims.robust else list(cf.SINGULAR))


def _pinv(G, M, lam):
    return allocate("pinv", G, M, lam)


def test_a_formula_that_blows_up_at_a_rank_change_fails_there():
    # The seed's pinv formula, claimed robust: huge actuator forces as M_a loses rank.
    got = failed(lambda G, M, lam: allocate("pinv_exact", G, M, lam))
    assert list(got) == ["M_a loses rank"], got
    assert "of contact force (over 10000x)" in got["M_a loses rank"]


def test_a_jump_at_a_rank_change_fails_as_a_jump():
    # Twice the force once the second contact has passed through the first.
    def jumpy(G, M, lam):
        out = _pinv(G, M, lam)
        return 2.0 * out if G[5, 3] > 0 else out

    got = failed(jumpy)
    assert "coincident contacts" in got and got["coincident contacts"].startswith("jumps by")


def test_non_linear_and_non_finite_allocators_fail_those_cases():
    got = failed(lambda G, M, lam: np.tanh(_pinv(G, M, lam)))
    assert set(got) == {"forces from 1e-9 to 1e3 N", "linear in lam"}, got
    assert (
        set(failed(lambda G, M, lam: np.tanh(_pinv(G, M, lam)), cf.Claims(linear=False))) == set()
    )
    # (NaN input it still refuses: allocate raises before the multiplication.)
    got = failed(lambda G, M, lam: _pinv(G, M, lam) * np.nan)
    assert set(got) == {*cf.SINGULAR, "forces from 1e-9 to 1e3 N", "linear in lam"}, got
    assert all("non-finite" in why for why in got.values()), got


def test_nan_input_must_be_refused_or_stay_finite():
    def passes_nan(G, M, lam):
        if np.all(np.isfinite(G)) and np.all(np.isfinite(lam)):
            return _pinv(G, M, lam)
        return lam[: M.shape[1]]  # NaN passed on to the device

    assert list(failed(passes_nan)) == ["NaN and inf input"]


def test_an_allocator_that_raises_or_misshapes_fails_naming_the_case():
    def raises(G, M, lam):
        raise RuntimeError("boom")

    got = failed(raises)
    assert all(
        "RuntimeError: boom" in why for case, why in got.items() if case != "NaN and inf input"
    )
    got = failed(lambda G, M, lam: _pinv(G, M, lam)[:-1])
    assert "returned shape" in got["forces from 1e-9 to 1e3 N"]


def test_the_command_lists_and_checks_naming_what_fails(capsys):
    assert main(["allocators", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["name"] for r in rows] == list(METHODS)
    assert {r["package"] for r in rows} == {"hapticd"}
    assert main(["allocators", "check", "pinv_exact"]) == 0
    out = capsys.readouterr().out
    assert "skipped: not claimed robust" in out and "FAIL" not in out
    assert main(["allocators", "check", "none-such"]) == 2
    assert "'none-such'" in capsys.readouterr().err
