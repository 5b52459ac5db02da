"""The bundled profiles reproduce stored physics to 1e-12 on replay and sim devices.

``tests/data/reference_physics.npz`` holds what each bundled profile produced
unpaced (every 5th tick of the recording's physics fields). A refactoring must
reproduce it; a deliberate change of behaviour regenerates it in a commit of
its own that says why::

    python tests/test_reference_output.py --regenerate
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hapticd import recording

ROOT = Path(__file__).resolve().parent.parent
REFERENCE = Path(__file__).with_name("data") / "reference_physics.npz"
STRIDE = 5
PROFILES = ("grasp-stiffness", "lift-weight")
DEVICES = ("replay", "sim")
PHYSICS = (
    "device_pos",
    "device_vel",
    "proxy_pos",
    "in_contact",
    "contact_force",
    "rendered_force",
    "device_force",
    "lam_a",
    "residual_internal",
    "residual_external",
    "residual_total",
    "amplification",
    "alpha",
    "env_force",
    "object_pos",
    "object_rot",
    "fault",
)


def physics(profile: str, device: str, out: Path) -> dict[str, np.ndarray]:
    """Run a bundled profile unpaced on ``device`` and return its physics fields."""
    path = out / f"{profile}-{device}.hrec"
    cmd = [sys.executable, "-m", "hapticd", "run", str(ROOT / "configs" / f"{profile}.yaml")]
    cmd += ["--unpaced", "--no-socket", "--no-realtime", "-q", "--device", device]
    cmd += ["--record", str(path)]
    subprocess.run(cmd, check=True, timeout=300)
    rec = recording.read(path)
    return {f"{profile}/{device}/{name}": rec[name][::STRIDE] for name in PHYSICS}


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("profile", PROFILES)
def test_bundled_profile_reproduces_reference(profile: str, device: str, tmp_path: Path) -> None:
    ref = np.load(REFERENCE)
    got = physics(profile, device, tmp_path)
    for key, value in got.items():
        want = ref[key]
        assert value.shape == want.shape, f"{key}: shape {value.shape}, reference {want.shape}"
        if value.dtype.kind == "f":
            scale = max(1.0, float(np.max(np.abs(want))))
            err = float(np.max(np.abs(value - want))) / scale
            assert err <= 1e-12, f"{key}: differs from the reference by {err:.3g} (relative)"
        else:
            assert np.array_equal(value, want), f"{key}: differs from the reference"


def _regenerate() -> None:
    import tempfile

    arrays: dict[str, np.ndarray] = {}
    with tempfile.TemporaryDirectory() as d:
        for profile in PROFILES:
            for device in DEVICES:
                arrays.update(physics(profile, device, Path(d)))
    REFERENCE.parent.mkdir(exist_ok=True)
    np.savez_compressed(REFERENCE, **arrays)
    print(f"wrote {REFERENCE} ({REFERENCE.stat().st_size} bytes)")


if __name__ == "__main__":
    if sys.argv[1:] != ["--regenerate"]:
        sys.exit(__doc__)
    _regenerate()
