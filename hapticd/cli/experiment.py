"""hapticd experiment (check, plan, run, analyze, export) and hapticd study."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from hapticd import params
from hapticd.cli.common import EXIT_BAD_INPUT, EXIT_ERROR, EXIT_OK, _positive
from hapticd.daemon.build import build_devices, build_scene, load_trajectories
from hapticd.profile import ProfileError

log = logging.getLogger("hapticd")


def cmd_experiment_check(args: argparse.Namespace) -> int:
    """Validate an experiment file and its base profile; print the design."""
    from hapticd.experiment import ExperimentError, check_experiment, make_plan

    try:
        exp, profile = check_experiment(args.experiment)
        load_trajectories(profile)
        build_scene(profile.scene, profile)
        build_devices(profile, clock=lambda: 0.0)
    except (ExperimentError, ProfileError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    v, spec = exp.varied, params.PARAMS[exp.varied.param]
    total = exp.n_blocks * exp.trials_per_block
    if exp.adaptive is None:
        total = len(make_plan(exp, exp.subject_seed("example")))
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
        f"  procedure    {exp.procedure}\n"
        f"  conditions   {conds}\n"
        f"  trials       {_trials_line(exp, total)}\n"
        f"  interval     {exp.interval.order}, 'was the second {exp.interval.question}?', "
        f"at most {exp.interval.exploration_s:g} s, ends on {exp.interval.ends_on}\n"
        f"  breaks       {exp.n_breaks()} of {exp.breaks.duration_s:g} s\n"
        f"  duration     about {dur / 60:.0f} min per subject ({exp.trial_s():g} s per trial "
        "with every interval at its limit, and the breaks)"
    )
    return EXIT_OK


def _trials_line(exp: Any, total: int) -> str:
    """The design's trials, as ``experiment check`` prints them."""
    st = exp.staircase
    if exp.quest_plus is not None:
        q = exp.quest_plus
        return (
            f"QUEST+, {exp.n_blocks} tracks interleaved (one per condition and standard), "
            f"{q.trials} trials each on {q.n_stimuli} comparisons from {q.min_ratio:g} to "
            f"{q.max_ratio:g} x the standard: {exp.n_blocks * q.trials} per subject"
        )
    if st is None:
        return (
            f"{exp.comparisons} comparisons x {exp.repetitions} repetitions per standard and "
            f"condition; {exp.trials_per_block} per block, {exp.n_blocks} blocks, {total} per "
            "subject"
        )
    return (
        f"staircase {st.rule} (converges on {st.target_share:.1%} correct), {exp.n_blocks} "
        f"tracks interleaved ({len(st.sign_list())} per condition and standard), each ending "
        f"after {st.stop_reversals} reversals or {st.max_trials} trials: at most "
        f"{exp.n_blocks * st.max_trials} per subject"
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
    plan = make_plan(exp, seed)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(plan[0].as_dict()), lineterminator="\n")
    writer.writeheader()
    writer.writerows(t.as_dict() for t in plan)
    if args.csv is None:
        sys.stdout.write(buf.getvalue())
        return EXIT_OK
    try:
        args.csv.write_text(buf.getvalue())
    except OSError as exc:
        print(f"hapticd: cannot write: {exc}", file=sys.stderr)
        return EXIT_ERROR
    print(f"{args.csv}: {len(plan)} trials of subject {args.subject!r} (seed {seed})")
    return EXIT_OK


