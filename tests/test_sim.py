"""The simulated finger closes the loop: stable above the passivity bound, chatters below it."""

import numpy as np
import pytest
import yaml
from hapticd_drivers import DeviceError, DeviceState, open_device

from hapticd import recording
from hapticd.daemon.build import builtin_trajectory
from hapticd.daemon.session import build_session
from hapticd.profile import ProfileError, parse_profile
from tests.conftest import GRASP_PROFILE

K = 5000.0  # an omega.3's rated stiffness, N/m
K_HAND = 300.0


class Clock:
    t = 0.0

    def __call__(self):
        return self.t


def test_free_finger_follows_its_path_and_settles_on_it():
    clock = Clock()
    t = np.array([0.0, 0.2, 1.0])
    x = np.array([[0, 0, 0], [0.01, 0, 0], [0.01, 0, 0]], dtype=float)
    dev = open_device(
        "sim", times=t, positions=x, clock=clock, mass_kg=0.05, hand_damping_n_s_per_m=5.0
    )
    st = DeviceState()
    with dev:
        dev.enable_forces(True)
        for k in range(1001):
            clock.t = k * 1e-3
            dev.read_state(st)
            dev.write_force(np.zeros(3))
    np.testing.assert_allclose(st.position, [0.01, 0, 0], atol=1e-6)
    # A constant force shifts the rest point by F / k_hand.
    with dev:
        dev.enable_forces(True)
        for k in range(1001, 3001):
            clock.t = k * 1e-3
            dev.read_state(st)
            dev.write_force(np.array([0.3, 0, 0]))
    np.testing.assert_allclose(st.position, [0.01 + 0.3 / K_HAND, 0, 0], atol=1e-5)


def test_sim_rejects_bad_parameters():
    with pytest.raises(DeviceError, match="mass must be positive"):
        open_device("sim", times=[0, 1], positions=np.zeros((2, 3)), mass_kg=0.0)


def closed_loop(tmp_path, hand_damping: float):
    data = yaml.safe_load(GRASP_PROFILE.read_text())
    for f in data["fingers"]:
        f["device"] = {
            "backend": "sim",
            "trajectory": "builtin:grasp-stiffness",
            "hand_stiffness_n_per_m": K_HAND,
            "hand_damping_n_s_per_m": hand_damping,
        }
        f["actuated_directions"] = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]  # full actuation
    data["rendering"].update(actuation_frame="world", allocator="pinv")
    data["scene"]["object"]["stiffness_n_per_m"] = K
    data["safety"]["max_force_n"] = 12.0
    path = tmp_path / f"sim-{hand_damping}.hrec"
    s = build_session(
        parse_profile(data, "sim.yaml"), paced=False, duration_s=5.4, record_path=path
    )
    summary = s.run()
    rec = recording.read(path)
    t = rec["t"]
    hold = (t > 2.8) & (t < 5.3)
    traj = recording.read(builtin_trajectory("grasp-stiffness"))
    # Where the hand would put the thumb: its path's depth past the contact surface.
    depth = np.maximum(0.0, np.interp(t, traj["t"], traj["device_pos"][:, 0, 0]) + 0.033)
    expected = K_HAND * K / (K + K_HAND) * depth  # two springs in series, at rest
    force = np.linalg.norm(rec["contact_force"][:, 0], axis=1)
    toggles = int(np.abs(np.diff(rec["in_contact"][hold, 0].astype(int))).sum())
    return summary, rec, force[hold], expected[hold], toggles


def test_rated_stiffness_is_stable_above_the_passivity_bound(tmp_path):
    # Colgate & Schenkel: passive when b > K T / 2 = 5000 * 1e-3 / 2 = 2.5 N s/m.
    summary, _rec, force, expected, toggles = closed_loop(tmp_path, hand_damping=3.0)
    assert summary["fault"] is None
    assert toggles == 0
    assert np.abs(force - expected).max() < 0.01  # the expected penetration, within 10 mN
    assert force.mean() > 3.0


def test_the_sim_shows_chatter_below_the_passivity_bound(tmp_path):
    _summary, rec, force, expected, toggles = closed_loop(tmp_path, hand_damping=2.0)
    assert toggles > 50  # the finger bounces off the wall
    assert np.abs(force - expected).max() > 1.0
    # Whatever the virtual world does, the devices never get an over-limit or NaN force.
    f = np.linalg.norm(rec["device_force"], axis=2)
    assert np.all(np.isfinite(f)) and f.max() <= 12.0 * (1 + 1e-12)


def test_sim_device_keys_are_validated():
    data = yaml.safe_load(GRASP_PROFILE.read_text())
    data["fingers"][0]["device"] = {
        "backend": "sim",
        "trajectory": "builtin:grasp-stiffness",
        "mass": 1,
    }
    with pytest.raises(
        ProfileError, match=r"fingers\[0:thumb\]\.device\.mass: unknown key; did you mean 'mass_kg'"
    ):
        parse_profile(data, "p.yaml")
