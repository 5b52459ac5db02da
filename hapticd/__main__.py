"""``python -m hapticd`` and the ``hapticd`` command: the command line (hapticd.cli)."""

from __future__ import annotations

import os
import signal
import sys

# BLAS libraries start a thread per core that spins between calls. Our matrices are
# small (3 x 3 to 6 x 12), so those threads only take cores from the servo loop, the
# other processes of a study and each other (a psychometric fit took 2.5x the CPU with
# them). One thread per process unless the user asked for more; set before numpy loads
# BLAS, and inherited by every process hapticd starts.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")

EXIT_INTERRUPTED = 128 + signal.SIGINT  # as a shell reports a Ctrl-C

_interrupted: list[int] = []


def _on_sigint(signum: int, frame: object) -> None:
    """Python's own Ctrl-C (a KeyboardInterrupt), remembered: an extension module that is
    importing turns the KeyboardInterrupt into an ImportError, which must still read as
    the interruption it was."""
    _interrupted.append(signum)
    raise KeyboardInterrupt


def main() -> int:
    """Run the command line; the BLAS thread variables default to 1 first."""
    try:  # first: a Ctrl-C may land on any instruction, the handler's installation too
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            signal.signal(signal.SIGINT, _on_sigint)
        for name in BLAS_THREAD_VARIABLES:
            os.environ.setdefault(name, "1")
        from hapticd.cli import main as cli_main

        return cli_main()
    except KeyboardInterrupt:  # Ctrl-C while the command line loads: nothing began
        print("hapticd: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception:
        if not _interrupted:
            raise
        # Ctrl-C inside an extension's import (numpy's, say), seen as that import's failure.
        print("hapticd: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
