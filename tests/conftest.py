"""Shared fixtures; every test must leave no thread behind."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, settings

ROOT = Path(__file__).resolve().parent.parent
GRASP_PROFILE = ROOT / "configs" / "grasp-stiffness.yaml"

# Deterministic generated cases in CI; more examples on demand (HYPOTHESIS_PROFILE=thorough).
settings.register_profile(
    "ci",
    derandomize=True,
    max_examples=300,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("thorough", max_examples=5000, deadline=None)
settings.load_profile("ci")


@pytest.fixture(autouse=True)
def no_leaked_threads():
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()]
        if not leaked:
            return
        time.sleep(0.01)
    pytest.fail(f"test leaked threads: {[t.name for t in leaked]}")


@pytest.fixture
def grasp_data() -> dict:
    return yaml.safe_load(GRASP_PROFILE.read_text())


@pytest.fixture
def write_profile(tmp_path):
    """Write a profile dict to a YAML file in tmp_path; trajectory paths stay builtin."""

    def _write(data: dict, name: str = "profile.yaml") -> Path:
        path = tmp_path / name
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        return path

    return _write
