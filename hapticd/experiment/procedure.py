"""The Procedure interface: how an experiment chooses its comparisons, and what its
analysis reports (docs/experiments.md, "Writing a procedure").

Every procedure, built-in (constant stimuli, the staircases, QUEST+) or from a lab's own
package (the ``hapticd.procedures`` entry-point group), implements ``Procedure``; the
runner, the model observer, ``hapticd study``, the trial store and ``hapticd experiment
analyze`` use nothing else of it. An experiment file names it by its name
(``procedure: NAME``); a plugin's settings are the file's ``settings`` section, checked by
its ``Settings`` model.

An adaptive procedure runs **tracks**: one per condition, standard and side (``sides``),
interleaved, each a state that is a pure function of its answers. So:

- the next trial: a live track drawn by a generator seeded by the subject's seed and the
  trial's index (``next_trial``), its ``comparison``;
- the update: ``update(track, more, comparison)`` after an answer (``more``: the
  comparison judged more), ``skip(track)`` after a failed exploration;
- done: ``done(track)``; the estimate: ``estimate(track)`` (``jnd`` in the varied
  parameter's SI unit, and whatever else it reports);
- resume needs only the stored rows (``block``, ``comparison``, ``comparison_more``,
  ``status``): ``replay`` rebuilds every track from them;
- analysis: ``analyze`` (per track the estimate; per subject, condition and standard the
  JND and Weber fraction; paired t-tests between conditions) and ``report``.

Pure: no I/O.
"""

from __future__ import annotations

import abc
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from hapticd_drivers.plugins import Plugin, Problem, Registry
from pydantic import BaseModel

from hapticd.experiment.comparisons import _test_lines, paired_tests, session_rows
from hapticd.experiment.trial import PlannedTrial

if TYPE_CHECKING:
    from hapticd.experiment.spec import Experiment

GROUP = "hapticd.procedures"


@dataclass
class Track:
    """One track's state every procedure's tracks carry: its index (the store's
    ``block``), condition, standard (SI), side (``sign`` +1 above the standard, -1 below),
    trials answered or skipped (``n``), and each answered trial's comparison / standard - 1
    (``levels``) and answer (``correct``: judged more above the standard, less below).
    A procedure's own track subclasses it with its state."""

    index: int
    condition: str
    standard: float
    sign: int = 1
    n: int = 0
    levels: list[float] = field(default_factory=list)
    correct: list[bool] = field(default_factory=list)

    @property
    def side(self) -> str:
        return "above" if self.sign > 0 else "below"


