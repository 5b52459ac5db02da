"""What a first-time user gets from the README's install: the device backends' libraries,
and commands that say how to reach the installed ``hapticd``."""

from __future__ import annotations

import re
import tomllib

from hapticd_drivers.registry import BACKENDS

from tests.conftest import ROOT


def _name(requirement: str) -> str:
    return re.split(r"[<>=!~ \[;]", requirement, maxsplit=1)[0].lower()


def test_the_base_install_holds_every_usb_backends_library():
    """`pip install -e .` (the README's) must run `--device usb --emulate` and `--device
    hid`: every package a backend's extra names is a base dependency."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    base = {_name(r) for r in project["dependencies"]}
    extras = project["optional-dependencies"]
    wanted = {b.extra for b in BACKENDS.values() if b.extra}
    assert wanted >= {"usb", "hid"}
    for extra in wanted:
        missing = {_name(r) for r in extras[extra]} - base
        assert not missing, f"hapticd[{extra}] holds {missing}, not in the base install"
    assert {"pyusb", "libusb-package", "hidapi"} <= base


def test_the_readme_says_how_its_commands_find_hapticd():
    """The quick start installs into .venv without activating it: the "Using it" section's
    bare `hapticd ...` commands need the venv activated, and must say so."""
    text = (ROOT / "README.md").read_text()
    quick = text.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    # The first command installs the run lock (no development tools): fast.
    assert ".venv/bin/pip install -r requirements/run.txt &&" in quick
    using = text.split("## Using it", 1)[1].split("\n## ", 1)[0]
    first = using.split("```sh", 1)[1].split("```", 1)[0]
    commands = [c for ln in first.splitlines() if (c := ln.split("#")[0].strip())]
    assert commands[0] == ". .venv/bin/activate", commands[:2]
    assert all(c.startswith("hapticd ") for c in commands[1:])


def test_every_package_folder_is_in_the_wheel():
    """setuptools puts only the listed packages in a wheel: a subpackage missing from the
    list works in the editable install and breaks `pip install .` (it did, for six)."""
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(tool["packages"])
    on_disk = {"hapticd_drivers"} | {
        ".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "hapticd").rglob("__init__.py")
    }
    assert listed == on_disk
