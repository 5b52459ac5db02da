"""Experiment files: a JND design (method of constant stimuli) as YAML, validated like
profiles (unknown keys rejected; errors name the file and the key path). See
docs/experiments.md."""

from __future__ import annotations

import hashlib
import math
import zlib
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    create_model,
    field_validator,
    model_validator,
)

from hapticd import params
from hapticd.profile import Profile, ProfileError, load_profile, read_document, validate_document

EXPERIMENT_VERSION = 1
DOCS = "docs/experiments.md"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ExperimentError(ValueError):
    """An experiment file that cannot be used; the message names file, key path and
    expectation."""


def _param_check(name: str) -> Any:
    def check(value: Any) -> Any:
        try:
            return params.PARAMS[name].check(value)
        except params.ParamError as exc:
            raise ValueError(str(exc)) from None

    return check


# One optional key per settable parameter (hapticd.params), checked as the control
# protocol checks it: a condition sets what a running daemon could be told to set.
ParamSet = create_model(
    "ParamSet",
    __base__=_Strict,
    __doc__="Settable parameters (hapticd.params) and their values, SI units.",
    **{
        name: (Annotated[Any, AfterValidator(_param_check(name))] | None, None)
        for name in params.PARAMS
    },
)


class Condition(_Strict):
    """One rendering condition: a name and the parameters it sets."""

    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    set: ParamSet = Field(description="parameters (hapticd.params) this condition sets")

    def values(self) -> dict[str, Any]:
        return {k: v for k, v in self.set.model_dump().items() if v is not None}


class Varied(_Strict):
    """The parameter that differs between standard and comparison."""

    param: str = Field(description="a numeric settable parameter of hapticd.params")
    standards: tuple[float, ...] = Field(min_length=1, description="standard values, SI units")
    ratios: tuple[float, ...] = Field(
        default=(),
        description="comparison = ratio x standard; at least 3 ratios (constant stimuli only)",
    )

    @field_validator("param")
    @classmethod
    def _numeric(cls, v: str) -> str:
        spec = params.PARAMS.get(v)
        if spec is None:
            raise ValueError(params.unknown_message(v))
        if spec.kind != "number":
            raise ValueError(f"{v} is not a number; the varied parameter must be one")
        return v

    @field_validator("standards")
    @classmethod
    def _standards(cls, v: tuple[float, ...], info: ValidationInfo) -> tuple[float, ...]:
        spec = params.PARAMS.get(info.data.get("param", ""))
        for s in v:
            if spec is not None and not (math.isfinite(s) and spec.in_range(s)):
                raise ValueError(
                    f"standard {s:g} is outside {spec.name}'s range {spec.range_text()}"
                )
        if len(set(v)) != len(v):
            raise ValueError(f"standards must differ, got {list(v)}")
        return v

    @field_validator("ratios")
    @classmethod
    def _ratios(cls, v: tuple[float, ...], info: ValidationInfo) -> tuple[float, ...]:
        if 0 < len(v) < 3:
            raise ValueError(f"at least 3 ratios are needed, got {list(v)}")
        if any(not (math.isfinite(r) and r > 0) for r in v):
            raise ValueError(f"ratios must be positive, got {list(v)}")
        if len(set(v)) != len(v):
            raise ValueError(f"ratios must differ, got {list(v)}")
        spec = params.PARAMS.get(info.data.get("param", ""))
        for s in info.data.get("standards") or ():
            for r in v:
                if spec is not None and not (math.isfinite(s * r) and spec.in_range(s * r)):
                    raise ValueError(
                        f"comparison = standard {s:g} x ratio {r:g} = {s * r:g} is outside "
                        f"{spec.name}'s range {spec.range_text()}"
                    )
        return v


