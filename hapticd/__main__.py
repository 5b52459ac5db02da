"""``python -m hapticd`` and the ``hapticd`` command: the command line (hapticd.cli)."""

from __future__ import annotations

import os
import sys

# BLAS libraries start a thread per core that spins between calls. Our matrices are
# small (3 x 3 to 6 x 12), so those threads only take cores from the servo loop, the
# other processes of a study and each other (a psychometric fit took 2.5x the CPU with
# them). One thread per process unless the user asked for more; set before numpy loads
# BLAS, and inherited by every process hapticd starts.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def main() -> int:
    """Run the command line; the BLAS thread variables default to 1 first."""
    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    from hapticd.cli import main as cli_main

    return cli_main()


if __name__ == "__main__":
    sys.exit(main())