class Procedure(abc.ABC):
    """How an experiment chooses its comparisons, and what its analysis reports.

    A subclass sets ``name`` (its entry point's), ``Settings`` (a pydantic model of the
    file's section; None: none) and implements the abstract methods. ``plans_ahead``:
    every trial is planned at the start (constant stimuli: ``hapticd.experiment.plan``);
    an adaptive procedure decides each next trial from the answers so far."""

    name: ClassVar[str] = ""
    Settings: ClassVar[type[BaseModel] | None] = None
    plans_ahead: ClassVar[bool] = False
    # The analysis's key in ``hapticd experiment analyze``'s JSON (default: the name).
    result_key: ClassVar[str] = ""
    # Where the settings are: the experiment file's section, and the store design's key
    # (a plugin's: ``settings``; the built-in adaptive ones have sections of their own).
    section_key: ClassVar[str] = "settings"

    def __init__(self, settings: Any = None) -> None:
        self.settings = settings

    # -- the design -------------------------------------------------------------------

    @classmethod
    def section(cls, exp: Experiment) -> Any:
        """This procedure's settings in ``exp``: its ``section_key`` section, validated."""
        if cls.Settings is None:
            return None
        raw = getattr(exp, cls.section_key)
        return raw if isinstance(raw, cls.Settings) else cls.Settings.model_validate(raw or {})

    @classmethod
    def from_design(cls, design: Mapping[str, Any]) -> Procedure:
        """The procedure of a store's ``design`` (meta.design: what ``design`` wrote)."""
        raw = design.get(cls.section_key)
        return cls(None if cls.Settings is None else cls.Settings.model_validate(raw or {}))

    def design(self) -> dict[str, Any]:
        """What the store keeps of the settings (``from_design`` reads it back)."""
        dump = None if self.settings is None else self.settings.model_dump()
        return {self.section_key: dump}

    def check(self, exp: Experiment) -> None:
        """More checks of ``exp`` against this procedure: ValueError saying what is wrong
        (none by default)."""
        return None

    @property
    def sides(self) -> tuple[int, ...]:
        """The tracks' signs per condition and standard: +1 above the standard, -1 below."""
        return (1,)

    @property
    @abc.abstractmethod
    def max_trials(self) -> int:
        """The most trials of one track (a block)."""

    @abc.abstractmethod
    def ratio_range(self) -> tuple[float, float]:
        """The smallest and largest comparison / standard this procedure may present."""

    def describe(self, exp: Experiment) -> str:
        """The design's trials, as ``hapticd experiment check`` prints them."""
        return (
            f"{self.name}, {exp.n_blocks} tracks interleaved ({len(self.sides)} per condition "
            f"and standard), at most {self.max_trials} trials each: at most "
            f"{exp.n_blocks * self.max_trials} per subject"
        )

    # -- a track ----------------------------------------------------------------------

    @abc.abstractmethod
    def new_track(self, index: int, condition: str, standard: float, sign: int) -> Any:
        """A track at its start (a ``Track``, or a subclass with the procedure's state)."""

    @abc.abstractmethod
    def comparison(self, track: Any) -> float:
        """The track's next comparison (the varied parameter's SI unit)."""

    @abc.abstractmethod
    def update(self, track: Any, more: bool, comparison: float) -> None:
        """Move ``track`` after the answer to ``comparison``: ``more``, it was judged more.
        Must count the trial (``track.n += 1``)."""

    @abc.abstractmethod
    def done(self, track: Any) -> bool:
        """Whether ``track`` has ended."""

    @abc.abstractmethod
    def estimate(self, track: Any) -> dict[str, Any]:
        """What ``track`` estimates so far: at least ``jnd`` (SI; None: not yet), and any
        other numbers the report shows."""

    def skip(self, track: Any) -> None:
        """A trial whose exploration failed: it counts towards the track's trials (so a
        track that always fails ends) and moves nothing."""
        track.n += 1

    # -- the session ------------------------------------------------------------------

    def tracks(self, exp: Experiment) -> list[Any]:
        """Every track of ``exp`` at its start, in the store's block order: conditions as
        listed, standards ascending, the sides in ``sides``' order."""
        out: list[Any] = []
        for c in exp.conditions:
            for s in sorted(exp.varied.standards):
                for sign in self.sides:
                    out.append(self.new_track(len(out), c.name, float(s), sign))
        return out

    def next_trial(
        self, exp: Experiment, seed: int, index: int, tracks: list[Any]
    ) -> PlannedTrial | None:
        """Trial ``index`` of the session: a track drawn among those not done (uniformly,
        by a generator seeded by ``seed`` and ``index``), its comparison; None when every
        track is done. The same seed gives the same session, in any process, resumed."""
        live = [t for t in tracks if not self.done(t)]
        if not live:
            return None
        rng = np.random.default_rng([int(seed), int(index)])
        track = live[int(rng.integers(len(live)))]
        first = exp.interval.order == "randomized" and bool(rng.integers(2))
        every = exp.breaks.every_trials
        pause = exp.breaks.duration_s if every and index > 0 and index % every == 0 else 0.0
        # 60 x 1.05 is 63.00000000000001 in binary; the design meant 63.
        comparison = float(f"{self.comparison(track):.12g}")
        return PlannedTrial(
            index=index,
            block=track.index,
            position=track.n,
            condition=track.condition,
            standard=track.standard,
            ratio=comparison / track.standard,
            comparison=comparison,
            comparison_first=first,
            break_before_s=float(pause),
        )

    def replay(self, exp: Experiment, rows: Iterable[Mapping[str, Any]]) -> list[Any]:
        """The tracks after the complete and failed store ``rows`` (``plan_index``,
        ``block``, ``status``, ``comparison``, ``comparison_more``), in plan order: what a
        resumed run starts from."""
        tracks = self.tracks(exp)
        for r in sorted(rows, key=lambda r: r["plan_index"]):
            status = r.get("status", "complete")
            if status == "failed":
                self.skip(tracks[int(r["block"])])
            elif status == "complete":
                self.update(tracks[int(r["block"])], bool(r["comparison_more"]), r["comparison"])
        return tracks

    def session(
        self,
        exp: Experiment,
        seed: int,
        answer: Callable[[PlannedTrial], bool | None],
        done: Iterable[Mapping[str, Any]] = (),
    ) -> list[tuple[PlannedTrial, bool | None]]:
        """The rest of a session after the store rows ``done``: each next trial and
        ``answer(trial)`` (True: the comparison judged more; None: its exploration failed),
        until every track is done. For simulated observers (no store)."""
        rows = list(done)
        tracks = self.replay(exp, rows)
        index = 1 + max((int(r["plan_index"]) for r in rows), default=-1)
        out = []
        while (trial := self.next_trial(exp, seed, index, tracks)) is not None:
            more = answer(trial)
            out.append((trial, more))
            if more is None:
                self.skip(tracks[trial.block])
            else:
                self.update(tracks[trial.block], more, trial.comparison)
            index += 1
        return out

    # -- the analysis -----------------------------------------------------------------

    def track_rows(self, rows: Iterable[Mapping[str, Any]]) -> dict[tuple[str, int], Any]:
        """Every track in the store ``rows`` (complete trials of any subjects), replayed:
        {(subject, block): track}. Its condition, standard and side are its trials' (the
        side: of its first comparison), so the rows suffice whatever reduced design ran."""
        by: dict[tuple[str, int], list[Mapping[str, Any]]] = defaultdict(list)
        for r in rows:
            if r.get("status", "complete") == "complete" and r.get("block") is not None:
                by[(r["subject"], int(r["block"]))].append(r)
        out = {}
        for (subject, block), rs in sorted(by.items()):
            rs = sorted(rs, key=lambda r: r["plan_index"])
            first = rs[0]
            sign = 1
            if len(self.sides) > 1:
                sign = 1 if first["comparison"] > first["standard"] else -1
            track = self.new_track(block, first["condition"], float(first["standard"]), sign)
            for r in rs:
                self.update(track, bool(r["comparison_more"]), r["comparison"])
            out[(subject, block)] = track
        return out

    def analyze(
        self,
        trials: list[dict[str, Any]],
        *,
        conditions: list[str] | None = None,
        jnd_point: float = 0.75,
    ) -> dict[str, Any]:
        """Per track its estimate; per subject, condition and standard the JND (the mean
        of its sides' ``jnd``) and Weber fraction; paired t-tests of the Weber fractions
        between conditions."""
        tracks = self.track_rows(session_rows(trials))
        rows = []
        for (subject, _), t in tracks.items():
            est = self.estimate(t)
            rows.append(
                {
                    "subject": subject,
                    "condition": t.condition,
                    "standard": t.standard,
                    "side": getattr(t, "side", "above"),
                    "trials": t.n,
                    "done": self.done(t),
                    **est,
                }
            )
        cells: dict[tuple[str, str, float], list[dict[str, Any]]] = defaultdict(list)
        for r in rows:
            cells[(r["subject"], r["condition"], r["standard"])].append(r)
        thresholds, weber = [], {}
        for key in sorted(cells):
            jnds = [r.get("jnd") for r in cells[key]]
            ok = all(j is not None and np.isfinite(j) for j in jnds)
            jnd = float(np.mean(jnds)) if ok else None
            weber[key] = None if jnd is None else jnd / key[2]
            thresholds.append(
                {
                    "subject": key[0],
                    "condition": key[1],
                    "standard": key[2],
                    "jnd": jnd,
                    "weber": weber[key],
                    "reason": None if ok else "a track has no estimate yet",
                }
            )
        present = sorted({k[1] for k in cells})
        order = [c for c in conditions or [] if c in present]
        order += [c for c in present if c not in order]
        return {
            "procedure": self.name,
            "tracks": rows,
            "thresholds": thresholds,
            "tests": paired_tests(
                weber, order, sorted({k[2] for k in cells}), sorted({k[0] for k in cells})
            ),
        }

    def report(self, result: dict[str, Any], unit: str) -> str:
        """The analysis's section of the report."""
        lines = [f"{self.name} tracks (standards and JNDs in {unit}):"]
        for r in result["tracks"]:
            extra = " ".join(
                f"{k} {v:.4g}"
                for k, v in r.items()
                if k not in ("subject", "condition", "standard", "side", "trials", "done")
                and isinstance(v, float)
            )
            lines.append(
                f"  {r['subject']:<10} {r['condition']:<10} standard {r['standard']:<8.4g} "
                f"{r['side']:<5} {r['trials']:>3} trials {extra}"
            )
        lines.append(f"{self.name} JNDs per subject, condition and standard:")
        for t in result["thresholds"]:
            res = t["reason"] if t["jnd"] is None else f"JND {t['jnd']:.4g} Weber {t['weber']:.3f}"
            lines.append(
                f"  {t['subject']:<10} {t['condition']:<10} standard {t['standard']:<8.4g} {res}"
            )
        lines += _test_lines(result["tests"], f"the {self.name} Weber fractions")
        return "\n".join(lines) + "\n"


