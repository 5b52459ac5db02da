"""What every command shares: exit codes, option parsers, --set, progress and log options."""

from __future__ import annotations

import argparse
import logging
import math
import sys

log = logging.getLogger("hapticd")

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_BAD_INPUT = 2
EXIT_FAULT = 3
EXIT_PIPE = 128 + 13  # what a shell reports for a program ended by SIGPIPE
# Ctrl-C before a run began (nothing was opened): what a shell reports for SIGINT. A Ctrl-C
# during a run is an orderly stop instead, whose exit code is the run's.
EXIT_INTERRUPTED = 128 + 2


class OutputClosed(Exception):  # noqa: N818  (not an error: the reader has gone)
    """Standard output was closed by its reader (``hapticd ... | head -1``). Not an
    OSError, so the commands' handlers of socket errors let it through to ``main``."""


def emit(text: str) -> None:
    """Print ``text`` and flush; OutputClosed if the reader of stdout has gone."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        raise OutputClosed from None


def stdout_closed() -> bool:
    """Whether stdout is a pipe or socket whose reader has gone (POLLERR on its end)."""
    import select

    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        return any(ev & select.POLLERR for _, ev in poller.poll(0))
    except (OSError, ValueError, AttributeError):
        return False


def _fmt(v: float | None, unit: str = "") -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:g}{unit}"


def _overrides(args: argparse.Namespace) -> list[str]:
    """The ``--set KEY=VALUE`` values of ``run`` and ``check`` (none for other callers)."""
    return list(getattr(args, "set", None) or [])


def _add_set_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override one profile value (repeatable): KEY a dotted key path, list items by "
        "index or name (scene.object.stiffness_n_per_m=90, fingers[thumb].device.max_force_n=5), "
        "VALUE a YAML scalar or list; validated with the profile",
    )


def _rate(text: str) -> float:
    v = float(text)
    if not 0.1 <= v <= 1000:
        raise argparse.ArgumentTypeError(f"expected a rate in [0.1, 1000] Hz, got {text}")
    return v


def _port(text: str) -> int:
    v = int(text)
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"expected a TCP port in [0, 65535], got {text}")
    return v


def _at(text: list[str], n_fingers: int) -> list[float]:
    if len(text) != 3 * n_fingers:
        raise ValueError(
            f"--at needs {3 * n_fingers} numbers (x y z in m for each of {n_fingers} fingers), "
            f"got {len(text)}"
        )
    try:
        return [float(v) for v in text]
    except ValueError as exc:
        raise ValueError(f"--at: {exc}") from None


def _every(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive number of ticks, got {text}")
    return v


def _wants_progress(args: argparse.Namespace) -> bool:
    """A progress line on stderr: with --progress, or when stderr is a terminal."""
    return bool(getattr(args, "progress", False)) or sys.stderr.isatty()


class _ProgressLine:
    """One line on stderr, rewritten in place (at most every ``PERIOD_S``), ended by
    ``done``: ``hapticd: LABEL 41% (3.2 of 7.8 s)``."""

    PERIOD_S = 0.25

    def __init__(self, label: str) -> None:
        self.label = label
        self._last = -math.inf
        self._shown = False

    def show(self, done: float, total: float | None, unit: str, *, force: bool = False) -> None:
        import time

        now = time.monotonic()
        if not force and now - self._last < self.PERIOD_S:
            return
        self._last = now
        if total:
            text = f"{100.0 * min(done / total, 1.0):3.0f}% ({done:g} of {total:g} {unit})"
        else:
            text = f"{done:g} {unit}"
        sys.stderr.write(f"\rhapticd: {self.label} {text}\x1b[K")
        sys.stderr.flush()
        self._shown = True

    def done(self) -> None:
        if self._shown:
            sys.stderr.write("\n")
            sys.stderr.flush()


def _count(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive number of events, got {text}")
    return v


def _positive(text: str) -> float:
    v = float(text)
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text}")
    return v


def _add_progress_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--progress",
        action="store_true",
        help="show a progress line on stderr (default: when stderr is a terminal; a run "
        "shows one only --unpaced)",
    )


LOG_LEVELS = ("debug", "info", "warning", "error")


def _add_log_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--log-level",
        choices=LOG_LEVELS,
        help="what the log on stderr shows (default info: faults, device events, control "
        "changes; debug adds what the run was built from)",
    )
    parser.add_argument(
        "-v", "--verbose", action="store_true", help="the same as --log-level debug"
    )


def _log_level(args: argparse.Namespace) -> int:
    """The logging level ``args`` ask for (INFO unless -v or --log-level say otherwise)."""
    if getattr(args, "verbose", False):
        return logging.DEBUG
    name = getattr(args, "log_level", None)
    return getattr(logging, name.upper()) if name else logging.INFO
