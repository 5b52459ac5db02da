"""hapticd experiment (check, plan, run, analyze, export) and hapticd study."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from hapticd import params
from hapticd.cli.common import EXIT_BAD_INPUT, EXIT_ERROR, EXIT_OK, _positive
from hapticd.daemon.build import build_devices, build_scene, load_trajectories
from hapticd.profile import ProfileError

log = logging.getLogger("hapticd")


def cmd_experiment_check(args: argparse.Namespace) -> int:
    """Validate an experiment file and its base profile; print the design."""
    from hapticd.cli.plugins import warn_backend_problems, warn_procedure_problems
    from hapticd.experiment import ExperimentError, check_experiment, make_plan

    warn_procedure_problems()
    warn_backend_problems()
    try:
        exp, profile = check_experiment(args.experiment, args.profile)
        load_trajectories(profile)
        build_scene(profile.scene, profile)
        build_devices(profile, clock=lambda: 0.0)
        if args.meta is not None:
            exp.check_metadata(parse_meta(args.meta))
    except (ExperimentError, ProfileError, ValueError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    v, spec = exp.varied, params.PARAMS[exp.varied.param]
    total = exp.n_blocks * exp.trials_per_block
    if exp.proc.plans_ahead:
        total = len(make_plan(exp, exp.subject_seed("example"), 0))
    dur = exp.duration_s()
    conds = ", ".join(
        f"{c.name} ({', '.join(f'{k}={val}' for k, val in c.values().items())})"
        for c in exp.conditions
    )
    print(
        f"{args.experiment}: OK: experiment {exp.name!r} on profile {profile.name!r} "
        f"({exp.profile_path()})\n"
        f"  varied       {v.param} ({spec.unit}): standards "
        f"{', '.join(f'{s:g}' for s in v.standards)}"
        + (f"; ratios {', '.join(f'{r:g}' for r in v.ratios)}" if v.ratios else "")
        + "\n"
        f"  procedure    {exp.procedure} ({_package(exp.procedure)})\n"
        f"  conditions   {conds}\n"
        f"  trials       {_trials_line(exp, total)}\n"
        f"  interval     {exp.interval.order}, 'was the second {exp.interval.question}?', "
        f"at most {exp.interval.exploration_s:g} s, ends on {exp.interval.ends_on}\n"
        f"  breaks       {exp.n_breaks()} of {exp.breaks.duration_s:g} s\n"
        f"  duration     about {dur / 60:.0f} min per subject ({exp.trial_s():g} s per trial "
        "with every interval at its limit, and the breaks)\n"
        f"  metadata     {_metadata_line(exp)}"
    )
    if exp.procedure == "staircase" and exp.staircase is not None:
        _staircase_bias(args.experiment, exp.staircase)
    if exp.randomization.counterbalance != "none":
        print(f"  orders       {_orders_line(exp)}")
        if exp.subjects:
            warning = _imbalance(exp, _orders(exp, len(exp.subjects)))
            if warning:
                print(f"hapticd: warning: {args.experiment}: subjects: {warning}", file=sys.stderr)
    return EXIT_OK


def parse_meta(items: list[str] | None) -> dict[str, str]:
    """``--meta KEY=VALUE`` items as {KEY: VALUE}; ValueError for an item without
    ``=`` or a key given twice."""
    out: dict[str, str] = {}
    for item in items or ():
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ValueError(f"--meta {item!r}: expected KEY=VALUE, e.g. experimenter=AB")
        if key in out:
            raise ValueError(f"--meta {key}: given twice")
        out[key] = value
    return out


def _metadata_line(exp: Any) -> str:
    """The session metadata keys a run takes (``--meta KEY=VALUE``), required ones
    marked."""
    keys = exp.metadata.keys
    return (
        ", ".join(
            k + (" (required)" if k in keys and keys[k].required else "")
            for k in exp.metadata.names()
        )
        + " (--meta KEY=VALUE)"
    )


def _cycle(exp: Any) -> int:
    """Subjects per balanced cycle of the design's counterbalancing (0: none)."""
    from hapticd.experiment.plan import williams_rows

    scheme = exp.randomization.counterbalance
    if scheme == "latin_square":
        return len(williams_rows(len(exp.conditions)))
    return 2 if scheme == "abba" else 0