# -- the registry ---------------------------------------------------------------------

_BUILTINS = {
    "constant_stimuli": "hapticd.experiment.procedures:ConstantStimuli",
    "staircase": "hapticd.experiment.procedures:StaircaseProcedure",
    "quest_plus": "hapticd.experiment.procedures:QuestPlusProcedure",
}
BUILTIN: frozenset[str] = frozenset(_BUILTINS)


def check_plugin(name: str, obj: Any) -> str | None:
    """Why an entry point's object is no procedure (None: it is one): a concrete
    ``Procedure`` subclass whose ``name`` is the entry point's and whose ``Settings`` is
    a pydantic model (or None)."""
    if not (isinstance(obj, type) and issubclass(obj, Procedure)):
        return f"expected a subclass of hapticd.experiment.procedure.Procedure, got {obj!r}"
    if obj.plans_ahead:
        return "a plugin procedure is adaptive (plans_ahead is constant stimuli's alone)"
    if obj.name != name:
        return f"its name is {obj.name!r}, the entry point's {name!r}: they must agree"
    if obj.Settings is not None and not (
        isinstance(obj.Settings, type) and issubclass(obj.Settings, BaseModel)
    ):
        return "its Settings must be a pydantic model (or None)"
    missing = sorted(getattr(obj, "__abstractmethods__", ()))
    if missing:
        return f"it does not implement {', '.join(missing)}"
    return None


