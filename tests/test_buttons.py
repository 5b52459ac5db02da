"""Buttons: played from a trajectory, mapped by the profile to a deadman or a response key,
shown in status, telemetry and ``hapticd status``, and their events with response tags."""

from __future__ import annotations

import copy
import json
import threading

import numpy as np
import pytest
from hapticd_drivers import DeviceError, DeviceState
from hapticd_drivers.replay import ReplayDevice

from hapticd import recording
from hapticd.cli import main
from hapticd.control import ControlClient
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.events import NAMES
from hapticd.profile import ProfileError, load_profile, parse_profile
from tests.test_events import calm, grasp_with_buttons, profile_on

RAMP_S = 0.2


def test_replay_plays_each_samples_buttons_until_the_next():
    t = np.array([0.0, 0.1, 0.2, 0.3])
    pos = np.zeros((4, 3))
    now = [0.0]
    dev = ReplayDevice(t, pos, clock=lambda: now[0], buttons=np.array([0, 5, 4, 1]))
    dev.open()
    st = DeviceState()
    seen = []
    for when in (0.0, 0.05, 0.1, 0.15, 0.2, 0.299, 0.3, 5.0, 0.12):  # and back in time
        now[0] = when
        dev.read_state(st)
        seen.append(st.buttons)
    assert seen == [0, 0, 5, 5, 4, 4, 1, 1, 5]
    plain = ReplayDevice(t, pos, clock=lambda: 0.2)
    plain.open()
    plain.read_state(st)
    assert st.buttons == 0  # a trajectory without buttons: every button up


@pytest.mark.parametrize(
    ("buttons", "why"),
    [
        (np.array([0, 1, 2]), r"one integer bit set per sample \(4,\)"),
        (np.array([0.0, 1.0, 0.0, 1.0]), "one integer bit set per sample"),
        (np.array([0, 1, -1, 0]), "32-bit bit sets"),
        (np.array([0, 1, 2**32, 0]), "32-bit bit sets"),
    ],
)
def test_replay_refuses_buttons_that_are_not_bit_sets_per_sample(buttons, why):
    with pytest.raises(DeviceError, match=why):
        ReplayDevice(np.arange(4) * 0.1, np.zeros((4, 3)), buttons=buttons)


# -- the profile --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("buttons", "where", "what"),
    [
        ([{"button": 0, "role": "deadman", "ramp": 0.1}], "buttons[0].ramp", "unknown key"),
        ([{"button": 0, "role": "brake"}], "buttons[0]", "deadman"),
        ([{"button": 32, "role": "deadman"}], "buttons[0].button", "less than or equal to 31"),
        ([{"button": "0", "role": "deadman"}], "buttons[0].button", "integer"),
        ([{"role": "response"}], "buttons[0].button", "missing"),
        ([{"button": 0, "role": "deadman", "ramp_s": -1}], "buttons[0].ramp_s", "greater"),
        (
            [{"button": 0, "role": "deadman"}, {"button": 1, "role": "deadman"}],
            "buttons",
            "at most one deadman",
        ),
        (
            [{"button": 2, "role": "deadman"}, {"button": 2, "role": "response"}],
            "buttons",
            "one role; repeated: [2]",
        ),
        ([{"button": 1, "role": "response", "label": ""}], "buttons[0].label", "at least 1"),
    ],
)
def test_bad_button_roles_name_the_key_and_what_was_expected(grasp_data, buttons, where, what):
    grasp_data["fingers"][1]["buttons"] = buttons
    with pytest.raises(ProfileError) as exc:
        parse_profile(grasp_data, "p.yaml")
    msg = str(exc.value)
    assert f"fingers[1:index].{where}" in msg and what in msg, msg


