"""The backend registry is the one declaration: every backend is selectable by a profile
and by --device, and the profile schema, CLI and docs derive from it."""

from __future__ import annotations

import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hapticd_drivers import registry
from hapticd_drivers.registry import BACKENDS, REQUIRED

from hapticd.cli import build_parser
from hapticd.daemon.build import build_devices
from hapticd.profile import DEVICE_MODELS, ProfileError, load_profile, parse_profile

ROOT = Path(__file__).resolve().parent.parent
GRASP = ROOT / "configs" / "grasp-stiffness.yaml"


def _with_backend(tmp_path: Path, name: str, **keys: object) -> Path:
    data = yaml.safe_load(GRASP.read_text())
    for finger in data["fingers"]:
        old = finger["device"]
        device: dict[str, object] = {"backend": name}
        if registry.backend(name).plays_trajectory:
            device["trajectory"] = old["trajectory"]
        device.update(keys)
        finger["device"] = device
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_every_backend_is_selectable_by_a_profile(name: str, tmp_path: Path) -> None:
    profile = load_profile(_with_backend(tmp_path, name))
    assert [f.device.backend for f in profile.fingers] == [name, name]
    assert type(profile.fingers[0].device) is DEVICE_MODELS[name]


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_every_backend_is_a_device_choice(name: str) -> None:
    args = build_parser().parse_args(["run", str(GRASP), "--device", name])
    assert args.device == name


def test_an_unknown_device_choice_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", str(GRASP), "--device", "nope"])
    assert "invalid choice" in capsys.readouterr().err


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_every_entry_names_an_importable_class(name: str) -> None:
    b = BACKENDS[name]
    cls = getattr(importlib.import_module(b.module), b.cls)
    assert isinstance(cls, type)
    for hook in (b.discover, b.preflight):
        if hook is not None:
            module, _, fn = hook.partition(":")
            assert callable(getattr(importlib.import_module(module), fn))


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_profile_models_carry_the_registry_keys(name: str) -> None:
    model = DEVICE_MODELS[name]
    fields = model.model_fields
    assert set(fields) == {"backend", "mount"} | {k.name for k in BACKENDS[name].keys}
    for k in BACKENDS[name].keys:
        assert fields[k.name].is_required() == (k.default is REQUIRED)


def test_a_bad_key_is_reported_where_the_user_wrote_it(tmp_path: Path) -> None:
    path = _with_backend(tmp_path, "usb", indx=1)
    with pytest.raises(ProfileError) as err:
        load_profile(path)
    msg = str(err.value)
    assert "fingers[0:thumb].device.indx" in msg and ".usb." not in msg
    assert "did you mean 'index'" in msg


def test_a_bound_from_the_registry_is_enforced(tmp_path: Path) -> None:
    path = _with_backend(tmp_path, "dhd", device_watchdog_s=0.5)
    with pytest.raises(ProfileError, match=r"device_watchdog_s"):
        load_profile(path)


def test_dhd_profile_fails_only_on_the_missing_library(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv("HAPTICD_LIBDHD", raising=False)
    path = _with_backend(tmp_path, "dhd", library=str(tmp_path / "no-libdhd.so"))
    profile = load_profile(path)
    with pytest.raises(ProfileError) as err:
        build_devices(profile, clock=lambda: 0.0)
    msg = str(err.value)
    assert "fingers[0:thumb].device" in msg and "libdhd" in msg


def test_check_reports_the_missing_libdhd_and_how_to_point_at_it(tmp_path: Path) -> None:
    path = _with_backend(tmp_path, "dhd")
    env = {k: v for k, v in __import__("os").environ.items() if k != "HAPTICD_LIBDHD"}
    env["HAPTICD_LIBDHD"] = ""
    env["LD_LIBRARY_PATH"] = str(tmp_path)  # no system libdhd here either
    out = subprocess.run(
        [sys.executable, "-m", "hapticd", "check", str(path)],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert out.returncode == 2, out
    assert "'library'" in out.stderr and "HAPTICD_LIBDHD" in out.stderr


def test_check_accepts_dhd_with_the_fake_library(tmp_path: Path, libdhd) -> None:
    path = _with_backend(tmp_path, "dhd", library=libdhd[0])
    out = subprocess.run(
        [sys.executable, "-m", "hapticd", "check", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert "thumb (dhd" in out.stdout


def test_device_override_runs_the_target_backend_on_its_defaults() -> None:
    profile = parse_profile(yaml.safe_load(GRASP.read_text()), GRASP)
    devices, _ = build_devices(profile, device="sim", clock=lambda: 0.0)
    assert [type(d).__name__ for d in devices] == ["SimulatedFinger"] * 2


def test_the_docs_tables_are_the_registry() -> None:
    text = (ROOT / "docs" / "devices.md").read_text()
    m = re.search(r"<!-- generated from .*?-->\n(.*?)<!-- end of generated tables -->", text, re.S)
    assert m, "docs/devices.md lost its generated-table markers"
    assert m.group(1) == registry.docs(), (
        "docs/devices.md differs from the registry: paste the output of "
        "`python -c 'from hapticd_drivers.registry import docs; print(docs(), end=\"\")'`"
    )