_REGISTRY = Registry(GROUP, BUILTIN, check_plugin)


def _plugins() -> dict[str, Plugin]:
    return _REGISTRY.plugins()


def reload_plugins() -> None:
    """Find the installed procedures again (the next lookup does)."""
    _REGISTRY.reload()


def problems() -> list[Problem]:
    """The ``hapticd.procedures`` entry points refused, with why."""
    return _REGISTRY.problems()


def names() -> list[str]:
    """Every procedure's name: the built-ins, then the installed ones."""
    return [*_BUILTINS, *sorted(_plugins())]


def package_of(name: str) -> str:
    """The package a procedure comes from: hapticd for a built-in."""
    plugins = _plugins()
    return plugins[name].package if name in plugins else "hapticd"


class UnknownProcedureError(ValueError):
    """A procedure name that is neither built in nor installed (or a refused plugin's)."""


def get(name: str) -> type[Procedure]:
    """The procedure class named ``name``; UnknownProcedureError naming the known ones, or
    the refused plugin's package, entry point and why."""
    if name in _BUILTINS:
        import importlib

        module, _, attr = _BUILTINS[name].partition(":")
        return getattr(importlib.import_module(module), attr)
    plugins = _plugins()
    if name in plugins:
        return plugins[name].obj
    refused = _REGISTRY.refused(name)
    if refused is not None:
        raise UnknownProcedureError(f"procedure {name!r} is refused: {refused.message()}")
    known = ", ".join(repr(n) for n in names())
    raise UnknownProcedureError(
        f"unknown procedure {name!r}; the procedures: {known} (a lab's own: an entry point "
        f"of {GROUP}, docs/experiments.md)"
    )


def of(exp: Experiment) -> Procedure:
    """The procedure of ``exp``, with its settings."""
    cls = get(exp.procedure)
    return cls(cls.section(exp))


def from_design(design: Mapping[str, Any]) -> Procedure:
    """The procedure of a store's ``design`` (meta.design)."""
    return get(str(design.get("procedure") or "constant_stimuli")).from_design(design)


def listing() -> list[dict[str, Any]]:
    """Every procedure, built-in and installed, with its package; then the refused entry
    points (``problem``: why)."""
    rows: list[dict[str, Any]] = [
        {"name": n, "package": package_of(n), "problem": None} for n in names()
    ]
    rows += [
        {"name": p.name, "package": ", ".join(p.packages), "problem": p.message()}
        for p in problems()
    ]
    return rows
