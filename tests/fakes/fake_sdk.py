"""Build the fake Force Dimension SDK (tests/fakes/fake_dhd.c) for the tests or a shell.

From a checkout, to walk the dhd path without devices (docs/devices.md):

    python tests/fakes/fake_sdk.py --out /tmp/fakesdk

builds /tmp/fakesdk/libfakedrd.so (a fake libdrd) and libfakedhd.so (a bare libdhd)
and prints the environment to use them: HAPTICD_LIBDHD and the fake's own
HAPTICD_FAKE_DHD_* settings (device count, model, serial numbers, motion, ...).
Needs a C compiler (cc or gcc).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

SOURCE = Path(__file__).with_name("fake_dhd.c")
DRD, DHD = "fakedrd", "fakedhd"

# The fake's settings from the environment, read when the library loads.
ENVIRONMENT = {
    "HAPTICD_FAKE_DHD_DEVICES": "how many devices (none set: 0, and the other settings unused)",
    "HAPTICD_FAKE_DHD_TYPE": "their dhdGetSystemType (33: omega.3, the default; 60 Falcon, "
    "63 delta.3, 104 sigma.7; 91 a type hapticd does not know)",
    "HAPTICD_FAKE_DHD_SERIALS": "1: serial numbers 10001, 10002, ... (default); 0: none",
    "HAPTICD_FAKE_DHD_CALIBRATED": "1: calibrated at power-on (default); 0: not",
    "HAPTICD_FAKE_DHD_STATE": "a file that keeps the calibration from one command to the next",
    "HAPTICD_FAKE_DHD_MOTION": "still (default) or sine: each device at POSITION + "
    "AMPLITUDE sin(2 pi t / PERIOD_S), t from when the library loaded",
    "HAPTICD_FAKE_DHD_POSITION": "x,y,z in the device's frame, m (default 0,0,0)",
    "HAPTICD_FAKE_DHD_AMPLITUDE": "x,y,z, m (default 0,0,0)",
    "HAPTICD_FAKE_DHD_PERIOD_S": "s (default 2)",
    "HAPTICD_FAKE_DHD_SDK_VERSION": "the version dhdGetSDKVersion reports (default 3.17.5)",
    "HAPTICD_FAKE_DHD_LEGACY": "older behaviours, a sum of flags: 1 DRD state on any handle, "
    "2 no velocity window, 4 opening an open device fails, 8 no error codes (default 0)",
}


def build(out_dir: Path, drd: bool = True) -> Path:
    """Compile the fake into ``out_dir``: libfakedrd.so (``drd``) or libfakedhd.so; its
    path. RuntimeError when there is no C compiler."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise RuntimeError("no C compiler (cc or gcc) to build the fake Force Dimension SDK")
    out = Path(out_dir) / f"lib{DRD if drd else DHD}.so"
    defines = ["-DFAKE_DRD"] if drd else []
    cmd = [cc, "-shared", "-fPIC", "-O1", *defines, "-o", str(out), str(SOURCE), "-lm"]
    subprocess.run(cmd, check=True)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="directory for the libraries")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        drd, dhd = build(args.out, True), build(args.out, False)
    except (RuntimeError, subprocess.CalledProcessError) as exc:
        print(f"fake_sdk: {exc}", file=sys.stderr)
        return 1
    print(f"# built {drd} (a fake libdrd) and {dhd} (a bare libdhd); to use the first:")
    print(f"export HAPTICD_LIBDHD={drd}")
    print("export HAPTICD_FAKE_DHD_DEVICES=2")
    print("# and optionally:")
    for name, meaning in ENVIRONMENT.items():
        if name != "HAPTICD_FAKE_DHD_DEVICES":
            print(f"#   {name}: {meaning}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
