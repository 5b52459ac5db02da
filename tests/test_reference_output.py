"""The bundled profiles reproduce stored physics to 1e-12 on replay and sim devices, with
the Python code and with the compiled kernels.

``tests/data/reference_physics.npz`` holds what each bundled profile produced
unpaced (every 5th tick of the recording's physics fields). A refactoring must
reproduce it; a deliberate change of behaviour regenerates it in a commit of
its own that says why::

    python tests/test_reference_output.py --regenerate

The runs pin OpenBLAS's kernels (``OPENBLAS_CORETYPE=Haswell``): OpenBLAS picks
its kernels by CPU and they round differently (an AVX-512 machine differs from
an AVX2 one in the last bit of a product), and once the lift's cube is
squeezed those last bits grow to 0.7 mm by the end of the run. Pinned, the
same code gives the same bits on any x86-64 machine with AVX2.
"""

from __future__ import annotations

import os
import platform
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
# The Python code (the reference, which regenerates the file) and the compiled kernels
# (hapticd.physics.kernels: every kernel the renderer names for the profile: the free-body step,
# the allocation, the contact, friction and the contact forces): both must reproduce it.
# Measured: the same bits on both.
KERNELS = ("python", "compiled")
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
# Kernels every AVX2 machine can run (see the module's docstring).
PINNED_ENV = {"OPENBLAS_CORETYPE": "Haswell"}


def _has_avx2() -> bool:
    try:
        return "avx2" in Path("/proc/cpuinfo").read_text().split()
    except OSError:
        return False


needs_avx2 = pytest.mark.skipif(
    platform.machine() != "x86_64" or not _has_avx2(),
    reason="the reference used OpenBLAS's Haswell kernels: needs an x86-64 CPU with AVX2",
)


def physics(profile: str, device: str, out: Path, kernels: str = "python") -> dict[str, np.ndarray]:
    """Run a bundled profile unpaced on ``device`` with ``kernels`` (rendering.kernels) and
    return its physics fields."""
    path = out / f"{profile}-{device}.hrec"
    cmd = [sys.executable, "-m", "hapticd", "run", str(ROOT / "configs" / f"{profile}.yaml")]
    cmd += ["--unpaced", "--no-socket", "--no-realtime", "-q", "--device", device]
    cmd += ["--record", str(path), "--set", f"rendering.kernels={kernels}"]
    run = subprocess.run(
        cmd,
        check=True,
        timeout=300,
        env={**os.environ, **PINNED_ENV},
        capture_output=True,
        text=True,
    )
    # A compiled run that fell back to Python would prove nothing about the kernels.
    assert "kernels render instead" not in run.stderr, run.stderr
    rec = recording.read(path)
    return {f"{profile}/{device}/{name}": rec[name][::STRIDE] for name in PHYSICS}


@needs_avx2
@pytest.mark.parametrize("kernels", KERNELS)
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("profile", PROFILES)
def test_bundled_profile_reproduces_reference(
    profile: str, device: str, kernels: str, tmp_path: Path
) -> None:
    ref = np.load(REFERENCE)
    got = physics(profile, device, tmp_path, kernels)
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