def cmd_experiment_analyze(args: argparse.Namespace) -> int:
    """Fits, group means and paired t-tests from trial stores."""
    from hapticd.experiment import analyze as ana
    from hapticd.experiment.store import StoreError, open_for_analysis

    trials: list[dict[str, Any]] = []
    failed: list[dict[str, Any]] = []
    first: dict[str, Any] | None = None
    try:
        for db in args.db:
            meta, rows = open_for_analysis(db, None)
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
    from hapticd.experiment import ExperimentError

    try:
        if design.get("procedure") == "quest_plus" and design.get("quest_plus"):
            result["quest_plus"] = ana.analyze_quest(
                trials, design["quest_plus"], point, design.get("conditions")
            )
    except ExperimentError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    param = args.param or design.get("param", "stimulus")
    unit = args.unit or design.get("unit", "SI units")
    print(
        f"hapticd experiment analyze: experiment {first.get('experiment')!r}, varied {param} "
        f"({unit}), {len(trials)} complete trials"
    )
    if failed:  # left out of every fit: said, and kept in the JSON
        result["failed"] = ana.failed_trials(failed)
        print(ana.format_failed(result["failed"]), end="")
    if design.get("procedure") == "staircase" and design.get("staircase"):
        result["staircases"] = ana.analyze_staircases(
            trials, design["staircase"], design.get("conditions")
        )
    print(ana.format_report(result, unit), end="")
    if "staircases" in result:
        print(ana.format_staircases(result["staircases"], unit), end="")
    if "quest_plus" in result:
        print(ana.format_quest(result["quest_plus"], unit), end="")
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
    """A trial store as a tidy CSV, one row per trial (hapticd.experiment.export)."""
    import csv

    from hapticd.experiment import export
    from hapticd.experiment.store import StoreError

    status = None if args.all else "complete"
    try:
        if args.csv is None:
            rows = export.trial_rows(args.db, status=status)
            writer = csv.DictWriter(sys.stdout, fieldnames=export.NAMES, lineterminator="\n")
            writer.writeheader()
            writer.writerows(rows)
            return EXIT_OK
        n = export.write_csv(args.db, args.csv, status=status)
    except StoreError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:
        print(f"hapticd: cannot write: {exc}", file=sys.stderr)
        return EXIT_ERROR
    what = "trials" if args.all else "complete trials"
    print(f"{args.csv}: {n} {what} of {args.db}, one row each")
    return EXIT_OK


def cmd_experiment_run(args: argparse.Namespace) -> int:
    """Run (or resume) one subject on a running daemon (hapticd.experiment.runner)."""
    from hapticd.experiment import ExperimentError, check_experiment
    from hapticd.experiment import runner as rn

    try:
        exp, _ = check_experiment(args.experiment)
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
            observer=args.observer, options=opts,
        )  # fmt: skip
    except (ExperimentError, ProfileError, rn.StoreError, ValueError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except rn.TrialAbortedError as exc:
        why = "interrupted (Ctrl-C)" if exc.interrupted else str(exc)
        print(
            f"hapticd: {why}: the trial in progress is stored incomplete, the answered ones "
            f"are kept; continue with --resume",
            file=sys.stderr,
        )
        return 130 if exc.interrupted else EXIT_ERROR
    except rn.RunnerError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("hapticd: interrupted between trials; continue with --resume", file=sys.stderr)
        return 130
    print(f"hapticd: {done} trial(s) answered; {left} left" + ("" if left else ": done"))
    return EXIT_OK


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


def _add_experiment(sub: Any) -> None:
    """The experiment subcommand: check a design, analyze trial stores."""
    exp = sub.add_parser("experiment", help="JND experiments: check a design, analyze trials")
    esub = exp.add_subparsers(dest="experiment_command", required=True)
    chk = esub.add_parser("check", help="validate an experiment file and its profile")
    chk.add_argument("experiment", type=Path)
    chk.set_defaults(func=cmd_experiment_check)
    _add_experiment_run(esub)
    pl = esub.add_parser("plan", help="one subject's trial plan as CSV")
    pl.add_argument("experiment", type=Path)
    pl.add_argument("--subject", required=True, help="the subject's id (its seed derives from it)")
    pl.add_argument("--seed", type=int, help="use this seed instead of the subject's")
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
    ex = esub.add_parser("export", help="a trial store as a tidy CSV, one row per trial")
    ex.add_argument("db", type=Path, help="the trial store")
    ex.add_argument("--csv", type=Path, metavar="OUT", help="write here (default: stdout)")
    ex.add_argument(
        "--all", action="store_true", help="incomplete and failed trials too (status column)"
    )
    ex.set_defaults(func=cmd_experiment_export)


def _add_study(sub: Any) -> None:
    """hapticd study: model-observer subjects in parallel (hapticd.experiment.study)."""

    def run(args: argparse.Namespace) -> int:
        from hapticd.experiment.study import cmd_study

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