def _orders_line(exp: Any) -> str:
    """What the counterbalancing does, for ``experiment check``."""
    n, scheme, cycle = len(exp.conditions), exp.randomization.counterbalance, _cycle(exp)
    what = (
        f"latin_square: subject k gets row k of a balanced (Williams) Latin square of {n} "
        f"conditions, {cycle} rows"
        + (f" ({n} is odd: a balanced design needs 2 x {n})" if n % 2 else "")
        if scheme == "latin_square"
        else "abba: each condition in two halves, A B B A, and B A A B every other subject"
    )
    listed = f"{len(exp.subjects)} subjects listed" if exp.subjects else "no subjects listed"
    return f"{what}; balanced for every {cycle} subjects; {listed} (hapticd experiment orders)"


def _subject_ids(exp: Any, n: int) -> list[str]:
    """The first ``n`` subjects: the file's, then s01.. style ids for the rest."""
    return list(exp.subjects[:n]) + [f"s{k + 1:02d}" for k in range(len(exp.subjects), n)]


def _orders(exp: Any, n: int) -> list[list[str]]:
    """The condition orders of the first ``n`` subjects (``_subject_ids``)."""
    import numpy as np

    from hapticd.experiment.plan import condition_order

    return [
        condition_order(exp, np.random.default_rng(exp.subject_seed(sid)), k)
        for k, sid in enumerate(_subject_ids(exp, n))
    ]


def _imbalance(exp: Any, orders: list[list[str]]) -> str | None:
    """How far ``orders`` are from balanced (None when balanced): the spreads and the
    number of subjects that would balance them."""
    from hapticd.experiment.plan import balance

    bal = balance(orders, [c.name for c in exp.conditions])
    if bal.balanced:
        return None
    cycle = _cycle(exp)
    fix = f"; a multiple of {cycle} subjects balances it" if cycle else ""
    return (
        f"{len(orders)} subjects are not balanced: the counts of the conditions at a "
        f"position differ by up to {bal.position_spread} (max - min), the counts of ordered "
        f"pairs as neighbours by up to {bal.pair_spread}{fix}"
    )


def cmd_experiment_orders(args: argparse.Namespace) -> int:
    """The condition orders of N subjects and how balanced they are."""
    from hapticd.experiment import ExperimentError, load_experiment
    from hapticd.experiment.plan import balance

    try:
        exp = load_experiment(args.experiment)
        n = args.subjects or len(exp.subjects)
        if not exp.proc.plans_ahead:
            raise ExperimentError(
                f"{args.experiment}: procedure {exp.procedure} interleaves its tracks: "
                "there is no block order to print"
            )
        if n < 1:
            raise ExperimentError(
                f"{args.experiment}: "
                + (
                    "--subjects: expected 1 or more"
                    if args.subjects
                    else "the file lists no subjects: give --subjects N"
                )
            )
        orders = _orders(exp, n)
    except ExperimentError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    names = [c.name for c in exp.conditions]
    ids = _subject_ids(exp, n)
    width = max(len(x) for x in [*ids, *names, "subject"])
    print(
        f"experiment {exp.name}: counterbalance {exp.randomization.counterbalance}, "
        f"{len(names)} conditions, {n} subjects"
    )
    print(f"{'subject':<{width}}  index  order")
    for k, (sid, order) in enumerate(zip(ids, orders, strict=True)):
        print(f"{sid:<{width}}  {k:>5}  {' '.join(order)}")
    bal = balance(orders, names)
    length = len(orders[0])
    print("each condition's count at each position:")
    print(f"{'':<{width}}  " + " ".join(f"{p + 1:>3}" for p in range(length)))
    for c, row in zip(names, bal.positions, strict=True):
        print(f"{c:<{width}}  " + " ".join(f"{x:>3}" for x in row))
    print("carryover: how often the column's condition directly follows the row's:")
    print(f"{'':<{width}}  " + " ".join(f"{c:>{width}}" for c in names))
    for c, row in zip(names, bal.carryover, strict=True):
        print(f"{c:<{width}}  " + " ".join(f"{x:>{width}}" for x in row))
    warning = _imbalance(exp, orders)
    if warning is None:
        print("balanced: the same count at every position, and for every ordered pair")
    else:
        print(f"hapticd: warning: {warning}", file=sys.stderr)
    return EXIT_OK


