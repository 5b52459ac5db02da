import subprocess
import sys

import numpy as np

from hapticd import recording
from hapticd.daemon.build import builtin_trajectory
from hapticd.loop.trajectory import Hold, MinJerk, Squeeze, minjerk_profile, sample
from tests.conftest import ROOT


def test_minjerk_profile_endpoints_and_symmetry():
    s = np.linspace(0, 1, 101)
    p = minjerk_profile(s)
    assert p[0] == 0 and p[-1] == 1
    np.testing.assert_allclose(p + p[::-1], 1, atol=1e-12)
    v = np.gradient(p, s)
    assert abs(v[0]) < 1e-3 and abs(v[-1]) < 1e-3


def test_sampled_path_is_continuous_with_smooth_velocity():
    t, x = sample(
        np.zeros(3),
        [
            Hold(0.2),
            MinJerk(0.5, (0.01, 0, 0)),
            Squeeze(1.0, (1, 0, 0), 0.002, 2.0),
            MinJerk(0.5, (0, 0, 0)),
        ],
        1000.0,
    )
    assert t[-1] == 2.2
    np.testing.assert_allclose(x[-1], 0, atol=1e-15)
    v = np.diff(x, axis=0) / 1e-3
    assert np.max(np.abs(np.diff(v, axis=0))) < 0.01  # no velocity steps at segment joins


def test_bundled_trajectory_regenerates_to_rounding(tmp_path):
    subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "make_trajectories.py"), "--out", str(tmp_path)],
        check=True,
        capture_output=True,
    )
    made = sorted(tmp_path.glob("*.hrec"))
    assert [p.name for p in made] == [
        "grasp-cycle.hrec",
        "grasp-stiffness.hrec",
        "lift-cycle.hrec",
        "lift-weight.hrec",
    ]
    for path in made:
        new, old = recording.read(path), recording.read(builtin_trajectory(path.stem))
        assert (new.fields, new.fingers, new.meta) == (old.fields, old.fingers, old.meta)
        # To the last bit or so: numpy releases may round a sine's last bit differently.
        for name in new:
            np.testing.assert_allclose(new[name], old[name], rtol=0, atol=1e-15, err_msg=name)


def test_bundled_grasp_trajectory_pinches_the_cube():
    rec = recording.read(builtin_trajectory("grasp-stiffness"))
    assert rec.fingers == ["thumb", "index"]
    x = rec["device_pos"][:, :, 0]
    t = rec["t"]
    hold = (t > 2.6) & (t < 5.4)
    assert np.all(x[hold, 0] > -0.033) and np.all(
        x[hold, 1] < 0.033
    )  # both inside contact distance
    assert np.all(np.abs(x[t > 6.3]) > 0.0355)  # released: 2.5 mm clear of contact
