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
