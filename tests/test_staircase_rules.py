"""The staircase's rules against PsychoPy's StairHandler (tests/stairhandler_port.py):
given the same answers, every track presents the same levels, reverses at the same
trials and levels, and ends at the same trial, for every step type, up-down rule,
initial rule and stopping rule StairHandler has."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as hs

from hapticd.experiment import adaptive as ad
from hapticd.experiment.spec import Staircase, updown_target
from tests.stairhandler_port import StairHandlerPort

RULES = {"1up2down": (1, 2), "1up3down": (1, 3)}


def step_sizes(st: Staircase) -> list[float]:
    """The staircase's steps as StairHandler's stepSizes: one further at each reversal."""
    steps = [st.step]
    while st.step_rule == "halve" and steps[-1] > (st.min_step or 0.0):
        steps.append(max(steps[-1] / 2, st.min_step or 0.0))
    return steps


def port_of(st: Staircase) -> StairHandlerPort:
    n_up, n_down = st.moves
    return StairHandlerPort(
        st.start,
        n_reversals=st.stop_reversals,
        step_sizes=step_sizes(st),
        n_trials=st.min_trials,
        n_up=n_up,
        n_down=n_down,
        initial_rule=st.initial_rule,
        step_type=st.step_type,
        min_val=st.min_distance,
        max_val=st.max_distance,
    )


def run_both(st: Staircase, answers: list[bool]) -> tuple[ad.Track, StairHandlerPort]:
    """Both staircases through ``answers`` (until either ends), compared at every trial."""
    track, port = ad.Track.new(0, "c", 60.0, 1, st), port_of(st)
    for k, correct in enumerate(answers):
        assert track.done(st) == port.finished, (k, track, port.__dict__)
        if port.finished:
            break
        assert track.distance == port.next_level(), k
        track.answer(correct, st)
        port.respond(int(correct))
        assert track.reversals == port.reversal_levels, k
        assert track.reversal_trials == [t + 1 for t in port.reversal_trials], k
    return track, port


@hs.composite
def stairhandler_settings(draw) -> Staircase:
    """A staircase every option of which StairHandler has: stop both (nReversals and
    nTrials), lin / db / log steps, fixed or halving to a floor (a list of step sizes),
    a rule of n_up and n_down, the initial rule, minVal and maxVal."""
    step_type = draw(hs.sampled_from(["lin", "db", "log"]))
    max_distance = draw(hs.floats(0.2, 0.9))
    start = draw(hs.floats(0.05, 1.0)) * max_distance
    step = {
        "lin": draw(hs.floats(0.005, 0.2)) * max_distance,
        "db": draw(hs.floats(0.5, 6.0)),
        "log": draw(hs.floats(0.02, 0.3)),
    }[step_type]
    halve = draw(hs.booleans())
    min_step = step * draw(hs.floats(0.05, 1.0)) if halve else None
    min_distance = 0.0
    if step_type == "lin" and draw(hs.booleans()):
        min_distance = -draw(hs.floats(0.0, 1.0)) * max_distance
    rule = draw(hs.sampled_from(["1up2down", "1up3down", "updown"]))
    moves = {}
    if rule == "updown":
        n_up = draw(hs.integers(1, 3))
        moves = {"n_up": n_up, "n_down": draw(hs.integers(n_up + 1, 5))}
    base = Staircase(
        rule=rule, start=start, step=step, max_distance=max_distance, **moves,
        step_type=step_type, step_rule="halve" if halve else "fixed", min_step=min_step,
        min_distance=min_distance, stop="both", stop_reversals=2, max_trials=1000,
        threshold_reversals=1, initial_rule=draw(hs.booleans()),
    )  # fmt: skip
    # StairHandler raises nReversals to its number of step sizes; ask for that many.
    reversals = max(draw(hs.integers(2, 12)), len(step_sizes(base)))
    return base.model_copy(
        update={
            "stop_reversals": reversals,
            "min_trials": draw(hs.integers(0, 60)),
            "threshold_reversals": draw(hs.integers(1, reversals)),
        }
    )


@given(st=stairhandler_settings(), answers=hs.lists(hs.booleans(), min_size=1, max_size=150))
def test_the_same_answers_give_stairhandlers_levels_reversals_and_end(st, answers):
    track, port = run_both(st, answers)
    k = st.threshold_reversals
    if len(port.reversal_levels) >= k:
        mean = sum(port.reversal_levels[-k:]) / k
        assert track.threshold(st) == pytest.approx(mean, rel=1e-12)
    else:
        assert track.threshold(st) is None


def test_a_long_run_of_mostly_correct_answers_matches_stairhandler_to_its_end():
    """An observer near its 80 % point: many reversals, the halving to its floor, the end
    on both reversals and trials, for each step type."""
    answers = [(7 * k) % 10 < 8 for k in range(400)]
    for step_type, step, min_step in (("lin", 0.08, 0.01), ("db", 4.0, 1.0), ("log", 0.2, 0.05)):
        st = Staircase(
            rule="1up3down", start=0.4, step=step, step_type=step_type, step_rule="halve",
            min_step=min_step, max_distance=0.6, initial_rule=True, stop="both",
            stop_reversals=12, min_trials=80, max_trials=1000, threshold_reversals=8,
        )  # fmt: skip
        track, port = run_both(st, answers)
        assert port.finished and track.done(st)
        assert track.n == len(port.levels) >= 80 and len(track.reversals) >= 12
        assert track.step == min_step  # the floor reached


def test_the_initial_rule_moves_after_every_answer_until_the_first_reversal():
    st = Staircase(
        rule="1up3down", start=0.4, step=0.1, step_rule="halve", min_step=0.025,
        max_distance=0.6, initial_rule=True, stop_reversals=4, threshold_reversals=2,
    )  # fmt: skip
    t = ad.Track.new(0, "if", 60.0, 1, st)
    for correct in (True, True):
        t.answer(correct, st)
    assert t.distance == pytest.approx(0.2)  # one down a correct answer, not three
    t.answer(False, st)  # the first reversal: the step halves, and it still moves at once
    assert t.reversals == [pytest.approx(0.2)] and t.step == pytest.approx(0.05)
    assert t.distance == pytest.approx(0.25)
    for _ in range(2):
        t.answer(True, st)
    assert t.distance == pytest.approx(0.25)  # now three correct answers in a row
    t.answer(True, st)  # the second reversal: down by the step halved again
    assert len(t.reversals) == 2 and t.distance == pytest.approx(0.225)


def test_db_and_log_steps_multiply_the_distance_and_never_reach_the_standard():
    for step_type, factor in (("db", 10 ** (6 / 20)), ("log", 10**0.3)):
        st = Staircase(
            rule="1up2down", start=0.4, step=6.0 if step_type == "db" else 0.3,
            step_type=step_type, step_rule="fixed", max_distance=0.6, max_trials=200,
        )  # fmt: skip
        t = ad.Track.new(0, "if", 60.0, 1, st)
        t.answer(True, st)
        t.answer(True, st)
        assert t.distance == pytest.approx(0.4 / factor)
        t.answer(False, st)
        assert t.distance == pytest.approx(0.4)
        t.answer(False, st)
        assert t.distance == pytest.approx(0.6)  # clipped at max_distance
        for _ in range(100):
            t.answer(True, st)
        assert 0 < t.distance < 1e-6


def test_stop_both_needs_the_reversals_and_the_trials_and_max_trials_ends_it_anyway():
    base = dict(rule="1up2down", start=0.4, step=0.1, step_rule="fixed", max_distance=0.6)
    both = Staircase(**base, stop="both", stop_reversals=2, min_trials=10, max_trials=30,
                     threshold_reversals=2)  # fmt: skip
    either = Staircase(**base, stop_reversals=2, max_trials=30, threshold_reversals=2)
    a, b = ad.Track.new(0, "c", 1.0, 1, both), ad.Track.new(0, "c", 1.0, 1, either)
    for correct in (True, True, False, True, True):
        a.answer(correct, both)
        b.answer(correct, either)
    assert len(a.reversals) == len(b.reversals) == 2
    assert b.done(either) and not a.done(both)  # 5 trials of the 10
    for _ in range(5):
        a.answer(True, both)
    assert a.done(both) and a.n == 10
    c = ad.Track.new(0, "c", 1.0, 1, both)
    for _ in range(30):
        c.answer(True, both)  # never reverses: the cap ends it
    assert c.done(both) and not c.reversals


@pytest.mark.parametrize(
    ("n_up", "n_down", "share"),
    [(1, 2, 2**-0.5), (1, 3, 2 ** (-1 / 3)), (1, 4, 2**-0.25), (2, 3, None), (2, 5, None)],
)
def test_the_updown_rule_converges_where_down_and_up_are_equally_likely(n_up, n_down, share):
    p = updown_target(n_up, n_down)
    if share is not None:
        assert p == pytest.approx(share, abs=1e-12)
    # n_down correct in a row before n_up wrong in a row, half the time: the chain of
    # runs solved exactly by its absorbing probabilities, by value iteration.
    q = 1 - p
    down = [0.0] * (n_down + n_up + 1)  # states: +k correct, -k wrong in a row
    for _ in range(2000):
        new = down.copy()
        for k in range(n_down):  # k correct in a row (k = 0: fresh)
            nxt_c = 1.0 if k + 1 >= n_down else down[k + 1]
            nxt_w = 0.0 if n_up == 1 else down[n_down + 1]
            new[k] = p * nxt_c + q * nxt_w
        for j in range(1, n_up):  # j wrong in a row
            nxt_w = 0.0 if j + 1 >= n_up else down[n_down + j + 1]
            new[n_down + j] = p * (1.0 if n_down == 1 else down[1]) + q * nxt_w
        down = new
    assert down[0] == pytest.approx(0.5, abs=1e-9)
    st = Staircase(rule="updown", n_up=n_up, n_down=n_down, start=0.4, step=0.1,
                   max_distance=0.6)  # fmt: skip
    assert st.target_share == pytest.approx(p) and st.moves == (n_up, n_down)


@pytest.mark.parametrize(
    ("changes", "what"),
    [
        ({"rule": "updown", "n_up": 2, "n_down": 2}, "more than 50 %"),
        ({"rule": "updown"}, "n_down"),
        ({"n_down": 3}, "updown rule's"),
        ({"rule": "weighted", "target": 0.75, "initial_rule": True}, "changes nothing"),
        ({"min_trials": 5}, "stop: both"),
        ({"stop": "both", "min_trials": 90}, "exceeds max_trials"),
        ({"step_type": "db", "step": 3.0, "min_distance": -0.1}, "step_type lin"),
        ({"min_distance": -0.7}, "at most max_distance"),
        ({"min_distance": 0.5}, "farther than it"),
    ],
)
def test_settings_stairhandler_cannot_run_as_meant_are_refused(changes, what):
    base = dict(rule="1up2down", start=0.4, step=0.1, max_distance=0.6, max_trials=60)
    with pytest.raises(ValueError, match=what):
        Staircase(**{**base, **changes})