def _staircase_bias(path: Any, st: Any) -> None:
    """The staircase's simulated JND against its point, and a warning when it is off
    (hapticd.experiment.bias)."""
    from hapticd.experiment import bias

    rows, warning = bias.check(st)
    print(
        f"  bias         simulated JND vs its {st.target_share:.1%} point: {bias.summary(rows)} "
        f"({bias.CHECK_SUBJECTS} subjects each; scripts/staircase_bias.py)"
    )
    if warning:
        print(f"hapticd: warning: {path}: staircase: {warning}", file=sys.stderr)


def _package(name: str) -> str:
    from hapticd.experiment import procedure

    return f"from package {procedure.package_of(name)}"


def _trials_line(exp: Any, total: int) -> str:
    """The design's trials, as ``experiment check`` prints them."""
    if not exp.proc.plans_ahead:
        return exp.proc.describe(exp)
    return (
        f"{exp.comparisons} comparisons x {exp.repetitions} repetitions per standard and "
        f"condition; {exp.trials_per_block} per block, {exp.n_blocks} blocks, {total} per "
        "subject"
    )


def cmd_experiment_plan(args: argparse.Namespace) -> int:
    """One subject's trial plan as CSV (stdout or --csv)."""
    import csv
    import io

    from hapticd.experiment import ExperimentError, load_experiment, make_plan

    try:
        exp = load_experiment(args.experiment)
    except ExperimentError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    seed = exp.subject_seed(args.subject) if args.seed is None else args.seed
    if exp.proc.plans_ahead:
        try:
            index = exp.subject_index(args.subject, args.subject_index)
        except ExperimentError as exc:
            print(f"hapticd: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        rows = [t.as_dict() for t in make_plan(exp, seed, index)]
        what = f"{len(rows)} trials"
    else:  # the comparisons follow the answers: the tracks, each at most max_trials long
        rows = _adaptive_tracks(exp)
        what = (
            f"{len(rows)} {exp.procedure} tracks, at most "
            f"{sum(r['max_trials'] for r in rows)} trials"
        )
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    if args.csv is None:
        sys.stdout.write(buf.getvalue())
        return EXIT_OK
    try:
        args.csv.write_text(buf.getvalue())
    except OSError as exc:
        print(f"hapticd: cannot write: {exc}", file=sys.stderr)
        return EXIT_ERROR
    print(f"{args.csv}: {what} of subject {args.subject!r} (seed {seed})")
    return EXIT_OK


def _adaptive_tracks(exp: Any) -> list[dict[str, Any]]:
    """The tracks of an adaptive design, in the store's block order: condition, standard,
    side, the first comparison (the varied parameter's SI unit) and the most trials."""
    proc = exp.proc
    return [
        {
            "block": t.index,
            "condition": t.condition,
            "standard": t.standard,
            "side": getattr(t, "side", "above"),
            "first_comparison": float(f"{proc.comparison(t):.12g}"),
            "max_trials": proc.max_trials,
        }
        for t in proc.tracks(exp)
    ]


@contextlib.contextmanager
def _store_warnings() -> Iterator[None]:
    """Each StoreWarning (a damaged store read anyway) and ExportWarning (recordings not
    read) raised in the block printed to stderr as one line, at once."""
    from hapticd.experiment.export import ExportWarning
    from hapticd.experiment.store import StoreWarning

    def show(message: Any, category: type[Warning], *args: Any, **kwargs: Any) -> None:
        if issubclass(category, StoreWarning | ExportWarning):
            print(f"hapticd: warning: {message}", file=sys.stderr)
        else:
            shown(message, category, *args, **kwargs)

    with warnings.catch_warnings():
        warnings.simplefilter("always", StoreWarning)
        warnings.simplefilter("always", ExportWarning)
        shown = warnings.showwarning
        warnings.showwarning = show
        yield


def cmd_experiment_analyze(args: argparse.Namespace) -> int:
    """Fits, group means and paired t-tests from trial stores."""
    from hapticd.experiment import analyze as ana
    from hapticd.experiment.store import StoreError, open_for_analysis

    trials: list[dict[str, Any]] = []
    failed: list[dict[str, Any]] = []
    first: dict[str, Any] | None = None
    try:
        for db in args.db:
            with _store_warnings():
                meta, rows = open_for_analysis(db, None)
            rows = ana.session_rows(rows)  # practice trials are never analysed
            failed += [r for r in rows if r["status"] == "failed"]
            rows = [r for r in rows if r["status"] == "complete"]
            if first is not None and meta.get("experiment_hash") != first.get("experiment_hash"):
                raise StoreError(
                    f"{db}: holds experiment {meta.get('experiment')!r} with another file hash "
                    f"than {args.db[0]} ({first.get('experiment')!r}): not analysed together"
                )
            first = first or meta
            trials += rows
    except StoreError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if not trials:
        print(f"hapticd: {', '.join(map(str, args.db))}: no complete trials", file=sys.stderr)
        return EXIT_BAD_INPUT
    assert first is not None
    design = first.get("design") or {}
    point = args.jnd_point or design.get("jnd_point", 0.75)
    try:
        result = ana.analyze(
            trials,
            conditions=design.get("conditions"),
            n_boot=args.boot,
            seed=args.seed,
            jnd_point=point,
            fitter=args.fitter,
        )
    except ImportError:
        print(
            "hapticd: --fitter psignifit needs psignifit: pip install 'hapticd[psignifit]'",
            file=sys.stderr,
        )
        return EXIT_ERROR
    from hapticd.experiment import ExperimentError, procedure

    try:
        proc = procedure.from_design(design)
        section = (
            None
            if proc.plans_ahead
            else proc.analyze(trials, conditions=design.get("conditions"), jnd_point=point)
        )
    except procedure.UnknownProcedureError as exc:
        # A store of a procedure not installed here: its fit still stands, its section not.
        print(f"hapticd: warning: {exc}: its own section is left out", file=sys.stderr)
        proc, section = procedure.get("constant_stimuli")(()), None
    except (ExperimentError, ValueError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    if section is not None:
        result[proc.result_key or proc.name] = section
    param = args.param or design.get("param", "stimulus")
    unit = args.unit or design.get("unit", "SI units")
    print(
        f"hapticd experiment analyze: experiment {first.get('experiment')!r}, varied {param} "
        f"({unit}), {len(trials)} complete trials"
    )
    if failed:  # left out of every fit: said, and kept in the JSON
        result["failed"] = ana.failed_trials(failed)
        print(ana.format_failed(result["failed"]), end="")
    print(ana.format_report(result, unit), end="")
    if section is not None:
        print(proc.report(section, unit), end="")
    try:
        if args.json is not None:
            args.json.write_text(json.dumps(ana.to_json(result), indent=1, allow_nan=False) + "\n")
        if args.plots is not None:
            try:
                paths = ana.plot(result, args.plots, param=param, unit=unit)
                if "staircases" in result:
                    paths += ana.plot_staircases(
                        result["staircases"], args.plots, param=param, unit=unit
                    )
                for path in paths:
                    print(f"plot: {path}")
            except ImportError:
                print("hapticd: --plots needs matplotlib: pip install matplotlib", file=sys.stderr)
                return EXIT_ERROR
    except OSError as exc:
        print(f"hapticd: cannot write: {exc}", file=sys.stderr)
        return EXIT_ERROR
    return EXIT_OK


def cmd_experiment_export(args: argparse.Namespace) -> int:
    """A trial store as a tidy table, one row per trial, as CSV, Parquet or MAT
    (hapticd.experiment.export); with --samples, each interval's samples too."""
    from hapticd.experiment.store import StoreError
    from hapticd.experiment.tables import TableFormatError
    from hapticd.recording.format import RecordingError

    status = None if args.all else "complete"
    try:
        with _store_warnings():
            return _export(args, status)
    except (StoreError, TableFormatError, RecordingError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ImportError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        print(f"hapticd: cannot write: {exc}", file=sys.stderr)
        return EXIT_ERROR


def _default_format(db: Path) -> str:
    """The store's experiment's ``export.format`` (csv for a store made before it)."""
    from hapticd.experiment.store import open_for_analysis

    meta, _ = open_for_analysis(db, "complete")
    return str(meta["design"].get("export_format") or "csv")


def _export(args: argparse.Namespace, status: str | None) -> int:
    """``cmd_experiment_export``'s work: the table to stdout (CSV) or to ``--out``, and
    the samples to ``--samples``."""
    from hapticd.experiment import export, tables

    to_file = args.out is not None or args.samples is not None
    # --csv and stdout are CSV; a file's format is the experiment file's by default.
    if args.format is None and to_file and args.csv is None:
        fmt = tables.check_format(_default_format(args.db))
    else:
        fmt = tables.check_format(args.format or "csv")
    out = args.out or args.csv
    if args.csv is not None and args.out is not None:
        raise tables.TableFormatError("give --out or --csv, not both")
    if args.csv is not None and fmt != "csv":
        raise tables.TableFormatError(f"--csv writes CSV; for {fmt} give --out FILE")
    read_recs = not args.no_recordings
    what = "trials" if args.all else "complete trials"
    if out is None and args.samples is None:
        if fmt != "csv":
            raise tables.TableFormatError(f"--format {fmt} writes a file: give --out FILE")
        table = export.trials_table(
            args.db, status=status, recordings=read_recs, recordings_dir=args.recordings
        )
        tables.write_csv(table, sys.stdout)
        return EXIT_OK
    if out is not None:
        n = export.write_trials(
            args.db, out, fmt, status=status, recordings=read_recs,
            recordings_dir=args.recordings,
        )  # fmt: skip
        print(f"{out}: {n} {what} of {args.db}, one row each ({fmt})")
    if args.samples is not None:
        paths = export.write_samples(
            args.db, args.samples, fmt, status=status, recordings_dir=args.recordings
        )
        print(f"{args.samples}: {len(paths)} intervals' samples of {args.db}, one {fmt} each")
    return EXIT_OK


def cmd_experiment_run(args: argparse.Namespace) -> int:
    """Run (or resume) one subject on a running daemon (hapticd.experiment.runner)."""
    from hapticd.cli.plugins import warn_procedure_problems
    from hapticd.experiment import ExperimentError, check_experiment
    from hapticd.experiment import runner as rn

    warn_procedure_problems()
    try:
        exp, _ = check_experiment(args.experiment, args.profile)
        standards = None if args.standards is None else rn.float_list(args.standards)
        exp = rn.reduced(
            exp, standards=standards, repetitions=args.repetitions, break_s=args.break_s
        )
        opts = rn.RunOptions(
            socket=args.socket,
            keys_fd=None if args.no_keys else rn.stdin_fd(),
            person=rn.PersonOptions(
                release_wait_s=args.release_wait_s,
                touch_wait_s=args.touch_wait_s,
                answer_wait_s=args.answer_wait_s,
                buttons=rn.parse_buttons(args.buttons),
            ),
        )
        db = args.db or Path(f"{exp.name}-trials.db")
        done, left = rn.run_experiment(
            exp, args.subject, db, seed=args.seed, resume=args.resume,
            observer=args.observer, options=opts, subject_index=args.subject_index,
            metadata=parse_meta(args.meta),
        )  # fmt: skip
    except (ExperimentError, ProfileError, rn.StoreError, ValueError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except rn.TrialAbortedError as exc:
        print(
            f"hapticd: {exc}: the trial in progress is stored incomplete, the answered ones "
            f"are kept; continue with --resume",
            file=sys.stderr,
        )
        return 128 + exc.signum if exc.interrupted else EXIT_ERROR
    except rn.RunnerError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM or SIGHUP between trials
        print(
            f"hapticd: interrupted ({rn.signal_name(exc)}) between trials; continue with --resume",
            file=sys.stderr,
        )
        return 128 + getattr(exc, "signum", 2)
    print(f"hapticd: {done} trial(s) answered; {left} left" + ("" if left else ": done"))
    return EXIT_OK


def _add_profile_option(parser: Any) -> None:
    parser.add_argument(
        "--profile",
        type=Path,
        metavar="PROFILE",
        help="run the design on this base profile (a rig's) instead of the one the "
        "experiment file names; checked the same way",
    )


def _add_experiment_run(esub: Any) -> None:
    run = esub.add_parser(
        "run",
        help="run a subject on a running daemon (answers: keys 1/n or 2/y, buttons, browser)",
    )
    run.add_argument("experiment", type=Path)
    run.add_argument("--subject", required=True, help="the subject's id (names the recordings)")
    run.add_argument("--db", type=Path, help="the trial store (default: NAME-trials.db here)")
    run.add_argument("--seed", type=int, help="use this seed instead of the subject's")
    run.add_argument("--repetitions", type=int, help="a reduced design: repetitions")
    run.add_argument("--standards", metavar="LIST", help="a reduced design: e.g. 60 or 30,90")
    run.add_argument(
        "--break-s", type=float, metavar="S", help="a reduced design: each break lasts S s"
    )
    run.add_argument("--resume", action="store_true", help="continue the subject's stored plan")
    _add_session_args(run)
    _add_profile_option(run)
    run.add_argument("--socket", type=Path, help="the daemon's control socket")
    run.add_argument(
        "--observer",
        default="person",
        help="who answers: person (at a running daemon; the default) or model (the simulated "
        "subject, in this process, no daemon)",
    )
    run.add_argument("--buttons", metavar="MAP", help="response labels as answers: L=yes,L=no")
    run.add_argument("--no-keys", action="store_true", help="read no answers from the terminal")
    from hapticd.experiment.runner import PersonOptions

    waits = PersonOptions()
    for flag, default, what in (
        ("--release-wait-s", waits.release_wait_s, "for the object to be released before a change"),
        ("--touch-wait-s", waits.touch_wait_s, "for the first touch of an interval"),
        ("--answer-wait-s", waits.answer_wait_s, "for an answer"),
    ):
        run.add_argument(
            flag,
            type=_positive,
            default=default,
            metavar="S",
            help=f"how long a person's run waits {what} before it stops, the trial stored "
            f"incomplete (default {default:g} s)",
        )
    run.set_defaults(func=cmd_experiment_run)


def _add_session_args(parser: Any, *, index: bool = True) -> None:
    """--meta (and --subject-index): a session's metadata and counterbalancing place."""
    parser.add_argument(
        "--meta",
        action="append",
        metavar="KEY=VALUE",
        help="session metadata, stored with the session and exported: session, "
        "experimenter, notes or a key the file declares (metadata.keys); repeat it",
    )
    if index:
        parser.add_argument(
            "--subject-index",
            type=int,
            metavar="K",
            help="the subject's place in a counterbalanced design, 0-based (default: its "
            "place in the file's subjects)",
        )


def _add_experiment(sub: Any) -> None:
    """The experiment subcommand: check a design, analyze trial stores."""
    exp = sub.add_parser("experiment", help="JND experiments: check a design, analyze trials")
    esub = exp.add_subparsers(dest="experiment_command", required=True)
    chk = esub.add_parser("check", help="validate an experiment file and its profile")
    chk.add_argument("experiment", type=Path)
    _add_session_args(chk, index=False)
    _add_profile_option(chk)
    chk.set_defaults(func=cmd_experiment_check)
    orders = esub.add_parser(
        "orders", help="the condition orders of N subjects and how balanced they are"
    )
    orders.add_argument("experiment", type=Path)
    orders.add_argument(
        "--subjects",
        type=int,
        metavar="N",
        help="this many subjects (default: the file's subjects list)",
    )
    orders.set_defaults(func=cmd_experiment_orders)
    _add_experiment_run(esub)
    pl = esub.add_parser("plan", help="one subject's trial plan as CSV")
    pl.add_argument("experiment", type=Path)
    pl.add_argument("--subject", required=True, help="the subject's id (its seed derives from it)")
    pl.add_argument("--seed", type=int, help="use this seed instead of the subject's")
    pl.add_argument(
        "--subject-index",
        type=int,
        metavar="K",
        help="the subject's place in a counterbalanced design (default: in the file's subjects)",
    )
    pl.add_argument("--csv", type=Path, metavar="OUT", help="write here (default: stdout)")
    pl.set_defaults(func=cmd_experiment_plan)
    ana = esub.add_parser(
        "analyze",
        help="psychometric fits, Weber fractions and paired t-tests from trial stores",
    )
    ana.add_argument("db", type=Path, nargs="+", help="trial store(s) of one experiment")
    ana.add_argument("--json", type=Path, metavar="OUT", help="write the results as JSON")
    ana.add_argument("--plots", type=Path, metavar="DIR", help="write the plots here")
    ana.add_argument("--boot", type=int, default=1000, help="bootstrap refits per fit")
    ana.add_argument("--seed", type=int, default=0, help="bootstrap seed")
    ana.add_argument(
        "--param", help="the varied parameter, for labels (default: the store's design)"
    )
    ana.add_argument("--unit", help="its unit, for labels (default: the store's design)")
    ana.add_argument(
        "--fitter",
        choices=("ml", "psignifit"),
        default="ml",
        help="ml: hapticd's maximum-likelihood fit (the default); psignifit: psignifit 4's "
        "Bayesian fit (pip: hapticd[psignifit])",
    )
    ana.add_argument(
        "--jnd-point",
        type=float,
        choices=(0.75, 0.84),
        help="the JND is x(P) - x(0.5) (default: the experiment's analysis.jnd_point, 0.75)",
    )
    ana.set_defaults(func=cmd_experiment_analyze)
    ex = esub.add_parser(
        "export", help="a trial store as a tidy table (CSV, Parquet, MAT), one row per trial"
    )
    ex.add_argument("db", type=Path, help="the trial store")
    ex.add_argument(
        "--format",
        metavar="FORMAT",
        help="csv, parquet (pip: hapticd[export]) or mat (MATLAB); default: the experiment "
        "file's export.format, csv",
    )
    ex.add_argument("--out", type=Path, metavar="FILE", help="write here (default: CSV to stdout)")
    ex.add_argument("--csv", type=Path, metavar="OUT", help="write CSV here (--format csv --out)")
    ex.add_argument(
        "--samples",
        type=Path,
        metavar="DIR",
        help="also write each interval's samples from its recording, one file per interval",
    )
    ex.add_argument(
        "--recordings",
        type=Path,
        metavar="DIR",
        help="look here (by file name) for recordings not at their stored path",
    )
    ex.add_argument(
        "--no-recordings",
        action="store_true",
        help="read no recording: the interval and force columns stay empty (fast)",
    )
    ex.add_argument(
        "--all", action="store_true", help="incomplete and failed trials too (status column)"
    )
    ex.set_defaults(func=cmd_experiment_export)


def _add_study(sub: Any) -> None:
    """hapticd study: model-observer subjects in parallel (hapticd.experiment.study)."""

    def run(args: argparse.Namespace) -> int:
        from hapticd.cli.plugins import warn_procedure_problems
        from hapticd.experiment.study import cmd_study

        warn_procedure_problems()
        return cmd_study(args)

    st = sub.add_parser("study", help="run simulated subjects (the model observer) in parallel")
    st.add_argument("experiment", type=Path)
    st.add_argument("--observers", type=int, required=True, metavar="N", help="subjects s01..")
    st.add_argument("--db", type=Path, help="trial store (default: study-EXPERIMENT.sqlite)")
    st.add_argument("--seed", type=int, help="derive each subject's seed from this")
    st.add_argument("--workers", type=int, metavar="K", help="processes (default: the cores)")
    st.add_argument("--standards", type=lambda s: [float(x) for x in s.split(",")], metavar="A,B")
    st.add_argument("--repetitions", type=int, metavar="N", help="per comparison (reduced)")
    st.add_argument("--scheduler", metavar="ADDRESS", help="a Dask scheduler (pip: hapticd[dask])")
    st.add_argument("--quiet", action="store_true", help="no progress bar")
    st.add_argument(
        "--judgement",
        metavar="NAME",
        help="how the model observer judges: a name in hapticd.experiment.observer.JUDGEMENTS "
        "(default weber; docs/experiments.md, observer variants)",
    )
    st.add_argument(
        "--actuation-angle-deg",
        type=float,
        metavar="A",
        help="tilt each finger's one actuated direction A degrees up from the grasp line "
        "(default: the profile's own)",
    )
    st.set_defaults(func=run)