def test_button_roles_are_read_with_their_defaults(grasp_data):
    grasp_data["fingers"][0]["buttons"] = [{"button": 0, "role": "deadman"}]
    grasp_data["fingers"][1]["buttons"] = [
        {"button": 1, "role": "response", "label": "stiffer"},
        {"button": 2, "role": "response"},
    ]
    prof = parse_profile(grasp_data, "p.yaml")
    thumb, index = prof.fingers
    assert thumb.deadman is not None and thumb.deadman.ramp_s == 0.25
    assert index.deadman is None and thumb.responses() == {}
    assert index.responses() == {1: "stiffer", 2: "index-2"}


# -- the deadman --------------------------------------------------------------------------------


def _run(profile, tmp_path, name):
    session = build_session(load_profile(profile), paced=False, record_path=tmp_path / name)
    session.loop.realtime_settings = None
    session.run()
    return session, recording.read(tmp_path / name)


def test_a_deadman_gives_exactly_zero_force_released_and_ramps_back_on_a_press(
    tmp_path, grasp_data, write_profile
):
    """The grasp twice on the same trajectory: without buttons, and with a deadman on both
    fingers. The thumb's button is down for [2.2, 4.0) s and from 4.5 s, the index's all
    along. Released, the thumb's force is exactly zero (in the recording and at the
    device) although the grasp pushes; from each press it is the plain run's force times
    (t - press) / ramp_s up to 1; the index, held from the start, gets the plain force."""

    def schedule(t):
        thumb = ((t >= 2.2) & (t < 4.0)) | (t >= 4.5)
        return np.stack([thumb.astype(int), np.ones_like(t, dtype=int)], axis=1)

    traj = grasp_with_buttons(tmp_path / "buttons.hrec", schedule)
    plain_profile = profile_on(dict(grasp_data), traj, write_profile)
    deadman = [{"button": 0, "role": "deadman", "ramp_s": RAMP_S}]
    gated_profile = write_profile(
        calm(
            {
                **grasp_data,
                "fingers": [
                    {**f, "buttons": copy.deepcopy(deadman)} for f in grasp_data["fingers"]
                ],
            }
        ),
        "gated.yaml",
    )
    _, plain = _run(plain_profile, tmp_path, "plain.hrec")
    session, gated = _run(gated_profile, tmp_path, "gated.hrec")
    assert gated.ticks == plain.ticks
    t = gated["t"]
    down = (gated["buttons"][:, 0] & 1).astype(int)
    presses = np.flatnonzero(np.diff(down) == 1) + 1
    releases = np.flatnonzero(np.diff(down) == -1) + 1
    assert t[presses] == pytest.approx([2.2, 4.5], abs=2e-3) and t[releases] == pytest.approx(
        [4.0], abs=2e-3
    )
    f_plain = plain["device_force"][:, 0]
    f_gated = gated["device_force"][:, 0]
    mag = np.linalg.norm(f_plain, axis=1)
    up = down == 0
    assert mag[up].max() > 0.5  # the grasp pushes while the button is up...
    assert not f_gated[up].any()  # ...and the thumb gets exactly nothing
    sent = session.devices[0].forces
    assert len(sent) == gated.ticks + 1  # every tick's force, and the shutdown's zero
    assert not sent[:-1][up].any()
    # Down: the plain force, times the ramp from the press.
    press_t = np.full(len(t), np.nan)
    for k in presses:
        press_t[k:] = t[k]
    gate = np.clip((t - press_t) / RAMP_S, 0.0, 1.0)
    held = ~up
    np.testing.assert_allclose(
        f_gated[held], f_plain[held] * gate[held][:, None], rtol=1e-12, atol=1e-15
    )
    ramping = held & (gate > 0) & (gate < 1) & (mag > 0.1)
    assert ramping.sum() > 100  # both ramps are in the grasp
    # The index's button is held from tick 0: nothing differs.
    np.testing.assert_array_equal(gated["device_force"][:, 1], plain["device_force"][:, 1])
    # The loop reported every change of the thumb's button, at its tick.
    got, lost = session.loop.event_ring.drain()
    assert lost == 0
    buttons = [
        (NAMES[k], int(tick))
        for k, tick, f in zip(got["kind"], got["tick"], got["finger"], strict=True)
        if NAMES[k].startswith("button_") and f == 0
    ]
    k0 = gated["tick"].astype(int)
    assert buttons == [
        ("button_down", k0[presses[0]]),
        ("button_up", k0[releases[0]]),
        ("button_down", k0[presses[1]]),
    ]


