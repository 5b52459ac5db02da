"""``python -m hapticd``: the same as the ``hapticd`` command."""

import sys

from hapticd.cli import main

sys.exit(main())
