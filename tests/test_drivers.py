import subprocess
import sys

import numpy as np
import pytest
from hapticd_drivers import BackendUnavailableError, DeviceError, DeviceState, open_device
from hapticd_drivers.registry import BACKENDS, Backend


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def make(clock, **kw):
    t = np.array([0.0, 0.1, 0.2])
    x = np.array([[0.0, 0, 0], [0.01, 0, 0], [0.01, 0.02, 0]])
    return open_device("replay", times=t, positions=x, clock=clock, **kw)


def test_replay_interpolates_between_samples_and_reports_the_end():
    clock = Clock()
    dev = make(clock)
    st = DeviceState()
    with dev:
        for t, want, vel in [
            (0.0, [0, 0, 0], [0.1, 0, 0]),
            (0.05, [0.005, 0, 0], [0.1, 0, 0]),
            (0.15, [0.01, 0.01, 0], [0, 0.2, 0]),
        ]:
            clock.t = t
            dev.read_state(st)
            np.testing.assert_allclose(st.position, want, atol=1e-15)
            np.testing.assert_allclose(st.velocity, vel, atol=1e-12)
            assert not dev.finished
        clock.t = 0.25
        dev.read_state(st)
        np.testing.assert_allclose(st.position, [0.01, 0.02, 0])
        np.testing.assert_allclose(st.velocity, 0)
        assert dev.finished


def test_replay_hold_extends_the_end():
    clock = Clock()
    dev = make(clock, hold_s=0.5)
    st = DeviceState()
    with dev:
        clock.t = 0.6
        dev.read_state(st)
        assert not dev.finished
        clock.t = 0.7
        dev.read_state(st)
        assert dev.finished


def test_replay_keeps_forces_and_refuses_bad_ones():
    clock = Clock()
    dev = make(clock, max_force_n=5.0)
    with dev:
        dev.enable_forces(True)
        dev.write_force(np.array([1.0, 2.0, 0.0]))
        dev.enable_forces(False)
        dev.write_force(np.array([1.0, 0.0, 0.0]))  # disabled: renders zero
        with pytest.raises(DeviceError, match="above its limit 5 N"):
            dev.write_force(np.array([4.0, 4.0, 0.0]))
        with pytest.raises(DeviceError, match="3 finite values"):
            dev.write_force(np.array([np.nan, 0.0, 0.0]))
        np.testing.assert_allclose(dev.forces, [[1, 2, 0], [0, 0, 0]])
    with pytest.raises(DeviceError, match="closed device"):
        dev.write_force(np.zeros(3))


def test_replay_rejects_bad_trajectories():
    with pytest.raises(DeviceError, match="strictly increase"):
        open_device("replay", times=[0, 0, 1], positions=np.zeros((3, 3)))
    with pytest.raises(DeviceError, match="do not match"):
        open_device("replay", times=[0, 1], positions=np.zeros((3, 3)))
    with pytest.raises(DeviceError, match="non-finite position"):
        open_device("replay", times=[0, 1], positions=[[0, 0, np.nan], [0, 0, 0]])


def test_unknown_backend_lists_known_ones():
    with pytest.raises(BackendUnavailableError, match=r"unknown device backend .omega9.*replay"):
        open_device("omega9")


def test_missing_optional_dependency_names_the_extra(monkeypatch):
    fancy = Backend("fancy", "hapticd_drivers._no_such_module", "X", "a test backend", (), "usb")
    monkeypatch.setitem(BACKENDS, "fancy", fancy)
    with pytest.raises(BackendUnavailableError, match=r"pip install 'hapticd\[usb\]'"):
        open_device("fancy")


def test_drivers_never_import_hapticd():
    code = (
        "import sys, hapticd_drivers, hapticd_drivers.replay, hapticd_drivers.registry\n"
        "bad = [m for m in sys.modules if m == 'hapticd' or m.startswith('hapticd.')]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("repeat", [False, True])
def test_a_trajectory_samples_what_at_and_buttons_at_give(repeat):
    """``Trajectory.sample`` (the replay device's read) writes the very floats ``at`` returns
    and returns ``buttons_at``'s buttons, whatever the cursor does: a tick's step, a jump over
    several samples, time going back, before the start, past the end, around a repeat."""
    from hapticd_drivers.trajectory import Trajectory

    rng = np.random.default_rng(7)
    t = np.cumsum(rng.uniform(1e-3, 3e-3, 60))
    x = np.cumsum(rng.normal(0.0, 1e-4, (60, 3)), axis=0)
    x[-1] = x[0]  # a repeated path ends where it starts
    b = rng.integers(0, 8, 60)
    ref = Trajectory(t, x, "ref", b, repeat)
    path = Trajectory(t, x, "path", b, repeat)
    end = float(t[-1] - t[0])
    times = [k * 1e-3 for k in range(int(end * 1e3) + 40)]  # every tick, past the end
    times += [0.05, 0.01, -0.5, end, end + 1e-9, 2.5 * end, 0.02, 0.021, 0.09, 1e-3]
    times += rng.uniform(-0.01, 3 * end, 200).tolist()
    pos, vel = np.zeros(3), np.zeros(3)
    for now in times:
        buttons = path.sample(now, memoryview(pos), memoryview(vel))
        want_pos, want_vel = ref.at(now)
        assert pos.tolist() == list(want_pos), now
        assert vel.tolist() == list(want_vel), now
        assert buttons == ref.buttons_at(now), now


def test_check_force_returns_the_force_it_accepts():
    from hapticd_drivers.base import check_force

    assert check_force(np.array([1.0, -2.0, 0.5]), 3.0, "d") == (1.0, -2.0, 0.5)
    assert check_force([0.0, 3.0, 0.0], 3.0, "d") == (0.0, 3.0, 0.0)  # a list: the slow path
    for bad in (np.zeros(4), np.zeros((3, 1)), np.array([0.0, np.inf, 0.0]), "abc"):
        with pytest.raises(DeviceError, match="expected 3 finite values"):
            check_force(bad, 3.0, "d")
    with pytest.raises(DeviceError, match="above its limit 3 N"):
        check_force(np.array([3.0, 0.1, 0.0]), 3.0, "d")


def test_a_device_state_holds_its_arrays_and_refuses_others():
    st = DeviceState()
    st.pos_view[1] = 0.25
    st.vel_view[2] = -1.5
    assert st.position.tolist() == [0.0, 0.25, 0.0] and st.velocity.tolist() == [0, 0, -1.5]
    rows = np.zeros((2, 3))
    st = DeviceState(rows[0], rows[1])  # an owner's own rows, filled in place
    st.pos_view[0] = 1.0
    assert rows[0, 0] == 1.0
    for bad in (np.zeros(3, dtype=np.float32), np.zeros(4), np.zeros((3, 2))[:, 0]):
        with pytest.raises(ValueError, match=r"DeviceState\.position"):
            DeviceState(bad)