# -- status, telemetry, events with a response, the CLI -------------------------------------


def test_buttons_in_status_telemetry_and_events_with_a_response_tag(
    tmp_path, grasp_data, write_profile, capsys
):
    """The thumb has a deadman it never presses, the index a response key (button 1,
    "stiffer") pressed for [0.5, 0.7) s and from 1.2 s. `hapticd events --json` prints the
    presses tagged with the response; status and telemetry show the button held and the
    deadman released; `hapticd status` says so."""

    def schedule(t):
        index = (((t >= 0.5) & (t < 0.7)) | (t >= 1.2)).astype(int) << 1
        return np.stack([np.zeros_like(index), index], axis=1)

    traj = grasp_with_buttons(tmp_path / "buttons.hrec", schedule)
    grasp_data["fingers"][0]["buttons"] = [{"button": 0, "role": "deadman"}]
    grasp_data["fingers"][1]["buttons"] = [{"button": 1, "role": "response", "label": "stiffer"}]
    profile = profile_on(grasp_data, traj, write_profile)
    session = build_session(load_profile(profile), duration_s=4.0, record_dir=tmp_path)
    session.loop.realtime_settings = None
    sock = tmp_path / "b.sock"
    server = ControlServer(session, sock)
    server.start()
    # As the daemon does: the run's end closes the server, and so every client's stream.
    runner = threading.Thread(target=lambda: (session.run(), server.close()), name="test-loop")
    runner.start()
    try:
        rc = main(["events", "--json", "--count", "2", "--kinds", "button_down,button_up",
                   "--socket", str(sock)])  # fmt: skip
        out = capsys.readouterr().out.strip().splitlines()
        assert rc == 0 and len(out) == 2
        down, up = (json.loads(line) for line in out)
        assert down["event"] == "button_down" and up["event"] == "button_up"
        for ev, t in ((down, 0.5), (up, 0.7)):
            assert ev["t"] == pytest.approx(t, abs=2e-3) and ev["tick"] == round(ev["t"] * 1e3)
            assert (ev["finger"], ev["finger_name"], ev["button"]) == (1, "index", 1)
            assert ev["response"] == "stiffer"
        rc = main(["events", "--count", "1", "--kinds", "button_down", "--socket", str(sock)])
        line = capsys.readouterr().out.strip()
        assert rc == 0 and "button_down" in line and "index" in line
        assert "button 1" in line and "response stiffer" in line
        with ControlClient(sock) as c:
            st = c.status()
            assert st["devices"][1]["buttons"] == [1] and st["devices"][0]["buttons"] == []
            assert st["devices"][0]["deadman"] == {"button": 0, "held": False, "gate": 0.0}
            assert st["devices"][1]["deadman"] is None
            c.subscribe(100.0)
            assert c.next_telemetry()["buttons"] == [[], [1]]
        rc = main(["status", "--socket", str(sock)])
        text = capsys.readouterr().out
        assert rc == 0 and "buttons 1 down" in text and "deadman 0 RELEASED: no force" in text
        rc = main(["events", "--kinds", "button_down,bogus", "--socket", str(sock)])
        assert rc == 2 and "unknown event(s) ['bogus']" in capsys.readouterr().err
    finally:
        session.loop.request_stop("test over")
        runner.join(timeout=20)
        server.close()
    # The thumb's deadman was never pressed: it got no force all run.
    assert not session.devices[0].forces.any()