class Interval(_Strict):
    """The two intervals of a trial and the question asked after them."""

    order: Literal["standard_first", "randomized"] = Field(
        description="standard_first: the standard is always the first interval; randomized: "
        "each comparison comes first in half of its repetitions"
    )
    question: Literal["stiffer", "heavier", "more"] = Field(
        description="asked after the second interval: was the second stiffer / heavier / "
        "more (of the varied parameter)? 'yes' always means the second had more"
    )
    exploration_s: float = Field(gt=0, le=60, description="longest exploration per interval, s")
    ends_on: Literal["release", "time_limit"] = Field(
        description="release: the interval ends when the contacts end (or at exploration_s); "
        "time_limit: it lasts exploration_s"
    )
    gap_s: float = Field(
        default=1.0, ge=0, le=60, description="between the two intervals (the change), s"
    )
    answer_s: float = Field(
        default=2.0, gt=0, le=60, description="expected time to answer, s (duration estimate)"
    )


class Blocks(_Strict):
    """How trials are grouped: a block holds one condition and one standard."""

    per_standard: int = Field(
        default=1, ge=1, description="blocks per standard and condition; splits the repetitions"
    )
    standard_order: Literal["ascending", "listed", "random"] = "ascending"
    condition_order: Literal["listed", "random"] = "listed"
    nesting: Literal["condition_outer", "standard_outer"] = Field(
        default="condition_outer",
        description="condition_outer: every block of one condition, then the next condition",
    )
    within: Literal["cycles", "shuffle"] = Field(
        default="cycles",
        description="cycles: every comparison once per cycle, each cycle shuffled; "
        "shuffle: one random permutation of the block",
    )


class Breaks(_Strict):
    every_blocks: int = Field(default=1, ge=0, description="a break after every N blocks; 0: none")
    every_trials: int | None = Field(
        default=None, ge=1, description="also a break every N trials within a block"
    )
    duration_s: float = Field(default=60.0, ge=0, le=3600, description="break length, s")


class Randomization(_Strict):
    seed: int = Field(ge=0, lt=2**63, description="seed of the trial order")
    per_subject: bool = Field(
        default=True, description="derive each subject's seed from seed and the subject's id"
    )


# The answer rule of each staircase and the share of "correct" answers it converges on
# (Levitt 1971): two (three) correct in a row make it harder, one wrong easier; the
# weighted rule (Kaernbach 1991) moves up by step x target / (1 - target) after a wrong
# answer, down by step after a correct one, and converges on its target.
RULE_TARGETS = {"1up2down": 2**-0.5, "1up3down": 2 ** (-1 / 3)}


class Staircase(_Strict):
    """An adaptive staircase per condition, standard and side (docs/experiments.md):
    the comparison's distance from the standard, as a fraction of the standard, goes
    down after correct answers and up after wrong ones."""

    rule: Literal["1up2down", "1up3down", "weighted"] = Field(
        description="1up2down (converges on 70.7 % correct), 1up3down (79.4 %), weighted "
        "(on target)"
    )
    target: float | None = Field(
        default=None, gt=0.5, lt=1.0, description="the weighted rule's share correct"
    )
    sides: Literal["both", "above"] = Field(
        default="both",
        description="both: a track above the standard (correct: the comparison judged more) "
        "and one below (correct: judged less), interleaved; above: only the first",
    )
    start: float = Field(gt=0, description="first distance from the standard, fraction of it")
    step: float = Field(gt=0, description="first step, fraction of the standard")
    step_rule: Literal["fixed", "halve"] = Field(
        default="halve", description="halve: the step halves at each reversal, to min_step"
    )
    min_step: float | None = Field(default=None, gt=0, description="smallest step (halve)")
    max_distance: float = Field(
        gt=0, description="the farthest a comparison may be from the standard, fraction of it"
    )
    stop_reversals: int = Field(default=8, ge=2, le=100, description="a track ends after these")
    max_trials: int = Field(default=60, ge=2, le=1000, description="or after these trials")
    threshold_reversals: int = Field(
        default=6, ge=1, description="the threshold: mean of the last N reversals' distances"
    )

    @model_validator(mode="after")
    def _converges(self) -> Staircase:
        if self.step > self.max_distance:
            raise ValueError(
                f"step {self.step:g} is larger than the range max_distance "
                f"{self.max_distance:g}: the staircase cannot converge"
            )
        if self.start > self.max_distance:
            raise ValueError(f"start {self.start:g} is beyond max_distance {self.max_distance:g}")
        if self.min_step is not None and self.min_step > self.step:
            raise ValueError(f"min_step {self.min_step:g} is larger than step {self.step:g}")
        if (self.rule == "weighted") != (self.target is not None):
            raise ValueError("target is needed by the weighted rule, and only by it")
        if self.threshold_reversals > self.stop_reversals:
            raise ValueError(
                f"threshold_reversals ({self.threshold_reversals}) exceeds stop_reversals "
                f"({self.stop_reversals}): a stopped track would not have them"
            )
        if self.sides == "both" and self.max_distance >= 1:
            raise ValueError(
                f"max_distance {self.max_distance:g}: a track below the standard needs it "
                "below 1 (a comparison above 0)"
            )
        return self

    @property
    def target_share(self) -> float:
        """The share of correct answers the track converges on."""
        return self.target if self.target is not None else RULE_TARGETS[self.rule]

    def sign_list(self) -> tuple[int, ...]:
        """The sides' signs: +1 above the standard, -1 below."""
        return (1, -1) if self.sides == "both" else (1,)


