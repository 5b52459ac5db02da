"""``hapticd backends`` and ``hapticd procedures``: what is installed, built-in and from
labs' packages (entry points), with the package each comes from and the entry points
refused; and the warnings ``check`` and ``run`` print for refused ones."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hapticd.cli.common import EXIT_BAD_INPUT, EXIT_OK


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
