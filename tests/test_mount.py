"""Device mounts: the map between each device's frame and the world, at the device bank."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from hypothesis import assume, given
from hypothesis import strategies as st

from hapticd import recording
from hapticd.daemon.build import builtin_trajectory
from hapticd.daemon.session import build_session
from hapticd.loop.mount import Mount, distance_to_polytope, mount_rotation
from hapticd.profile import ProfileError, load_profile
from tests.conftest import GRASP_PROFILE

angles = st.floats(-math.pi, math.pi, allow_nan=False)
coords = st.floats(-0.5, 0.5, allow_nan=False)


@given(
    st.tuples(angles, angles, angles),
    st.tuples(coords, coords, coords),
    st.floats(0.2, 5.0),
    st.tuples(coords, coords, coords),
)
def test_the_maps_are_each_others_inverse_and_keep_force_magnitudes(rpy, t, s, x):
    m = Mount.from_rpy(t, rpy, s)
    R = m.rotation
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(m.point_to_world(m.point_to_device(np.array(x))), x, atol=1e-12)
    np.testing.assert_allclose(m.point_to_world(np.array(x)), s * R @ np.array(x) + t, atol=1e-15)
    f = np.array(x) * 20.0
    assert np.linalg.norm(m.force_to_device(f)) == pytest.approx(np.linalg.norm(f), abs=1e-12)
    # Power: what the world port exchanges is s times what the device port does.
    v = np.array(t)
    assert f @ m.vector_to_world(v) == pytest.approx(s * (m.force_to_device(f) @ v), abs=1e-12)


def test_only_the_default_mount_is_the_identity():
    assert Mount().is_identity
    assert not Mount.from_rpy((0, 0, 0), (0, 0, 0), 2.0).is_identity
    assert not Mount.from_rpy((0, 0, 0.001), (0, 0, 0)).is_identity
    assert not Mount.from_rpy((0, 0, 0), (0, 0, 1e-9)).is_identity


@pytest.mark.parametrize(
    "rpy, message",
    [
        ((math.nan, 0.0, 0.0), "3 finite angles"),
        ((0.0, math.inf, 0.0), "3 finite angles"),
        ((0.0, 0.0, 90.0), r"within one turn.*degrees\?"),
    ],
)
def test_orientations_that_make_no_rotation_are_refused(rpy, message):
    with pytest.raises(ValueError, match=message):
        mount_rotation(rpy)


def _profile(tmp_path, mount: dict, finger: int = 0) -> dict:
    data = yaml.safe_load(GRASP_PROFILE.read_text())
    data["fingers"][finger]["device"]["mount"] = mount
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    "mount, key, message",
    [
        ({"orientation_rpy_rad": [".nan", 0, 0]}, "orientation_rpy_rad", "finite number"),
        ({"orientation_rpy_rad": [0, 0, 180]}, "orientation_rpy_rad", "degrees"),
        ({"orientation_rpy_rad": [0, 0]}, "orientation_rpy_rad", ""),
        ({"position_m": [0, ".inf", 0]}, "position_m", "finite"),
        ({"workspace_scale": 0}, "workspace_scale", "greater than 0"),
        ({"workspace_scale": ".nan"}, "workspace_scale", ""),
        ({"orientation_rpy": [0, 0, 0]}, "orientation_rpy", "did you mean"),
    ],
)
def test_a_bad_mount_names_the_key(tmp_path, mount, key, message):
    text = yaml.safe_dump(mount).replace("'.nan'", ".nan").replace("'.inf'", ".inf")
    path = _profile(tmp_path, yaml.safe_load(text), finger=1)
    with pytest.raises(ProfileError) as err:
        load_profile(path)
    msg = str(err.value)
    assert f"fingers[1:index].device.mount.{key}" in msg, msg
    assert message in msg, msg


def test_distance_to_a_box():
    # A 2 x 2 x 2 box about the origin: planes |x|, |y|, |z| <= 1.
    normals = np.vstack([np.eye(3), -np.eye(3)])
    offsets = np.ones(6)
    assert distance_to_polytope(normals, offsets, np.array([0.5, 0.0, 0.0])) == 0.0
    assert distance_to_polytope(normals, offsets, np.array([3.0, 0.0, 0.0])) == pytest.approx(2.0)
    # Nearest to a corner: the plane bound (max of face distances) would say 2, not 2 sqrt 3.
    d = distance_to_polytope(normals, offsets, np.array([3.0, 3.0, 3.0]))
    assert d == pytest.approx(2.0 * math.sqrt(3.0), rel=1e-7)


# Two device frames, each rotated, shifted and (the index finger's) scaled in the world.
MOUNTS = {
    "thumb": {"position_m": [-0.09, 0.02, -0.03], "orientation_rpy_rad": [0.3, -0.5, 2.0]},
    "index": {
        "position_m": [0.11, -0.015, 0.01],
        "orientation_rpy_rad": [-1.0, 0.2, -2.5],
        "workspace_scale": 1.5,
    },
}


def _trajectories(tmp_path) -> tuple[str, str]:
    """The world motion (the bundled grasp, the thumb 1.5 mm deeper) and the same motion
    mapped into each finger's device frame.

    Not the bundled grasp as it is: there both fingers touch the cube on the same tick,
    mirror images of each other, and the allocator splits the first squeeze between them
    by a difference of 1e-16 N: a tie that rounding breaks either way.
    """
    rec = recording.read(builtin_trajectory("grasp-stiffness"))
    world = rec["device_pos"].copy()
    world[:, rec.fingers.index("thumb"), 0] += 0.0015
    dev_pos = world.copy()
    for j, name in enumerate(rec.fingers):
        m = MOUNTS[name]
        scale = m.get("workspace_scale", 1.0)
        mount = Mount.from_rpy(m["position_m"], m["orientation_rpy_rad"], scale)
        dev_pos[:, j] = mount.point_to_device(world[:, j])
    paths = []
    for name, pos in (("world", world), ("device-frames", dev_pos)):
        path = tmp_path / f"{name}.hrec"
        recording.write(
            path,
            {"t": rec["t"], "device_pos": pos},
            recording.trajectory_fields(len(rec.fingers)),
            rec.fingers,
        )
        paths.append(str(path))
    return paths[0], paths[1]


def _run(profile_path, rec_path):
    s = build_session(load_profile(profile_path), paced=False, duration_s=4.0, record_path=rec_path)
    s.loop.realtime_settings = None
    out = s.run()
    assert out["end_reason"] == "duration reached" and out["fault"] is None
    return s, recording.read(rec_path)


def test_rendering_is_invariant_under_a_rigid_change_of_the_device_frames(tmp_path):
    data = yaml.safe_load(GRASP_PROFILE.read_text())
    world_traj, device_traj = _trajectories(tmp_path)
    for finger in data["fingers"]:
        finger["device"]["trajectory"] = world_traj
    world = tmp_path / "world.yaml"
    world.write_text(yaml.safe_dump(data))
    for finger in data["fingers"]:
        finger["device"]["trajectory"] = device_traj
        finger["device"]["mount"] = MOUNTS[finger["name"]]
    mounted = tmp_path / "mounted.yaml"
    mounted.write_text(yaml.safe_dump(data))

    _, a = _run(world, tmp_path / "world.hrec")
    s, b = _run(mounted, tmp_path / "mounted.hrec")
    assert a.ticks == b.ticks >= 4000
    # The frame holds world quantities: the same motion, the same forces, to rounding.
    for name in ("device_pos", "device_vel", "contact_force", "rendered_force", "device_force"):
        np.testing.assert_allclose(b[name], a[name], rtol=0, atol=1e-12, err_msg=name)
    assert np.abs(a["device_force"]).max() > 0.5  # the pinch was rendered
    # Each device got its own frame's force, R^T f (a bank that skipped it fails here).
    n = a.ticks - 1  # the last record is the shutdown's zero
    for j, dev in enumerate(s.devices):
        R = s.loop.bank.mounts[j].rotation
        np.testing.assert_allclose(dev.forces[:n], b["device_force"][:n, j] @ R, atol=1e-12)
        assert np.abs(dev.forces[:n] - b["device_force"][:n, j]).max() > 0.1


def test_check_reports_where_each_workspace_meets_the_object(tmp_path):
    import subprocess
    import sys

    data = yaml.safe_load(GRASP_PROFILE.read_text())
    # The thumb's device 200 mm to the left of the cube, turned a quarter about z.
    data["fingers"][0]["device"]["mount"] = {
        "position_m": [-0.2, 0.0, 0.0],
        "orientation_rpy_rad": [0.0, 0.0, math.pi / 2],
    }
    # The index's 60 mm to the right: the cube (25 mm half size) is within its 75 mm.
    data["fingers"][1]["device"]["mount"] = {"position_m": [0.06, 0.0, 0.0]}
    data["safety"]["workspace_radius_m"] = 0.1
    data["safety"]["workspace_center_m"] = [0.0, 0.0, 0.01]
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    out = subprocess.run(
        [sys.executable, "-m", "hapticd", "check", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    text = out.stdout
    thumb, index = text.split("  thumb:")[1].split("  index:")
    # The cube's centre in the thumb device's coordinates: R^T (0 - t), R a quarter turn.
    assert "(0.0, -200.0, 0.0) mm in its coordinates" in thumb
    assert "nearest object point 175.0 mm" in thumb and "out of reach" in thumb
    assert "(-60.0, 0.0, 0.0) mm in its coordinates" in index
    assert "nearest object point 35.0 mm" in index
    index, safety = index.split("  safety:")
    assert "reachable (part of it lies outside)" in index
    assert "(0.0, 0.0, -10.0) mm in its coordinates" in safety
    assert "the whole object is inside" in safety


@given(st.tuples(angles, angles, angles))
def test_device_bank_maps_state_and_force_through_the_mount(rpy):
    from hapticd_drivers import DeviceState

    from hapticd.loop.device_bank import DeviceBank
    from hapticd.physics.frame import Frame

    assume(max(abs(a) for a in rpy) > 1e-3)

    class Probe:
        info = None
        finished = False

        def __init__(self):
            self.written = None

        def read_state(self, st: DeviceState) -> None:
            st.position[:] = (0.01, -0.02, 0.03)
            st.velocity[:] = (0.1, 0.2, -0.3)
            st.buttons = 3

        def write_force(self, f):
            self.written = np.array(f)

    dev = Probe()
    bank = DeviceBank([dev], reconnect=False, on_fault=None, on_event=None)
    m = Mount.from_rpy((0.1, 0.2, -0.3), rpy, 2.0)
    bank.set_mounts([m])
    frame = Frame(1, 1)
    bank.read(frame, 0, 0.0)
    np.testing.assert_allclose(frame.device_pos[0], m.point_to_world(np.array([0.01, -0.02, 0.03])))
    np.testing.assert_allclose(frame.device_vel[0], m.vector_to_world(np.array([0.1, 0.2, -0.3])))
    assert frame.buttons[0] == 3
    frame.device_force[0] = (1.0, -2.0, 0.5)
    bank.write(frame, 0, 0.0)
    np.testing.assert_allclose(dev.written, m.rotation.T @ np.array([1.0, -2.0, 0.5]))
    np.testing.assert_array_equal(frame.device_force[0], (1.0, -2.0, 0.5))  # the world's stays