class QuestPlusDesign(_Strict):
    """QUEST+ (Watson 2017; the ``questplus`` package) per condition and standard: the
    comparison (a ratio of the standard, on a grid) that minimises the expected entropy
    of the posterior over the psychometric function's PSE and sigma, for a fixed number
    of trials."""

    min_ratio: float = Field(gt=0, lt=1, description="the smallest comparison / standard")
    max_ratio: float = Field(gt=1, description="the largest comparison / standard")
    n_stimuli: int = Field(default=41, ge=5, le=201, description="comparisons on the grid")
    trials: int = Field(default=40, ge=5, le=1000, description="trials per track")
    lapse: float = Field(default=0.02, ge=0, lt=0.5, description="assumed lapse rate")

    @property
    def max_trials(self) -> int:
        return self.trials

    def sign_list(self) -> tuple[int, ...]:
        """One track per condition and standard (both sides on one grid)."""
        return (1,)


class Analysis(_Strict):
    """How the answers are analysed."""

    jnd_point: Literal[0.75, 0.84] = Field(
        default=0.75,
        description="the JND is x(p) - x(0.5) of the fitted curve: 0.75 (0.6745 sigma) or "
        "0.84 (0.9945 sigma, about one sigma); every table and plot names it",
    )


class Experiment(_Strict):
    """A complete experiment file (docs/experiments.md)."""

    version: Literal[1] = 1
    # It names the recordings (EXPERIMENT-SUBJECT-TRIAL-INTERVAL.hrec): a file name.
    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    description: str = ""
    procedure: Literal["constant_stimuli", "staircase", "quest_plus"] = Field(
        default="constant_stimuli",
        description="how comparisons are chosen: constant_stimuli (every ratio, repetitions "
        "times, in a planned order), staircase (each next comparison from the answers so "
        "far, the tracks interleaved) or quest_plus (QUEST+, interleaved)",
    )
    profile: str = Field(min_length=1, description="base profile, relative to this file")
    varied: Varied
    conditions: tuple[Condition, ...] = Field(min_length=1)
    repetitions: int | None = Field(
        default=None, ge=1, le=1000, description="presentations of each comparison"
    )
    staircase: Staircase | None = None
    quest_plus: QuestPlusDesign | None = None
    interval: Interval
    blocks: Blocks = Blocks()
    breaks: Breaks = Breaks()
    randomization: Randomization
    analysis: Analysis = Analysis()

    source: Path | None = Field(default=None, exclude=True)
    file_hash: str = Field(default="", exclude=True, description="sha256 of the file's bytes")

    @field_validator("version", mode="before")
    @classmethod
    def _version(cls, v: Any) -> Any:
        # YAML's `true` equals 1 in Python; it is no version.
        if isinstance(v, bool) or v != 1:
            raise ValueError(
                f"expected 1 (the experiment file format this hapticd reads), got {v!r}"
            )
        return v

    @model_validator(mode="after")
    def _consistent(self) -> Experiment:
        names = [c.name for c in self.conditions]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"condition names must be unique, repeated: {dup}")
        for c in self.conditions:
            if self.varied.param in c.values():
                raise ValueError(
                    f"condition {c.name!r} sets {self.varied.param}, the varied parameter"
                )
        if self.procedure == "staircase":
            return self._staircase_consistent()
        if self.procedure == "quest_plus":
            return self._quest_consistent()
        if not self.varied.ratios:
            raise ValueError("varied.ratios is needed by procedure constant_stimuli")
        if self.repetitions is None:
            raise ValueError("repetitions is needed by procedure constant_stimuli")
        if self.staircase is not None or self.quest_plus is not None:
            raise ValueError(
                "staircase and quest_plus are for their procedures (procedure: staircase, "
                "procedure: quest_plus)"
            )
        if self.repetitions % self.blocks.per_standard:
            raise ValueError(
                f"repetitions ({self.repetitions}) must divide into blocks.per_standard "
                f"({self.blocks.per_standard}) equal blocks"
            )
        if self.interval.order == "randomized" and self.repetitions % 2:
            raise ValueError("interval.order randomized needs an even number of repetitions")
        return self

    def _quest_consistent(self) -> Experiment:
        q = self.quest_plus
        if q is None:
            raise ValueError("procedure quest_plus needs a quest_plus section")
        if self.varied.ratios or self.repetitions is not None or self.staircase is not None:
            raise ValueError(
                "varied.ratios, repetitions and staircase are not for quest_plus: it chooses "
                "its comparisons"
            )
        spec = params.PARAMS[self.varied.param]
        for s in self.varied.standards:
            for r in (q.min_ratio, q.max_ratio):
                if not spec.in_range(s * r):
                    raise ValueError(
                        f"quest_plus: the comparison standard {s:g} x {r:g} = {s * r:g} is "
                        f"outside {self.varied.param}'s range {spec.range_text()}"
                    )
        return self

    @property
    def adaptive(self) -> Staircase | QuestPlusDesign | None:
        """The adaptive procedure's section (staircase or quest_plus), None for constant
        stimuli."""
        return self.staircase if self.staircase is not None else self.quest_plus

    def _staircase_consistent(self) -> Experiment:
        st = self.staircase
        if st is None:
            raise ValueError("procedure staircase needs a staircase section")
        if self.varied.ratios or self.repetitions is not None:
            raise ValueError(
                "varied.ratios and repetitions are for constant_stimuli; a staircase chooses "
                "its comparisons"
            )
        spec = params.PARAMS[self.varied.param]
        for s in self.varied.standards:
            for sign in st.sign_list():
                c = s * (1 + sign * st.max_distance)
                if not spec.in_range(c):
                    raise ValueError(
                        f"staircase.max_distance: the comparison standard {s:g} x "
                        f"(1 {'+' if sign > 0 else '-'} {st.max_distance:g}) = {c:g} is outside "
                        f"{self.varied.param}'s range {spec.range_text()}"
                    )
        return self

    @property
    def comparisons(self) -> int:
        return len(self.varied.ratios)

    @property
    def trials_per_block(self) -> int:
        """Trials per block; a staircase's block is a track, at most max_trials long."""
        if self.adaptive is not None:
            return self.adaptive.max_trials
        assert self.repetitions is not None
        return self.comparisons * self.repetitions // self.blocks.per_standard

    @property
    def n_blocks(self) -> int:
        """Blocks per subject; a staircase's: its tracks (conditions x standards x sides)."""
        if self.adaptive is not None:
            return (
                len(self.conditions) * len(self.varied.standards) * len(self.adaptive.sign_list())
            )
        return len(self.conditions) * len(self.varied.standards) * self.blocks.per_standard

    def profile_path(self) -> Path:
        p = Path(self.profile)
        if p.is_absolute() or self.source is None:
            return p
        return self.source.parent / p

    def subject_seed(self, subject: str) -> int:
        """The seed of ``subject``'s plan: the file's seed, or one derived from it and the
        subject's id (per_subject), the same on every machine."""
        if not self.randomization.per_subject:
            return self.randomization.seed
        seq = np.random.SeedSequence([self.randomization.seed, zlib.crc32(subject.encode())])
        return int(seq.generate_state(1, np.uint64)[0] >> np.uint64(1))

    def trial_s(self) -> float:
        """Expected length of one trial, s: two explorations, the gap, the answer."""
        i = self.interval
        return 2 * i.exploration_s + i.gap_s + i.answer_s

    def duration_s(self) -> float:
        """Estimated session length per subject, s (every interval at its limit)."""
        total = self.n_blocks * self.trials_per_block
        return total * self.trial_s() + self.n_breaks() * self.breaks.duration_s

    def n_breaks(self) -> int:
        b = self.breaks
        if self.adaptive is not None:  # tracks interleave: breaks by trials only
            total = self.n_blocks * self.trials_per_block
            return (total - 1) // b.every_trials if b.every_trials else 0
        between = (self.n_blocks - 1) // b.every_blocks if b.every_blocks else 0
        within = (self.trials_per_block - 1) // b.every_trials if b.every_trials else 0
        return between + within * self.n_blocks


