"""``hapticd run/check --set KEY=VALUE`` overrides one profile value, validated with the
profile; an ``--unpaced`` run (a batch render) serves no control socket unless given one,
so two of them never fight over the default socket."""

from __future__ import annotations

import json
import socket
import threading

import pytest

from hapticd import control
from hapticd.cli import main
from hapticd.daemon.session import build_session
from hapticd.profile import ProfileError, load_profile
from tests.conftest import GRASP_PROFILE

RUN = ["run", str(GRASP_PROFILE), "--unpaced", "--duration", "2.5", "-q"]


def _max_force(tmp_path, *extra: str) -> dict:
    out = tmp_path / "summary.json"
    assert main([*RUN, "--no-socket", "--summary-json", str(out), *extra]) == 0
    return json.loads(out.read_text())


def test_set_changes_the_rendered_forces(tmp_path):
    base = _max_force(tmp_path)
    stiffer = _max_force(tmp_path, "--set", "scene.object.stiffness_n_per_m=120")
    # Twice the stiffness, the same penetration: twice the force (to the allocation's
    # rounding), on both fingers.
    for name in ("thumb", "index"):
        ratio = stiffer["fingers"][name]["max_force_n"] / base["fingers"][name]["max_force_n"]
        assert ratio == pytest.approx(2.0, rel=1e-6), (name, ratio)
    # Repeatable, list items by index and by name; the later wins.
    both = _max_force(
        tmp_path,
        "--set",
        "scene.object.stiffness_n_per_m=120",
        "--set",
        "fingers[thumb].device.max_force_n=0.5",
        "--set",
        "safety.max_force_n=0.7",
        "--set",
        "fingers[1].device.max_force_n=0.6",
    )
    assert both["fingers"]["thumb"]["max_force_n"] == pytest.approx(0.5)
    assert both["fingers"]["index"]["max_force_n"] == pytest.approx(0.6)


def test_set_values_are_validated_naming_the_key(capsys):
    cases = [
        ("scene.object.stiffness_n_per_m=-5", "scene.object.stiffness_n_per_m:"),
        ("scene.object.stiffness_n_per_m=.nan", "should be a finite number"),
        ("scene.object.stifness_n_per_m=60", "scene.object.stifness_n_per_m: unknown key"),
        ("fingers[0].device.max_force_n=[1, 2]", "fingers[0:thumb].device.max_force_n:"),
        ("fingers[pinky].radius_m=0.01", "has no item named 'pinky'; names: ['thumb', 'index']"),
        ("fingers[7].radius_m=0.01", "fingers has 2 item(s), no [7]"),
        ("rendering.allocator", "expected KEY=VALUE"),
        ("scene..object=1", "not a key path"),
        ("scene.object={stiffness_n_per_m: 1}", "not a mapping"),
        ("scene.object.mass_kg=&a 1", "anchors and aliases"),
    ]
    for text, expect in cases:
        for command in ("check", "run"):
            argv = [command, str(GRASP_PROFILE), "--set", text]
            assert main(argv + (["--unpaced"] if command == "run" else [])) == 2, text
            err = capsys.readouterr().err
            assert expect in err, (text, err)
            assert "Traceback" not in err
    # A value from --set has no line in the file: the message says where it came from.
    assert main(["check", str(GRASP_PROFILE), "--set", "scene.object.stiffness_n_per_m=0"]) == 2
    err = capsys.readouterr().err
    assert "scene.object.stiffness_n_per_m:" in err and "(from --set)" in err, err
    assert "(line " not in err.split("stiffness_n_per_m:", 1)[1].splitlines()[0]


def test_check_with_set_reports_the_changed_profile(capsys):
    assert main(["check", str(GRASP_PROFILE), "--set", "rendering.allocator=ef"]) == 0
    assert "allocator ef" in capsys.readouterr().out


def test_a_reload_of_the_running_file_keeps_the_set_values():
    # The devices hold their last sample for a day: the run lasts until stopped.
    overrides = [
        "scene.object.stiffness_n_per_m=90",
        "fingers[thumb].device.hold_s=86400",
        "fingers[index].device.hold_s=86400",
    ]
    session = build_session(load_profile(GRASP_PROFILE, overrides), paced=False)
    session.overrides = overrides
    runner = threading.Thread(target=session.run, name="test-loop")
    runner.start()
    try:
        assert session.reload()["profile"] == "grasp-stiffness"
        assert session.loop.renderer.param("stiffness_n_per_m") == 90.0
        # Without them the file's devices differ (hold_s): refused, nothing changes.
        session.overrides = []
        with pytest.raises(ProfileError, match="device changed"):
            session.reload()
        assert session.loop.renderer.param("stiffness_n_per_m") == 90.0
    finally:
        session.loop.request_stop("test over", ramp=False)
        runner.join(timeout=10)
    assert not runner.is_alive()


def test_an_unpaced_run_serves_no_socket_unless_given_one(tmp_path, capsys):
    """Another daemon holds the default socket: a batch render (--unpaced) runs beside it;
    with --socket it serves (and here is refused, the socket being taken)."""
    path = control.default_socket_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    other = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        other.bind(str(path))
        other.listen(1)
        assert main([*RUN[:-1], "--duration", "0.05"]) == 0
        err = capsys.readouterr().err
        assert "control socket" not in err and "another hapticd" not in err, err
        assert main(["run", str(GRASP_PROFILE), "--unpaced", "--duration", "0.05",
                     "--socket", str(path)]) == 1  # fmt: skip
        assert "another hapticd is serving" in capsys.readouterr().err
        # A paced run still serves the default socket (here: taken).
        assert main(["run", str(GRASP_PROFILE), "--duration", "0.05", "-q"]) == 1
        assert "another hapticd is serving" in capsys.readouterr().err
    finally:
        other.close()
