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
from hapticd.experiment.tables import FormatName
from hapticd.profile import (
    Bool,
    Float,
    Int,
    Profile,
    ProfileError,
    load_profile,
    read_document,
    validate_document,
)
from hapticd.protocol import SCREEN_TEXT_CHARS, screen_text_ok

EXPERIMENT_VERSION = 1
DOCS = "docs/experiments.md"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ExperimentError(ValueError):
    """An experiment file that cannot be used; the message names file, key path and
    expectation."""


def _param_check(name: str) -> Any:
    def check(value: Any) -> Any:
        spec = params.PARAMS[name]
        try:
            value = spec.check(value)
        except params.ParamError as exc:
            raise ValueError(str(exc)) from None
        if spec.plugins and value not in spec.choices:  # an allocator plugin's name?
            from hapticd.allocation import plugins

            if not plugins.is_known(value):
                raise ValueError(
                    f"{name} must be one of {list(spec.choices)} or an installed "
                    f"plugin's: {plugins.unknown(value)}"
                )
        return value

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
    standards: tuple[Float, ...] = Field(min_length=1, description="standard values, SI units")
    ratios: tuple[Float, ...] = Field(
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
    exploration_s: Float = Field(gt=0, le=60, description="longest exploration per interval, s")
    ends_on: Literal["release", "time_limit"] = Field(
        description="release: the interval ends when the contacts end (or at exploration_s); "
        "time_limit: it lasts exploration_s"
    )
    gap_s: Float = Field(
        default=1.0, ge=0, le=60, description="between the two intervals (the change), s"
    )
    answer_s: Float = Field(
        default=2.0, gt=0, le=60, description="expected time to answer, s (duration estimate)"
    )


class Blocks(_Strict):
    """How trials are grouped: a block holds one condition and one standard."""

    per_standard: Int = Field(
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
    every_blocks: Int = Field(default=1, ge=0, description="a break after every N blocks; 0: none")
    every_trials: Int | None = Field(
        default=None, ge=1, description="also a break every N trials within a block"
    )
    duration_s: Float = Field(default=60.0, ge=0, le=3600, description="break length, s")


class Randomization(_Strict):
    seed: Int = Field(ge=0, lt=2**63, description="seed of the trial order")
    per_subject: Bool = Field(
        default=True, description="derive each subject's seed from seed and the subject's id"
    )
    counterbalance: Literal["none", "latin_square", "abba"] = Field(
        default="none",
        description="the conditions' order across subjects: none (blocks.condition_order); "
        "latin_square (subject k: row k of a balanced Latin square); abba (each condition "
        "in two halves, A B B A, and B A A B for every other subject)",
    )


# The answer rule of each staircase and the share of "correct" answers it converges on
# (Levitt 1971): two (three) correct in a row make it harder, one wrong easier; updown:
# n_down correct in a row harder, n_up wrong in a row easier; the weighted rule
# (Kaernbach 1991) moves up by step x target / (1 - target) after a wrong answer, down by
# step after a correct one, and converges on its target.
RULE_MOVES = {"1up2down": (1, 2), "1up3down": (1, 3), "weighted": (1, 1)}


def updown_target(n_up: int, n_down: int) -> float:
    """The share correct a transformed up-down staircase converges on (Levitt 1971): the
    p at which n_down correct in a row come before n_up wrong in a row half the time
    (1 up 2 down: 0.5 ** 0.5)."""
    from scipy import optimize

    def down_first(p: float) -> float:
        q = 1 - p
        a, b = p ** (n_down - 1), q ** (n_up - 1)
        return a * (1 - q**n_up) / (a + b - a * b) - 0.5

    return float(optimize.brentq(down_first, 1e-9, 1 - 1e-9, xtol=1e-14))


RULE_TARGETS = {"1up2down": 2**-0.5, "1up3down": 2 ** (-1 / 3)}


class Staircase(_Strict):
    """An adaptive staircase per condition, standard and side (docs/experiments.md):
    the comparison's distance from the standard, as a fraction of the standard, goes
    down after correct answers and up after wrong ones. The moves, steps and stopping
    rule are PsychoPy's StairHandler's (``step_type``, ``n_up``/``n_down``,
    ``initial_rule``, ``stop``), given the same answers; the defaults are the rules this
    section had before those keys."""

    rule: Literal["1up2down", "1up3down", "weighted", "updown"] = Field(
        description="1up2down (converges on 70.7 % correct), 1up3down (79.4 %), weighted "
        "(on target), updown (n_up wrong in a row easier, n_down correct in a row harder)"
    )
    target: Float | None = Field(
        default=None, gt=0.5, lt=1.0, description="the weighted rule's share correct"
    )
    n_up: Int | None = Field(
        default=None, ge=1, le=10, description="updown: wrong answers in a row that move it up"
    )
    n_down: Int | None = Field(
        default=None, ge=1, le=10, description="updown: correct answers in a row that move it down"
    )
    initial_rule: Bool = Field(
        default=False,
        description="one up, one down until the first reversal (PsychoPy's applyInitialRule)",
    )
    sides: Literal["both", "above"] = Field(
        default="both",
        description="both: a track above the standard (correct: the comparison judged more) "
        "and one below (correct: judged less), interleaved; above: only the first",
    )
    start: Float = Field(gt=0, description="first distance from the standard, fraction of it")
    step_type: Literal["lin", "db", "log"] = Field(
        default="lin",
        description="lin: the step is added to (taken from) the distance, a fraction of the "
        "standard; db: the distance is multiplied (divided) by 10 ** (step / 20); log: by "
        "10 ** step",
    )
    step: Float = Field(gt=0, description="first step (lin: fraction of the standard; db; log10)")
    step_rule: Literal["fixed", "halve"] = Field(
        default="halve", description="halve: the step halves at each reversal, to min_step"
    )
    min_step: Float | None = Field(default=None, gt=0, description="smallest step (halve)")
    min_distance: Float = Field(
        default=0.0,
        ge=-1.0,
        description="the nearest a comparison may come to the standard, fraction of it; "
        "negative (lin steps): the track may cross the standard by that much",
    )
    max_distance: Float = Field(
        gt=0, description="the farthest a comparison may be from the standard, fraction of it"
    )
    stop: Literal["either", "both"] = Field(
        default="either",
        description="either: a track ends after stop_reversals reversals or max_trials "
        "trials; both: after stop_reversals reversals and min_trials trials (PsychoPy's "
        "nReversals and nTrials), max_trials at most",
    )
    stop_reversals: Int = Field(default=8, ge=2, le=100, description="a track ends after these")
    min_trials: Int = Field(
        default=0, ge=0, le=1000, description="stop both: a track runs at least these trials"
    )
    max_trials: Int = Field(default=60, ge=2, le=1000, description="or after these trials")
    threshold_reversals: Int = Field(
        default=6, ge=1, description="the threshold: mean of the last N reversals' distances"
    )

    @model_validator(mode="after")
    def _converges(self) -> Staircase:
        lin = self.step_type == "lin"
        if lin and self.step > self.max_distance:
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
        if (self.rule == "updown") != (self.n_down is not None) or (
            self.n_up is not None and self.rule != "updown"
        ):
            raise ValueError(
                "n_down (and n_up, 1 by default) are the updown rule's, and only its; "
                f"{self.rule} moves as its name says"
            )
        if self.rule == "updown" and self.target_share <= 0.5 + 1e-9:
            raise ValueError(
                f"n_up {self.moves[0]}, n_down {self.moves[1]} converge on "
                f"{self.target_share:.1%} correct: a threshold needs more than 50 % (n_down "
                "larger than n_up)"
            )
        if self.initial_rule and self.rule == "weighted":
            raise ValueError(
                "initial_rule: the weighted rule already moves after every answer (one up, "
                "one down); it changes nothing there"
            )
        if self.threshold_reversals > self.stop_reversals:
            raise ValueError(
                f"threshold_reversals ({self.threshold_reversals}) exceeds stop_reversals "
                f"({self.stop_reversals}): a stopped track would not have them"
            )
        if self.stop == "either" and self.min_trials:
            raise ValueError("min_trials is for stop: both (either: the first of the two ends it)")
        if self.min_trials > self.max_trials:
            raise ValueError(
                f"min_trials ({self.min_trials}) exceeds max_trials ({self.max_trials})"
            )
        if self.sides == "both" and self.max_distance >= 1:
            raise ValueError(
                f"max_distance {self.max_distance:g}: a track below the standard needs it "
                "below 1 (a comparison above 0)"
            )
        if self.min_distance >= self.start:
            raise ValueError(
                f"min_distance {self.min_distance:g}: a track starts at start "
                f"{self.start:g}, which must be farther than it"
            )
        if self.min_distance < 0 and not lin:
            raise ValueError(
                f"min_distance {self.min_distance:g}: {self.step_type} steps multiply the "
                "distance, which so never reaches the standard; crossing it needs "
                "step_type lin"
            )
        if -self.min_distance > self.max_distance or (
            self.sides == "above" and self.min_distance <= -1
        ):
            raise ValueError(
                f"min_distance {self.min_distance:g}: a track may cross the standard by at "
                f"most max_distance ({self.max_distance:g})"
                + (", and above 0" if self.sides == "above" else "")
            )
        return self

    @property
    def moves(self) -> tuple[int, int]:
        """(n_up, n_down): wrong answers in a row that move a track up, correct ones down."""
        if self.rule == "updown":
            return (self.n_up or 1, int(self.n_down or 1))
        return RULE_MOVES[self.rule]

    @property
    def target_share(self) -> float:
        """The share of correct answers the track converges on."""
        if self.target is not None:
            return self.target
        if self.rule in RULE_TARGETS:
            return RULE_TARGETS[self.rule]
        return updown_target(*self.moves)

    @property
    def up_factor(self) -> float:
        """How many steps a move up takes: the weighted rule's target / (1 - target), 1
        otherwise."""
        if self.rule != "weighted":
            return 1.0
        return self.target_share / (1 - self.target_share)

    def sign_list(self) -> tuple[int, ...]:
        """The sides' signs: +1 above the standard, -1 below."""
        return (1, -1) if self.sides == "both" else (1,)


class QuestPlusDesign(_Strict):
    """QUEST+ (Watson 2017; the ``questplus`` package) per condition and standard: the
    comparison (a ratio of the standard, on a grid) that minimises the expected entropy
    of the posterior over the psychometric function's PSE and sigma, for a fixed number
    of trials."""

    min_ratio: Float = Field(gt=0, lt=1, description="the smallest comparison / standard")
    max_ratio: Float = Field(gt=1, description="the largest comparison / standard")
    n_stimuli: Int = Field(default=41, ge=5, le=201, description="comparisons on the grid")
    trials: Int = Field(default=40, ge=5, le=1000, description="trials per track")
    lapse: Float = Field(default=0.02, ge=0, lt=0.5, description="assumed lapse rate")

    @property
    def max_trials(self) -> int:
        return self.trials

    def sign_list(self) -> tuple[int, ...]:
        """One track per condition and standard (both sides on one grid)."""
        return (1,)


class ExportSection(_Strict):
    """How ``hapticd experiment export`` writes this experiment's trials by default."""

    format: FormatName = Field(
        default="csv", description="csv, parquet or mat: the export's --format by default"
    )


class Analysis(_Strict):
    """How the answers are analysed."""

    jnd_point: Literal[0.75, 0.84] = Field(
        default=0.75,
        description="the JND is x(p) - x(0.5) of the fitted curve: 0.75 (0.6745 sigma) or "
        "0.84 (0.9945 sigma, about one sigma); every table and plot names it",
    )


# A subject's id: it names files (the recordings), so file-name characters only.
SUBJECT_ID = r"^[A-Za-z0-9_.-]{1,64}$"
# Session metadata every experiment takes (``--meta KEY=VALUE``); the subject is --subject.
STANDARD_METADATA = ("session", "experimenter", "notes")


class MetadataKey(_Strict):
    """A session metadata key the lab declares: whether a run must give it, and what a
    value may be."""

    required: Bool = Field(default=False, description="a run without it is refused")
    type: Literal["text", "integer", "number"] = Field(
        default="text", description="text, integer or number (SI units named in the key)"
    )
    choices: tuple[str, ...] = Field(default=(), description="the only values allowed (text)")
    description: str = ""

    @model_validator(mode="after")
    def _choices_are_text(self) -> MetadataKey:
        if self.choices and self.type != "text":
            raise ValueError(f"choices are for type text, not {self.type}")
        return self

    def parse(self, value: str) -> str | int | float:
        """``value`` (as given on the command line) as this key's type; ValueError saying
        what was expected."""
        if self.type == "text":
            if self.choices and value not in self.choices:
                raise ValueError(f"expected one of {', '.join(self.choices)}, got {value!r}")
            return value
        try:
            number: int | float = int(value) if self.type == "integer" else float(value)
        except ValueError:
            raise ValueError(
                f"expected {'an integer' if self.type == 'integer' else 'a number'}, got {value!r}"
            ) from None
        if not math.isfinite(number):
            raise ValueError(f"expected a finite number, got {value!r}")
        return number


MetadataName = Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]{0,31}$")]


class Metadata(_Strict):
    """The session metadata a lab declares beyond the standard keys (session,
    experimenter, notes), given at run time with ``--meta KEY=VALUE``."""

    keys: dict[MetadataName, MetadataKey] = Field(default_factory=dict)

    @field_validator("keys")
    @classmethod
    def _not_subject(cls, v: dict[str, MetadataKey]) -> dict[str, MetadataKey]:
        if "subject" in v:
            raise ValueError("subject is not declared here: every run gives it (--subject)")
        return v

    def spec(self, key: str) -> MetadataKey | None:
        """The declared (or standard: optional text) key ``key``; None for an unknown one."""
        if key in self.keys:
            return self.keys[key]
        return MetadataKey() if key in STANDARD_METADATA else None

    def names(self) -> tuple[str, ...]:
        """Every key a run may give: the standard ones, then the declared ones."""
        return STANDARD_METADATA + tuple(k for k in self.keys if k not in STANDARD_METADATA)


def _screen_text(v: str) -> str:
    if not screen_text_ok(v):
        raise ValueError(
            f"expected printable text (line breaks allowed) of at most {SCREEN_TEXT_CHARS} "
            "characters"
        )
    return v


ScreenText = Annotated[str, AfterValidator(_screen_text)]


class Instructions(_Strict):
    """What the subject's screen shows before the session (and its practice); the session
    begins when the subject answers "Ready to begin?" yes."""

    enabled: Bool = Field(default=True, description="show the instructions before the session")
    text: ScreenText = Field(default="", description="the instructions, shown as written")

    @model_validator(mode="after")
    def _text(self) -> Instructions:
        if self.enabled and not self.text.strip():
            raise ValueError(
                "text: the instructions' text is missing (needed while enabled is true: "
                "the words the subject reads before the session)"
            )
        return self


class Practice(_Strict):
    """Practice trials before the session: marked as practice on the subject's screen and
    in the store (``practice``), never analysed."""

    trials: Int = Field(ge=1, le=100, description="how many practice trials")
    conditions: tuple[str, ...] | None = Field(
        default=None, min_length=1, description="names of the conditions practised (all)"
    )
    standards: tuple[Float, ...] | None = Field(
        default=None, min_length=1, description="standards practised, SI (the design's)"
    )
    ratios: tuple[Float, ...] | None = Field(
        default=None,
        min_length=1,
        description="comparison / standard levels practised (the design's easiest: its "
        "farthest comparisons)",
    )

    @field_validator("ratios")
    @classmethod
    def _positive(cls, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if v is not None and any(not (math.isfinite(r) and r > 0) for r in v):
            raise ValueError(f"ratios must be positive, got {list(v)}")
        return v


class Feedback(_Strict):
    """Correct or incorrect on the subject's screen after a trial, where the trial has a
    correct answer (its comparison differs from its standard)."""

    after: Literal["none", "practice", "all"] = Field(
        default="none", description="none, practice trials only, or every trial"
    )
    duration_s: Float = Field(default=1.0, gt=0, le=10, description="how long it shows, s")


class Display(_Strict):
    """What the subject's page shows besides the states."""

    scene: Bool = Field(
        default=True,
        description="draw the scene; false: text only (the object's motion is a cue of its "
        "own in a weight task)",
    )
    progress: Bool = Field(default=False, description='"trial N of M" on the subject\'s screen')


class Experiment(_Strict):
    """A complete experiment file (docs/experiments.md)."""

    version: Literal[1] = 1
    # It names the recordings (EXPERIMENT-SUBJECT-TRIAL-INTERVAL.hrec): a file name.
    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    description: str = ""
    procedure: str = Field(
        default="constant_stimuli",
        description="how comparisons are chosen: constant_stimuli (every ratio, repetitions "
        "times, in a planned order), staircase (each next comparison from the answers so "
        "far, the tracks interleaved), quest_plus (QUEST+, interleaved), or the name of an "
        "installed procedure (hapticd procedures)",
    )
    profile: str = Field(min_length=1, description="base profile, relative to this file")
    varied: Varied
    conditions: tuple[Condition, ...] = Field(min_length=1)
    repetitions: Int | None = Field(
        default=None, ge=1, le=1000, description="presentations of each comparison"
    )
    staircase: Staircase | None = None
    quest_plus: QuestPlusDesign | None = None
    settings: dict[str, Any] | None = Field(
        default=None,
        description="an installed procedure's settings (its Settings model; docs/experiments.md)",
    )
    interval: Interval
    blocks: Blocks = Blocks()
    breaks: Breaks = Breaks()
    randomization: Randomization
    analysis: Analysis = Analysis()
    subjects: tuple[Annotated[str, Field(pattern=SUBJECT_ID)], ...] = Field(
        default=(),
        description="the subject list, in order: subject k (0-based) gets the k-th "
        "counterbalanced order",
    )
    metadata: Metadata = Metadata()

    # The subject's screen (docs/experiments.md, "The subject's screen").
    instructions: Instructions | None = None
    practice: Practice | None = None
    feedback: Feedback = Feedback()
    display: Display = Display()

    export: ExportSection = ExportSection()

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

    @field_validator("procedure")
    @classmethod
    def _known_procedure(cls, v: str) -> str:
        from hapticd.experiment import procedure

        procedure.get(v)  # UnknownProcedureError (a ValueError) names the known ones
        return v

    @field_validator("randomization")
    @classmethod
    def _counterbalance(cls, v: Randomization, info: ValidationInfo) -> Randomization:
        # The fields before it (procedure, blocks) are validated already: in info.data.
        scheme, procedure = v.counterbalance, info.data.get("procedure")
        blocks = info.data.get("blocks") or Blocks()
        if scheme == "none" or procedure is None:  # None: its own error is reported
            return v
        if procedure != "constant_stimuli":
            raise ValueError(
                f"counterbalance {scheme} orders blocks; procedure {procedure} interleaves "
                "its tracks: use counterbalance none"
            )
        if blocks.condition_order != "listed":
            raise ValueError(
                f"counterbalance {scheme} orders the conditions: blocks.condition_order must "
                "be listed, not random"
            )
        if scheme == "abba" and blocks.per_standard % 2:
            raise ValueError(
                "counterbalance abba presents each condition in two halves (A B B A): "
                f"blocks.per_standard must be even, got {blocks.per_standard}"
            )
        return v

    @field_validator("subjects")
    @classmethod
    def _unique_subjects(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        dup = sorted({s for s in v if v.count(s) > 1})
        if dup:
            raise ValueError(f"subjects must be unique, repeated: {dup}")
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
        if (
            self.procedure != "constant_stimuli"
            and self.settings is not None
            and self.procedure
            in (
                "staircase",
                "quest_plus",
            )
        ):
            raise ValueError(
                f"settings are an installed procedure's; {self.procedure}'s are its own "
                f"section ({self.procedure})"
            )
        if self.procedure == "staircase":
            return self._staircase_consistent()
        if self.procedure == "quest_plus":
            return self._quest_consistent()
        if self.procedure != "constant_stimuli":
            return self._plugin_consistent()
        if self.settings is not None:
            raise ValueError("settings are an installed procedure's, not constant_stimuli's")
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

    def subject_index(self, subject: str, index: int | None = None) -> int | None:
        """``subject``'s place in the counterbalancing (0-based): ``index`` when given,
        else its place in ``subjects``; None when the design counterbalances nothing and
        no index is given. ExperimentError when it needs one and has none, or when
        ``index`` contradicts the subject list."""
        listed = self.subjects.index(subject) if subject in self.subjects else None
        if index is not None:
            if index < 0:
                raise ExperimentError(f"{self.source}: subject index {index}: expected 0 or more")
            if listed is not None and listed != index:
                raise ExperimentError(
                    f"{self.source}: subject {subject!r} is number {listed} (0-based) of the "
                    f"file's subjects{_key_line(self, ('subjects', listed))}, not {index}"
                )
            return index
        if listed is not None or self.randomization.counterbalance == "none":
            return listed
        raise ExperimentError(
            f"{self.source}: randomization.counterbalance "
            f"{self.randomization.counterbalance}: subject {subject!r} is not in the file's "
            f"subjects{_key_line(self, ('subjects',))}; add it there, or give its index "
            "(--subject-index K, 0-based: it gets the K-th order)"
        )

    def check_metadata(
        self, given: dict[str, str], previous: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        """A session's metadata: ``given`` (KEY -> text, from ``--meta``) checked
        against the file's ``metadata`` section and typed, over ``previous`` (a resumed
        subject's last session's); ExperimentError naming every unknown key, bad value
        and missing required key, with the file's line."""
        meta, problems = self.metadata, []
        out = dict(previous or {})
        for key, text in given.items():
            spec = meta.spec(key)
            if spec is None:
                problems.append(
                    f"{key}: unknown metadata key (known: {', '.join(meta.names())}; declare "
                    f"it under metadata.keys{_key_line(self, ('metadata', 'keys'))})"
                )
                continue
            try:
                out[key] = spec.parse(text)
            except ValueError as exc:
                problems.append(f"{key}: {exc}{_key_line(self, ('metadata', 'keys', key))}")
        for key, spec in meta.keys.items():
            if spec.required and key not in out and key not in given:
                problems.append(
                    f"{key}: required (give --meta {key}=VALUE)"
                    f"{_key_line(self, ('metadata', 'keys', key))}"
                )
        if problems:
            head = f"{self.source}: {len(problems)} error(s) in the session's metadata"
            raise ExperimentError("\n".join([head] + [f"  {p}" for p in problems]))
        return out

    @field_validator("practice")
    @classmethod
    def _practice_consistent(cls, pr: Practice | None, info: ValidationInfo) -> Practice | None:
        # A field's check (the fields it needs come before it): the error names its line.
        d = info.data
        if pr is None or "varied" not in d or "conditions" not in d:
            return pr
        names = [c.name for c in d["conditions"]]
        for name in pr.conditions or ():
            if name not in names:
                raise ValueError(
                    f"conditions: no condition {name!r}; the conditions: {', '.join(names)}"
                )
        varied: Varied = d["varied"]
        spec = params.PARAMS[varied.param]
        ratios = practice_levels(
            pr, varied, d.get("staircase"), d.get("quest_plus"), _plugin_range(d)
        )
        for s in pr.standards or varied.standards:
            if not (math.isfinite(s) and spec.in_range(s)):
                raise ValueError(
                    f"standards: {s:g} is outside {spec.name}'s range {spec.range_text()}"
                )
            for r in ratios:
                if not (math.isfinite(s * r) and spec.in_range(s * r)):
                    raise ValueError(
                        f"ratios: the comparison {s:g} x {r:g} = {s * r:g} is outside "
                        f"{spec.name}'s range {spec.range_text()}"
                    )
        return pr

    def practice_standards(self) -> tuple[float, ...]:
        """The standards the practice trials use (SI)."""
        pr = self.practice
        return (pr.standards if pr and pr.standards else None) or self.varied.standards

    def practice_ratios(self) -> tuple[float, ...]:
        """The comparison / standard levels the practice trials use."""
        plugin = None
        if self.procedure not in ("constant_stimuli", "staircase", "quest_plus"):
            plugin = self.proc.ratio_range()
        return practice_levels(self.practice, self.varied, self.staircase, self.quest_plus, plugin)

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

    def _plugin_consistent(self) -> Experiment:
        """An installed procedure's design: its settings (its Settings model), no
        constant stimuli's or built-ins' keys, every comparison in the parameter's range."""
        from pydantic import ValidationError

        from hapticd.experiment import procedure

        if self.varied.ratios or self.repetitions is not None:
            raise ValueError(
                f"varied.ratios and repetitions are for constant_stimuli; {self.procedure} "
                "chooses its comparisons"
            )
        if self.staircase is not None or self.quest_plus is not None:
            raise ValueError(
                "staircase and quest_plus are for their procedures; an installed procedure "
                "takes settings"
            )
        cls = procedure.get(self.procedure)
        try:
            proc = cls(cls.section(self))
        except ValidationError as exc:
            errs = "; ".join(
                f"settings.{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors()
            )
            raise ValueError(f"procedure {self.procedure}: {errs}") from None
        proc.check(self)
        lo, hi = proc.ratio_range()
        spec = params.PARAMS[self.varied.param]
        for s in self.varied.standards:
            for r in (lo, hi):
                if not (math.isfinite(s * r) and spec.in_range(s * r)):
                    raise ValueError(
                        f"procedure {self.procedure}: the comparison standard {s:g} x {r:g} = "
                        f"{s * r:g} is outside {self.varied.param}'s range {spec.range_text()}"
                    )
        return self

    @property
    def proc(self) -> Any:
        """The procedure (hapticd.experiment.procedure.Procedure) with its settings."""
        from hapticd.experiment import procedure

        return procedure.of(self)

    @property
    def adaptive(self) -> Any:
        """The adaptive procedure's section (staircase, quest_plus, or an installed
        procedure's settings), None for constant stimuli."""
        if self.procedure == "constant_stimuli":
            return None
        if self.procedure not in ("staircase", "quest_plus"):
            return self.proc.settings
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
            # A track above the standard that may cross it reaches s x (1 + min_distance).
            c = s * (1 + st.min_distance)
            if st.min_distance < 0 and not spec.in_range(c):
                raise ValueError(
                    f"staircase.min_distance: the comparison standard {s:g} x (1 - "
                    f"{-st.min_distance:g}) = {c:g} is outside {self.varied.param}'s range "
                    f"{spec.range_text()}"
                )
        return self

    @property
    def comparisons(self) -> int:
        return len(self.varied.ratios)

    @property
    def trials_per_block(self) -> int:
        """Trials per block; a staircase's block is a track, at most max_trials long."""
        if self.procedure != "constant_stimuli":
            return int(self.proc.max_trials)
        assert self.repetitions is not None
        return self.comparisons * self.repetitions // self.blocks.per_standard

    @property
    def n_blocks(self) -> int:
        """Blocks per subject; a staircase's: its tracks (conditions x standards x sides)."""
        if self.procedure != "constant_stimuli":
            return len(self.conditions) * len(self.varied.standards) * len(self.proc.sides)
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
        """Estimated session length per subject, s (every interval at its limit; the
        practice trials too)."""
        total = self.n_blocks * self.trials_per_block
        total += self.practice.trials if self.practice is not None else 0
        return total * self.trial_s() + self.n_breaks() * self.breaks.duration_s

    def n_breaks(self) -> int:
        b = self.breaks
        if self.procedure != "constant_stimuli":  # tracks interleave: breaks by trials only
            total = self.n_blocks * self.trials_per_block
            return (total - 1) // b.every_trials if b.every_trials else 0
        between = (self.n_blocks - 1) // b.every_blocks if b.every_blocks else 0
        within = (self.trials_per_block - 1) // b.every_trials if b.every_trials else 0
        return between + within * self.n_blocks


def _key_line(exp: Experiment, path: tuple[str | int, ...]) -> str:
    """`` (line N)`` of the key at ``path`` in ``exp``'s file (read again: only an error
    message needs it); empty when the file or the key is not there."""
    if exp.source is None or not exp.source.is_file():
        return ""
    try:
        _, lines = read_document(exp.source, what="experiment", error=ExperimentError)
    except ExperimentError:
        return ""
    line = lines.get(path)
    return "" if line is None else f" (line {line})"


def practice_levels(
    pr: Practice | None,
    varied: Varied,
    staircase: Staircase | None,
    quest_plus: QuestPlusDesign | None,
    plugin: tuple[float, float] | None = None,
) -> tuple[float, ...]:
    """The comparison / standard levels of the practice trials: the file's, else the
    design's farthest comparisons (the easiest to tell; ``plugin``: an installed
    procedure's ratio range)."""
    if pr is not None and pr.ratios:
        return pr.ratios
    if plugin is not None:
        return tuple(sorted({r for r in plugin if r != 1.0})) or (1.0,)
    if staircase is not None:
        return tuple(1 + sign * staircase.start for sign in staircase.sign_list())
    if quest_plus is not None:
        return (quest_plus.min_ratio, quest_plus.max_ratio)
    if not varied.ratios:
        return (1.0,)
    return tuple(sorted({min(varied.ratios), max(varied.ratios)}))


def _plugin_range(data: dict[str, Any]) -> tuple[float, float] | None:
    """An installed procedure's ratio range from the fields validated so far (None: a
    built-in, or settings its own check will refuse)."""
    name = data.get("procedure")
    if name in (None, "constant_stimuli", "staircase", "quest_plus"):
        return None
    from hapticd.experiment import procedure

    try:
        cls = procedure.get(name)
        return cls(
            cls.Settings.model_validate(data.get("settings") or {}) if cls.Settings else None
        ).ratio_range()
    except Exception:  # the settings' own errors are told by _plugin_consistent
        return None


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
        limit = c.values().get("force_limit_n")
        cap = profile.safety.max_force_n
        if limit is not None and limit > cap:
            problems.append(
                f"conditions[{i}:{c.name}].set.force_limit_n: {limit:g} N is above the "
                f"profile's safety.max_force_n {cap:g} N (a condition may lower it, not raise it)"
            )
    if exp.varied.param == "force_limit_n":
        top = max(_varied_values(exp))
        if top > profile.safety.max_force_n:
            problems.append(
                f"varied: force_limit_n reaches {top:g} N, above the profile's "
                f"safety.max_force_n {profile.safety.max_force_n:g} N"
            )
    return problems


def _varied_values(exp: Experiment) -> list[float]:
    """The standards and the farthest comparisons the design may present (SI)."""
    v = exp.varied
    out = list(v.standards)
    if exp.staircase is not None:
        out += [s * (1 + exp.staircase.max_distance) for s in v.standards]
    elif exp.quest_plus is not None:
        out += [s * exp.quest_plus.max_ratio for s in v.standards]
    elif exp.procedure != "constant_stimuli":
        out += [s * exp.proc.ratio_range()[1] for s in v.standards]
    else:
        out += [s * r for s in v.standards for r in v.ratios]
    return out


def check_experiment(
    path: str | Path, profile: str | Path | None = None
) -> tuple[Experiment, Profile]:
    """Load ``path`` and the base profile it names (or ``profile``: the design run on
    another base profile, a rig's) and check them together; ExperimentError (or
    ProfileError for the profile) naming file and key."""
    exp = load_experiment(path)
    if profile is not None:
        exp = exp.model_copy(update={"profile": str(Path(profile).absolute())})
    prof_path = exp.profile_path()
    if not prof_path.is_file():
        raise ExperimentError(f"{exp.source}: profile: no such file {prof_path}")
    base = load_profile(prof_path)
    problems = check_against_profile(exp, base)
    if problems:
        lines = [f"{exp.source}: {len(problems)} error(s) against profile {prof_path}"]
        raise ExperimentError("\n".join(lines + [f"  {p}" for p in problems]))
    return exp, base


__all__ = [
    "Experiment",
    "ExperimentError",
    "ProfileError",
    "check_against_profile",
    "check_experiment",
    "load_experiment",
    "parse_experiment",
]
