"""The recording writer: ``python -m hapticd.recording RING_FD OUT_FD OUT_PATH PARENT_PID``."""

import sys

from hapticd.recording.ring import main

sys.exit(main(sys.argv[1:]))