def file_hash(path: str | Path) -> str:
    """sha256 of a file's bytes (hex)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def parse_experiment(
    data: object, source: str | Path = "<experiment>", lines: dict | None = None
) -> Experiment:
    """Validate an already-parsed YAML document into an Experiment; ``lines`` (from the
    loader) gives each key path's line for the messages."""
    exp = validate_document(
        Experiment, data, source, lines, what="experiment", docs=DOCS, error=ExperimentError
    )
    return exp.model_copy(update={"source": Path(source)})


def load_experiment(path: str | Path) -> Experiment:
    """Read and validate the experiment file at ``path`` (not its profile: see
    ``check_experiment``)."""
    p = Path(path)
    data, lines = read_document(p, what="experiment", error=ExperimentError)
    exp = parse_experiment(data, p.resolve(), lines)
    return exp.model_copy(update={"file_hash": file_hash(p)})


def check_against_profile(exp: Experiment, profile: Profile) -> list[str]:
    """What in ``exp`` the base ``profile`` cannot do, one message per problem naming
    the experiment's key."""
    problems = []
    obj = profile.scene.object
    if exp.varied.param == "mass_kg" and obj.fixed:
        problems.append(
            "varied.param: mass_kg on a fixed object (the profile's scene.object.fixed is "
            "true): its mass is never felt"
        )
    for i, c in enumerate(exp.conditions):
        dirs = c.values().get("actuated_directions")
        if dirs is not None:
            want = [len(f.actuated_directions) for f in profile.fingers]
            got = [len(d) for d in dirs]
            if got != want:
                problems.append(
                    f"conditions[{i}:{c.name}].set.actuated_directions: {got} directions per "
                    f"finger, the profile has {want} (the number cannot change live)"
                )
        if c.values().get("mass_kg") is not None and obj.fixed:
            problems.append(f"conditions[{i}:{c.name}].set.mass_kg: the profile's object is fixed")
    return problems


def check_experiment(path: str | Path) -> tuple[Experiment, Profile]:
    """Load ``path`` and the base profile it names and check them together;
    ExperimentError (or ProfileError for the profile) naming file and key."""
    exp = load_experiment(path)
    prof_path = exp.profile_path()
    if not prof_path.is_file():
        raise ExperimentError(f"{exp.source}: profile: no such file {prof_path}")
    profile = load_profile(prof_path)
    problems = check_against_profile(exp, profile)
    if problems:
        lines = [f"{exp.source}: {len(problems)} error(s) against profile {prof_path}"]
        raise ExperimentError("\n".join(lines + [f"  {p}" for p in problems]))
    return exp, profile


__all__ = [
    "Experiment",
    "ExperimentError",
    "ProfileError",
    "check_against_profile",
    "check_experiment",
    "load_experiment",
    "parse_experiment",
]
