"""``hapticd backends``, ``hapticd procedures`` and ``hapticd allocators``: what is
installed, built-in and from labs' packages (entry points), with the package each comes
from and the entry points refused; the warnings ``check`` and ``run`` print for refused
ones; ``hapticd allocators check NAME``, the allocators' conformance suite."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hapticd.cli.common import EXIT_BAD_INPUT, EXIT_ERROR, EXIT_OK


def _print(rows: list[dict[str, Any]], what: str, as_json: bool) -> int:
    if as_json:
        print(json.dumps(rows, indent=2))
    else:
        width = max(len(r["name"]) for r in rows)
        for r in rows:
            if r["problem"] is None:
                doc = f"  {r['doc']}" if r.get("doc") else ""
                print(f"{r['name']:<{width}}  {r['package']}{doc}")
        for r in rows:
            if r["problem"] is not None:
                print(f"hapticd: refused: {r['problem']}", file=sys.stderr)
    # A refused entry point is an installation to fix: said, and the exit code says so.
    return EXIT_BAD_INPUT if any(r["problem"] for r in rows) else EXIT_OK


def cmd_backends(args: argparse.Namespace) -> int:
    from hapticd_drivers import registry

    return _print(registry.listing(), "backends", args.json)


def cmd_procedures(args: argparse.Namespace) -> int:
    from hapticd.experiment import procedure

    return _print(procedure.listing(), "procedures", args.json)


def cmd_allocators(args: argparse.Namespace) -> int:
    """List the allocators, or (``check NAME``) run the conformance suite on one: each
    case on a line, exit 1 naming the cases that failed."""
    from hapticd.allocation import conformance, plugins

    if args.action is None:
        return _print(plugins.listing(), "allocators", args.json)
    try:
        f, claims = conformance.allocator(args.name)
    except KeyError:
        print(f"hapticd: allocators check: {plugins.unknown(args.name)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    outcomes = conformance.check(f, claims)
    compiled = None
    if plugins.get(args.name) is not None:  # what the tick will run: compiled, or why not
        compiled = plugins.native_address(plugins.handle(args.name))[1]
    if args.json:
        print(json.dumps([vars(o) for o in outcomes], indent=2))
    else:
        for o in outcomes:
            print(
                f"{'ok  ' if o.passed else 'FAIL'}  {o.case}"
                + (f": {o.detail}" if o.detail else "")
            )
        if plugins.get(args.name) is not None:
            print(
                "compiled with numba: the tick runs it compiled"
                if compiled is None
                else f"note: numba cannot compile it ({compiled}): the tick runs it as Python"
            )
    failed = [o.case for o in outcomes if not o.passed]
    if failed:
        print(f"hapticd: {args.name} fails {len(failed)} case(s): {', '.join(failed)}",
              file=sys.stderr)  # fmt: skip
        return EXIT_ERROR
    return EXIT_OK


def warn_backend_problems() -> None:
    """One warning line per refused ``hapticd.backends`` entry point (check, run)."""
    from hapticd_drivers import registry

    for p in registry.PROBLEMS:
        print(f"hapticd: warning: refused: {p.message()}", file=sys.stderr)


def warn_procedure_problems() -> None:
    """One warning line per refused ``hapticd.procedures`` entry point (experiment check
    and run)."""
    from hapticd.experiment import procedure

    for p in procedure.problems():
        print(f"hapticd: warning: refused: {p.message()}", file=sys.stderr)


def device_name(name: str) -> str:
    """``--device``'s type: a refused plugin's name is told with its package and entry
    point (an unknown name is argparse's invalid choice)."""
    from hapticd_drivers import registry

    refused = registry.problem(name)
    if refused is not None:
        raise argparse.ArgumentTypeError(refused.message())
    return name


def add_commands(sub: Any) -> None:
    for name, func, help_text in (
        ("backends", cmd_backends, "list the device backends, built-in and installed"),
        (
            "procedures",
            cmd_procedures,
            "list the psychophysical procedures, built-in and installed",
        ),
    ):
        p = sub.add_parser(
            name,
            help=help_text,
            description=f"{help_text.capitalize()}, each with the package it comes from; "
            "an installed entry point that is refused is told on stderr (exit 2).",
        )
        p.add_argument("--json", action="store_true", help="as JSON")
        p.set_defaults(func=func)
    text = "list the force allocators, or check one against the conformance suite"
    p = sub.add_parser(
        "allocators",
        help=text,
        description=f'{text.capitalize()} (docs/allocation.md, "Checking an allocator"): '
        "finite, bounded and continuous through rank changes, coincident and collinear "
        "contacts, forces from 1e-9 to 1e3 N, linear where claimed, NaN input refused.",
    )
    p.add_argument("--json", action="store_true", help="as JSON")
    p.set_defaults(func=cmd_allocators, action=None)
    checks = p.add_subparsers(dest="action")
    c = checks.add_parser("check", help="run the conformance suite on one allocator")
    c.add_argument("name", help="the allocator's name, as `hapticd allocators` lists it")
    c.add_argument("--json", action="store_true", help="each case as JSON")
