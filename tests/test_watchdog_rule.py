"""A real device never runs without the loop's wall-clock watchdog unless the profile says
so explicitly (safety.allow_no_watchdog), and then every start warns."""

from __future__ import annotations

import logging

import pytest
import yaml

from hapticd.cli import main
from hapticd.daemon.build import build_devices, check_watchdog
from hapticd.profile import ProfileError, load_profile
from tests.conftest import ROOT

REHEARSE = ROOT / "configs" / "rehearse-grasp.yaml"
FALCONS = ROOT / "configs" / "rigs" / "two-falcons.yaml"


def _without_watchdog(tmp_path, source, **safety) -> str:
    """``source`` (a profile that names no file of its own) with no watchdog, in tmp_path."""
    data = yaml.safe_load(source.read_text())
    data["safety"].update(watchdog_s=None, **safety)
    path = tmp_path / source.name
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.fixture
def falcons_unwatched(tmp_path):
    return _without_watchdog(tmp_path, FALCONS)


def test_a_hardware_rig_without_a_watchdog_is_refused_by_check(falcons_unwatched, capsys):
    assert main(["check", falcons_unwatched]) != 0
    err = capsys.readouterr().err
    assert "safety.watchdog_s" in err and "'falcon'" in err and "allow_no_watchdog" in err
    assert "fingers[0:" in err


def test_a_rehearsal_under_a_hardware_device_is_refused_before_any_device_is_made():
    """The rehearsal turns the watchdog off (no hardware); `--device dhd` puts a real device
    under it: refused before a device is created, naming every finger."""
    prof = load_profile(REHEARSE)
    assert prof.safety.watchdog_s is None
    build_devices(prof, clock=lambda: 0.0)  # its own replay devices need none
    with pytest.raises(ProfileError) as caught:
        build_devices(prof, device="dhd", clock=lambda: 0.0)
    msg = str(caught.value)
    assert msg.count("on 'dhd'") == len(prof.fingers) and "safety.watchdog_s" in msg
    for name in ("falcon", "usb", "hid"):
        with pytest.raises(ProfileError, match="watchdog"):
            check_watchdog(prof, device=name)
    # An emulator under the backend is no real device; nor are the simulated ones.
    check_watchdog(prof, device="usb", emulate=True)
    for name in ("replay", "sim", "virtual"):
        check_watchdog(prof, device=name)


def test_asking_for_no_watchdog_explicitly_runs_with_a_warning_each_start(tmp_path, caplog):
    prof = load_profile(_without_watchdog(tmp_path, FALCONS, allow_no_watchdog=True))
    for _ in range(2):
        with caplog.at_level(logging.WARNING, logger="hapticd"):
            check_watchdog(prof)
    warned = [r.getMessage() for r in caplog.records if "no watchdog" in r.getMessage()]
    assert len(warned) == 2 and "'falcon'" in warned[0]
