"""udev rules and device discovery."""

import json
import sys
import types

import numpy as np
from hapticd_drivers.delta import load_description
from hapticd_drivers.emulator import DeltaEmulator, FakeHidModule
from hapticd_drivers.registry import discover
from hapticd_drivers.trajectory import Trajectory
from hapticd_drivers.udev import rules

from hapticd.cli import main


def test_rules_cover_every_backends_devices():
    text = rules()
    assert 'SUBSYSTEM=="usb", ATTRS{idVendor}=="1209", ATTRS{idProduct}=="0001"' in text
    assert 'KERNEL=="hidraw*", ATTRS{idVendor}=="1209", ATTRS{idProduct}=="0001"' in text
    assert 'SUBSYSTEM=="usb", ATTRS{idVendor}=="1451", MODE="0660"' in text  # Force Dimension
    assert all('TAG+="uaccess"' in ln for ln in text.splitlines() if not ln.startswith("#"))


def test_discover_lists_emulated_hid_devices(monkeypatch):
    path = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)), "p")
    fake = FakeHidModule(
        [DeltaEmulator(load_description("delta-omega-class"), path, lambda: 0.0, serial="EMU-9")]
    )
    module = types.SimpleNamespace(enumerate=fake.enumerate, device=fake.device)
    monkeypatch.setitem(sys.modules, "hid", module)
    hid = [e for e in discover() if e["backend"] == "hid"]
    assert hid == [
        {"backend": "hid", "model": "delta-omega-class (usb, hid backends)", "found": ["EMU-9"]}
    ]


def test_devices_command_explains_what_it_cannot_do(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "hid", None)
    monkeypatch.delenv("HAPTICD_LIBDHD", raising=False)
    monkeypatch.setattr("ctypes.util.find_library", lambda name: None)
    assert main(["devices", "--json"]) == 0
    report = {e["backend"]: e for e in json.loads(capsys.readouterr().out)}
    assert "pip install 'hapticd[hid]'" in report["hid"]["problem"]
    assert "HAPTICD_LIBDHD" in report["dhd"]["problem"]
    assert main(["udev-rules"]) == 0
    assert "70-hapticd.rules" in capsys.readouterr().out
