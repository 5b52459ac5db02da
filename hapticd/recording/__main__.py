"""The recording writer process: ``python -m hapticd.recording RING_PATH OUT_PATH PARENT_PID``."""

import sys

from hapticd.recording.ring import main

sys.exit(main(sys.argv[1:]))
