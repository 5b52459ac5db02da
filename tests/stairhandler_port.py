"""A reference for the staircase tests: the level-choosing logic of PsychoPy's
``psychopy.data.StairHandler`` (psychopy/data/staircase.py), re-written from reading it,
without its data handling, logging and saving. PsychoPy itself is not in this project's
lock; this keeps its rules, step for step, so that hapticd's tracks can be checked
against them given the same answers.

What it keeps: the run counter (same answers in a row since the last move, signed), the
optional one-up-one-down rule until the first reversal, the reversal bookkeeping (the
level of the answered trial, and its 0-based trial number), the list of step sizes taken
one further at each reversal (the last kept), the db / log / lin moves with their
operations in StairHandler's order, minVal and maxVal, and the end once both nReversals
reversals and nTrials trials are reached (nReversals raised to the number of step sizes).
"""

from __future__ import annotations


class StairHandlerPort:
    """One PsychoPy staircase: ``next_level()`` the next trial's level, ``respond(1|0)``
    after its answer (1: correct)."""

    def __init__(
        self,
        start: float,
        *,
        n_reversals: int,
        step_sizes: list[float],
        n_trials: int,
        n_up: int,
        n_down: int,
        initial_rule: bool,
        step_type: str,
        min_val: float | None,
        max_val: float | None,
    ) -> None:
        self.steps = list(step_sizes)
        self.step = self.steps[0]
        # StairHandler asks for at least as many reversals as there are step sizes.
        self.n_reversals = max(n_reversals, len(self.steps))
        self.n_trials, self.n_up, self.n_down = n_trials, n_up, n_down
        self.initial, self.step_type = initial_rule, step_type
        self.min_val, self.max_val = min_val, max_val
        self.level = start
        self.trial = -1  # the current trial's 0-based number
        self.answers: list[int] = []
        self.levels: list[float] = []
        self.reversal_levels: list[float] = []
        self.reversal_trials: list[int] = []
        self.direction = "start"
        self.counter = 0
        self.first_reversal_just_made = False
        self.finished = False

    def next_level(self) -> float:
        if self.finished:
            raise StopIteration
        self.trial += 1
        self.levels.append(self.level)
        return self.level

    def respond(self, result: int) -> None:
        same = len(self.answers) > 0 and self.answers[-1] == result
        self.answers.append(result)
        if result == 1:
            self.counter = self.counter + 1 if same else 1
        else:
            self.counter = self.counter - 1 if same else -1
        self._next()

    def _next(self) -> None:
        initial_phase = self.initial and not self.reversal_levels
        if initial_phase:
            going = "down" if self.answers[-1] == 1 else "up"
            reversal = self.direction == ("up" if going == "down" else "down")
            self.direction = going
        elif self.counter >= self.n_down:
            reversal = self.direction not in ("start", "down")
            self.direction = "down"
        elif self.counter <= -self.n_up:
            reversal = self.direction not in ("start", "up")
            self.direction = "up"
        else:
            reversal = False
        if reversal:
            self.reversal_trials.append(self.trial)
            if self.initial and not self.reversal_levels:
                self.first_reversal_just_made = True
            self.reversal_levels.append(self.levels[-1])
        if len(self.reversal_levels) >= self.n_reversals and len(self.levels) >= self.n_trials:
            self.finished = True
        if reversal and len(self.steps) > 1:
            self.step = self.steps[min(len(self.reversal_levels), len(self.steps) - 1)]
        if self.initial and (not self.reversal_levels or self.first_reversal_just_made):
            self.first_reversal_just_made = False
            self._down() if self.answers[-1] == 1 else self._up()
        elif self.counter >= self.n_down:
            self._down()
        elif self.counter <= -self.n_up:
            self._up()

    def _up(self) -> None:
        if self.step_type == "db":
            self.level *= 10.0 ** (self.step / 20.0)
        elif self.step_type == "log":
            self.level *= 10.0**self.step
        else:
            self.level += self.step
        if self.max_val is not None and self.level > self.max_val:
            self.level = self.max_val
        self.counter = 0

    def _down(self) -> None:
        if self.step_type == "db":
            self.level /= 10.0 ** (self.step / 20.0)
        elif self.step_type == "log":
            self.level /= 10.0**self.step
        else:
            self.level -= self.step
        self.counter = 0
        if self.min_val is not None and self.level < self.min_val:
            self.level = self.min_val
