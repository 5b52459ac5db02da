"""Adaptive procedures: interleaved staircases whose next comparison depends on the
answers so far (docs/experiments.md, "Staircases").

A **track** is one condition, one standard and one side (above the standard: correct
is "the comparison judged more"; below: "judged less"). Its state (the comparison's
distance from the standard as a fraction of the standard, the step, the correct
answers in a row, the reversals) is a pure function of its answers, so a resumed run
rebuilds it from the stored trials (``replay``) and goes on exactly where it stopped.
Which track presents trial k, and whether its comparison comes first, is drawn from a
generator seeded by the subject's seed and k alone: the same seed gives the same
session, whoever answers, in any process, after any resume.

The built-in procedures (hapticd.experiment.procedures) wrap these tracks in the
Procedure interface; the functions below go through it.

Pure: no I/O (the walker that stores each trial is ``run_adaptive_subject``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hapticd.experiment.plan import PlannedTrial
from hapticd.experiment.spec import Experiment, ExperimentError, QuestPlusDesign, Staircase


@dataclass
class Track:
    """One staircase's state; ``distance`` and ``step`` are fractions of the standard
    (``step_type`` lin; db and log steps are in decibels and log10 units)."""

    index: int
    condition: str
    standard: float
    sign: int  # +1: comparisons above the standard; -1: below
    distance: float
    step: float
    # Same answers in a row since the last move: +k correct, -k wrong (StairHandler's
    # correctCounter).
    run: int = 0
    last_move: int = 0  # +1 up (easier), -1 down (harder), 0 none yet
    n: int = 0  # trials answered
    reversals: list[float] = field(default_factory=list)  # distances where it turned
    reversal_trials: list[int] = field(default_factory=list)  # at which trial (1-based)
    levels: list[float] = field(default_factory=list)  # each trial's distance
    correct: list[bool] = field(default_factory=list)

    @classmethod
    def new(cls, index: int, condition: str, standard: float, sign: int, st: Staircase) -> Track:
        """A track of ``st`` at its start."""
        return cls(index, condition, standard, sign, st.start, st.step)

    @property
    def side(self) -> str:
        return "above" if self.sign > 0 else "below"

    @property
    def name(self) -> str:
        return f"{self.condition}/{self.standard:g}/{self.side}"

    def comparison(self) -> float:
        """The next comparison value (the varied parameter's unit)."""
        # 60 x 1.05 is 63.00000000000001 in binary; the design meant 63.
        return float(f"{self.standard * (1 + self.sign * self.distance):.12g}")

    def done(self, st: Staircase) -> bool:
        turned = len(self.reversals) >= st.stop_reversals
        if st.stop == "both":
            return (turned and self.n >= st.min_trials) or self.n >= st.max_trials
        return turned or self.n >= st.max_trials

    def answer(self, correct: bool, st: Staircase) -> None:
        """Move after one answer, as PsychoPy's StairHandler does: down (harder) after
        ``n_down`` correct answers in a row, up (easier) after ``n_up`` wrong ones (one
        and one before the first reversal with ``initial_rule``; the weighted rule: one
        and one, up ``target / (1 - target)`` steps); a change of direction is a
        reversal, where the step halves (``step_rule: halve``, down to min_step)."""
        self.levels.append(self.distance)
        self.correct.append(correct)
        self.n += 1
        if correct:
            self.run = self.run + 1 if self.run > 0 else 1
        else:
            self.run = self.run - 1 if self.run < 0 else -1
        n_up, n_down = (1, 1) if st.initial_rule and not self.reversals else st.moves
        move = -1 if self.run >= n_down else 1 if self.run <= -n_up else 0
        if move == 0:
            return
        self.run = 0
        if self.last_move and move != self.last_move:
            self.reversals.append(self.distance)
            self.reversal_trials.append(self.n)
            if st.step_rule == "halve":
                self.step = max(self.step / 2, st.min_step or 0.0)
        self.last_move = move
        size = self.step * (st.up_factor if move > 0 else 1.0)
        # The operations StairHandler does, so the same answers give the same levels.
        if st.step_type == "lin":
            d = self.distance + size if move > 0 else self.distance - size
        else:
            factor = 10.0 ** (size / 20.0 if st.step_type == "db" else size)
            d = self.distance * factor if move > 0 else self.distance / factor
        self.distance = float(min(max(d, st.min_distance), st.max_distance))

    def threshold(self, st: Staircase) -> float | None:
        """The mean distance of the last ``threshold_reversals`` reversals (fraction of
        the standard), None with fewer."""
        k = st.threshold_reversals
        return float(np.mean(self.reversals[-k:])) if len(self.reversals) >= k else None


class QuestTrack:
    """One QUEST+ track (the ``questplus`` package): the posterior over the PSE and
    sigma (as fractions of the standard) of P(comparison judged more) = l/2 + (1 - l)
    Phi((ratio - mean) / sd), and the next comparison, the grid ratio of least expected
    entropy. Its "correct" is "the comparison judged more" (``sign`` +1)."""

    sign = 1

    def __init__(self, index: int, condition: str, standard: float, q: QuestPlusDesign) -> None:
        try:
            import questplus  # an optional dependency: imported when a file uses QUEST+
        except ImportError:
            raise ExperimentError(
                "procedure quest_plus needs the questplus package: pip install 'hapticd[questplus]'"
            ) from None

        self.index, self.condition, self.standard = index, condition, standard
        self.n = 0
        self.levels: list[float] = []
        self.correct: list[bool] = []
        half = (q.max_ratio - q.min_ratio) / 2
        self._qp = questplus.QuestPlus(
            stim_domain={"intensity": np.linspace(q.min_ratio, q.max_ratio, q.n_stimuli)},
            param_domain={
                "mean": np.linspace(1 - half / 2, 1 + half / 2, 31),
                "sd": np.geomspace(0.01, 2 * half, 25),
                "lower_asymptote": [q.lapse / 2],
                "lapse_rate": [q.lapse / 2],
            },
            outcome_domain={"response": ["Yes", "No"]},
            func="norm_cdf",
            stim_scale="linear",
        )

    @property
    def side(self) -> str:
        return "both"

    @property
    def name(self) -> str:
        return f"{self.condition}/{self.standard:g}"

    def comparison(self) -> float:
        """The next comparison value: the grid ratio of least expected entropy."""
        ratio = float(self._qp.next_stim["intensity"])
        return float(f"{self.standard * ratio:.12g}")

    def done(self, q: QuestPlusDesign) -> bool:
        return self.n >= q.trials

    def answer(self, more: bool, q: QuestPlusDesign, comparison: float) -> None:
        """The answer to ``comparison``: ``more`` the comparison judged more."""
        grid = self._qp.stim_domain["intensity"]
        # The grid's own value, so the update finds it in the stimulus domain.
        ratio = float(grid[int(np.argmin(np.abs(grid - comparison / self.standard)))])
        self._qp.update(stim={"intensity": ratio}, outcome={"response": "Yes" if more else "No"})
        self.levels.append(ratio - 1)
        self.correct.append(bool(more))
        self.n += 1

    def estimate(self) -> dict[str, float]:
        """The posterior mean PSE and sigma, in the varied parameter's unit."""
        est = self._qp.param_estimate
        return {
            "pse": float(est["mean"]) * self.standard,
            "sigma": float(est["sd"]) * self.standard,
        }


AnyTrack = Track | QuestTrack


def tracks_for(exp: Experiment) -> list[Any]:
    """Every track of ``exp`` at its start, in order: conditions as listed, standards
    ascending, above before below (a track's index is its ``block`` in the store)."""
    return _procedure(exp).tracks(exp)


def _procedure(exp: Experiment) -> Any:
    from hapticd.experiment import procedure

    proc = procedure.of(exp)
    if proc.plans_ahead:
        raise ValueError(f"experiment {exp.name!r} has no adaptive procedure")
    return proc


def is_correct(track: AnyTrack, comparison_more: bool) -> bool:
    """Whether an answer is correct for ``track``: the comparison judged more above the
    standard, less below it."""
    return bool(comparison_more) == (track.sign > 0)


def replay(exp: Experiment, trials: Iterable[Mapping[str, Any]]) -> list[Any]:
    """The tracks after the complete and failed ``trials`` (store rows with
    ``plan_index``, ``block`` (the track), ``status`` and ``comparison_more``), in plan
    order (``skip``: a failed trial). Procedure.replay."""
    return _procedure(exp).replay(exp, trials)


def skip(track: AnyTrack) -> None:
    """A trial of ``track`` whose exploration failed: it counts towards the track's
    trials (its stopping rule, so a track that always fails ends) and moves nothing."""
    track.n += 1


def apply_answer(track: AnyTrack, more: bool, section: Any, comparison: float) -> None:
    """Move ``track`` after an answer to ``comparison`` (``more``: judged more)."""
    if isinstance(track, QuestTrack):
        track.answer(more, section, comparison)
    else:
        track.answer(is_correct(track, more), section)


def next_trial(exp: Experiment, seed: int, index: int, tracks: list[Any]) -> PlannedTrial | None:
    """Trial ``index`` of the session: a track drawn among those not done (uniformly, by
    a generator seeded by ``seed`` and ``index``), its current comparison; None when
    every track is done. Procedure.next_trial."""
    return _procedure(exp).next_trial(exp, seed, index, tracks)


def session(
    exp: Experiment,
    seed: int,
    answer: Callable[[PlannedTrial], bool | None],
    done: Iterable[Mapping[str, Any]] = (),
) -> list[tuple[PlannedTrial, bool | None]]:
    """The rest of a session after the complete and failed trials ``done``: each next
    trial and ``answer(trial)`` (True: the comparison judged more; None: its exploration
    failed, ``skip``), until every track is done. For simulated observers (no store).
    Procedure.session."""
    return _procedure(exp).session(exp, seed, answer, done)


def tracks_from_rows(rows: Iterable[Mapping[str, Any]], st: Staircase) -> dict[tuple, Track]:
    """Every track in the store rows ``rows`` (complete trials of any subjects), replayed:
    {(subject, block): Track}. A track's condition and standard are its trials', its side
    that of its first comparison (``start`` from the standard, never on it), so the
    store's rows suffice, whatever reduced design the run used."""
    by: dict[tuple, list[Mapping[str, Any]]] = {}
    for r in rows:
        if r.get("status", "complete") == "complete" and r.get("block") is not None:
            by.setdefault((r["subject"], int(r["block"])), []).append(r)
    out = {}
    for (subject, block), rs in sorted(by.items()):
        rs = sorted(rs, key=lambda r: r["plan_index"])
        first = rs[0]
        sign = 1 if first["comparison"] > first["standard"] else -1
        track = Track.new(block, first["condition"], float(first["standard"]), sign, st)
        for r in rs:
            track.answer(is_correct(track, bool(r["comparison_more"])), st)
        out[(subject, block)] = track
    return out
