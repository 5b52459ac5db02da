"""The built-in procedures, through the Procedure interface (hapticd.experiment.procedure):
constant stimuli (planned ahead: hapticd.experiment.plan), the staircases and QUEST+ (their
tracks: hapticd.experiment.adaptive). They register in the same table as a lab's own."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from hapticd.experiment.adaptive import QuestTrack, Track, is_correct
from hapticd.experiment.procedure import Procedure
from hapticd.experiment.spec import QuestPlusDesign, Staircase
from hapticd.psychophysics import Z75

if TYPE_CHECKING:
    from hapticd.experiment.spec import Experiment


class ConstantStimuli(Procedure):
    """The method of constant stimuli: every ratio of ``varied.ratios``, ``repetitions``
    times, in a planned order (``make_plan``); analysed by the psychometric fit alone.
    Its settings are the ratios."""

    name = "constant_stimuli"
    plans_ahead = True

    @classmethod
    def section(cls, exp: Experiment) -> Any:
        return tuple(exp.varied.ratios)

    @classmethod
    def from_design(cls, design: Mapping[str, Any]) -> Procedure:
        return cls(tuple(design.get("ratios") or ()))

    def design(self) -> dict[str, Any]:
        return {}

    @property
    def max_trials(self) -> int:
        raise TypeError("constant stimuli plans its blocks: Experiment.trials_per_block")

    def ratio_range(self) -> tuple[float, float]:
        return (min(self.settings), max(self.settings)) if self.settings else (1.0, 1.0)

    def _planned(self, *_: Any) -> Any:
        raise TypeError("constant stimuli plans every trial ahead (hapticd.experiment.plan)")

    new_track = comparison = update = done = estimate = _planned  # type: ignore[assignment]


class StaircaseProcedure(Procedure):
    """The interleaved staircases of the file's ``staircase`` section (adaptive.Track)."""

    name = "staircase"
    Settings = Staircase
    result_key = "staircases"

    section_key = "staircase"

    @property
    def sides(self) -> tuple[int, ...]:
        return self.settings.sign_list()

    @property
    def max_trials(self) -> int:
        return self.settings.max_trials

    def ratio_range(self) -> tuple[float, float]:
        st = self.settings
        low = 1 - st.max_distance if st.sides == "both" else min(1.0, 1 + st.min_distance)
        return (low, 1 + st.max_distance)

    def describe(self, exp: Experiment) -> str:
        st = self.settings
        n_up, n_down = st.moves
        rule = f"updown ({n_up} up, {n_down} down)" if st.rule == "updown" else st.rule
        extra = [f"{st.step_type} steps"] if st.step_type != "lin" else []
        if st.initial_rule:
            extra.append("one up, one down until the first reversal")
        if st.min_distance < 0:
            extra.append(f"crossing the standard by up to {-st.min_distance:g}")
        end = (
            f"{st.stop_reversals} reversals and {st.min_trials} trials, {st.max_trials} at most"
            if st.stop == "both"
            else f"{st.stop_reversals} reversals or {st.max_trials} trials"
        )
        return (
            f"staircase {rule} (converges on {st.target_share:.1%} correct"
            + "".join(f"; {e}" for e in extra)
            + f"), {exp.n_blocks} tracks interleaved ({len(st.sign_list())} per condition and "
            f"standard), each ending after {end}: at most "
            f"{exp.n_blocks * st.max_trials} per subject"
        )

    def new_track(self, index: int, condition: str, standard: float, sign: int) -> Track:
        return Track.new(index, condition, standard, sign, self.settings)

    def comparison(self, track: Track) -> float:
        return track.comparison()

    def update(self, track: Track, more: bool, comparison: float) -> None:
        track.answer(is_correct(track, more), self.settings)

    def done(self, track: Track) -> bool:
        return track.done(self.settings)

    def estimate(self, track: Track) -> dict[str, Any]:
        d = track.threshold(self.settings)
        return {"threshold_distance": d, "jnd": None if d is None else d * track.standard}

    def analyze(
        self,
        trials: list[dict[str, Any]],
        *,
        conditions: list[str] | None = None,
        jnd_point: float = 0.75,
    ) -> dict[str, Any]:
        from hapticd.experiment.analyze import analyze_staircases

        return analyze_staircases(trials, self.settings.model_dump(), conditions)

    def report(self, result: dict[str, Any], unit: str) -> str:
        from hapticd.experiment.analyze import format_staircases

        return format_staircases(result, unit)


class QuestPlusProcedure(Procedure):
    """QUEST+ per condition and standard, the file's ``quest_plus`` section (QuestTrack)."""

    name = "quest_plus"
    Settings = QuestPlusDesign
    result_key = "quest_plus"

    section_key = "quest_plus"

    @property
    def max_trials(self) -> int:
        return self.settings.trials

    def ratio_range(self) -> tuple[float, float]:
        return (self.settings.min_ratio, self.settings.max_ratio)

    def describe(self, exp: Experiment) -> str:
        q = self.settings
        return (
            f"QUEST+, {exp.n_blocks} tracks interleaved (one per condition and standard), "
            f"{q.trials} trials each on {q.n_stimuli} comparisons from {q.min_ratio:g} to "
            f"{q.max_ratio:g} x the standard: {exp.n_blocks * q.trials} per subject"
        )

    def new_track(self, index: int, condition: str, standard: float, sign: int) -> QuestTrack:
        return QuestTrack(index, condition, standard, self.settings)

    def comparison(self, track: QuestTrack) -> float:
        return track.comparison()

    def update(self, track: QuestTrack, more: bool, comparison: float) -> None:
        track.answer(more, self.settings, comparison)

    def done(self, track: QuestTrack) -> bool:
        return track.done(self.settings)

    def estimate(self, track: QuestTrack) -> dict[str, Any]:
        est = track.estimate()
        return {**est, "jnd": Z75 * est["sigma"]}

    def analyze(
        self,
        trials: list[dict[str, Any]],
        *,
        conditions: list[str] | None = None,
        jnd_point: float = 0.75,
    ) -> dict[str, Any]:
        from hapticd.experiment.analyze import analyze_quest

        return analyze_quest(trials, self.settings.model_dump(), jnd_point, conditions)

    def report(self, result: dict[str, Any], unit: str) -> str:
        from hapticd.experiment.analyze import format_quest

        return format_quest(result, unit)
