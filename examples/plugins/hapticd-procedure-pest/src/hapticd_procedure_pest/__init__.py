"""PEST (Taylor & Creelman 1967) as a hapticd procedure: one module, one entry point.

A track tests one comparison, ``distance`` from the standard (a fraction of it), until a
Wald sequential test decides: after T trials there with C correct, it moves harder
(closer) when C > target T + wald, easier (farther) when C < target T - wald, and stays
otherwise. Each move starts a new test. PEST's step rules:

1. at a reversal (a move against the last one) the step halves;
2. the second move in one direction keeps the step;
3. the third doubles it, unless the move just before the last reversal was a doubling;
4. the fourth and later double it (at most ``max_step``).

A track ends when its step falls below ``min_step`` (the test has converged) or after
``max_trials``; its threshold is the distance it would test next, so the JND is that
distance times the standard (SI). Pure: no I/O, a pure function of the answers (so a
resumed run rebuilds it from the stored trials).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from hapticd.experiment.procedure import Procedure, Track


class PestSettings(BaseModel):
    """The experiment file's ``settings`` for ``procedure: pest``; distances and steps
    are fractions of the standard."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    target: float = Field(0.75, gt=0.5, lt=1.0, description="the share correct tracked")
    start: float = Field(gt=0, description="first distance from the standard")
    step: float = Field(gt=0, description="first step")
    min_step: float = Field(gt=0, description="a track ends when its step falls below this")
    max_step: float | None = Field(None, gt=0, description="the largest step (default: 4 x step)")
    max_distance: float = Field(gt=0, description="the farthest comparison from the standard")
    wald: float = Field(1.0, gt=0, le=5, description="the Wald test's deviation limit, trials")
    max_trials: int = Field(60, ge=2, le=1000, description="a track ends after these trials")
    sides: Literal["both", "above"] = "above"

    @model_validator(mode="after")
    def _consistent(self) -> PestSettings:
        if self.start > self.max_distance:
            raise ValueError(f"start {self.start:g} is beyond max_distance {self.max_distance:g}")
        if self.min_step > self.step:
            raise ValueError(f"min_step {self.min_step:g} is larger than step {self.step:g}")
        if self.sides == "both" and self.max_distance >= 1:
            raise ValueError("sides both: max_distance must be below 1 (a comparison above 0)")
        return self


@dataclass
class PestTrack(Track):
    """One PEST track: its distance and step (fractions of the standard), the current
    test's trials and correct answers, and the moves so far."""

    distance: float = 0.0
    step: float = 0.0
    at_level: int = 0  # trials of the current test
    right: int = 0  # correct answers of the current test
    last_move: int = 0  # +1 easier (farther), -1 harder (closer), 0 none yet
    run: int = 0  # moves in a row in last_move's direction
    doubled: bool = False  # whether the last move doubled the step
    doubled_before_reversal: bool = False
    reversals: list[float] = field(default_factory=list)


class Pest(Procedure):
    """PEST's tracks, one per condition, standard and side."""

    name = "pest"
    Settings = PestSettings

    @property
    def sides(self) -> tuple[int, ...]:
        return (1, -1) if self.settings.sides == "both" else (1,)

    @property
    def max_trials(self) -> int:
        return self.settings.max_trials

    def ratio_range(self) -> tuple[float, float]:
        d = self.settings.max_distance
        return (1 - d if self.settings.sides == "both" else 1.0, 1 + d)

    def new_track(self, index: int, condition: str, standard: float, sign: int) -> PestTrack:
        s = self.settings
        return PestTrack(index, condition, standard, sign, distance=s.start, step=s.step)

    def comparison(self, track: PestTrack) -> float:
        return track.standard * (1 + track.sign * track.distance)

    def done(self, track: PestTrack) -> bool:
        return track.step < self.settings.min_step or track.n >= self.settings.max_trials

    def update(self, track: PestTrack, more: bool, comparison: float) -> None:
        s = self.settings
        correct = bool(more) == (track.sign > 0)
        track.levels.append(track.distance)
        track.correct.append(correct)
        track.n += 1
        track.at_level += 1
        track.right += correct
        expected = s.target * track.at_level
        if track.right > expected + s.wald:
            move = -1  # better than the target here: harder
        elif track.right < expected - s.wald:
            move = 1  # worse: easier
        else:
            return
        track.at_level = track.right = 0
        if track.last_move and move != track.last_move:  # rule 1: a reversal halves
            track.reversals.append(track.distance)
            track.doubled_before_reversal = track.doubled
            track.step /= 2
            track.run, track.doubled = 1, False
        else:
            track.run += 1
            double = track.run >= 4 or (track.run == 3 and not track.doubled_before_reversal)
            if double:  # rules 3 and 4
                track.step = min(2 * track.step, s.max_step or 4 * s.step)
            track.doubled = double
        track.last_move = move
        track.distance = min(max(track.distance + move * track.step, 0.0), s.max_distance)

    def estimate(self, track: PestTrack) -> dict[str, Any]:
        return {
            "distance": track.distance,
            "reversals": float(len(track.reversals)),
            "jnd": track.distance * track.standard if track.n else None,
        }
