"""The dhd backend against a fake libdhd compiled here (tests/fakes/fake_dhd.c)."""

import ctypes

import numpy as np
import pytest
from hapticd_drivers import DeviceError, DeviceState, open_device


def force_of(lib, i):
    buf = (ctypes.c_double * 3)()
    lib.fake_get_force(i, buf)
    return np.array(buf[:])


def test_open_by_serial_read_write_and_close(libdhd):
    path, lib = libdhd
    lib.fake_reset(2)
    lib.fake_set_state(1, 0.01, -0.02, 0.03, 0.1, 0.0, -0.1)
    dev = open_device("dhd", library=path, serial_number=10002, device_watchdog_s=0.01)
    dev.open()
    assert dev.info.serial == "10002" and dev.info.model == "fake omega.3"
    assert lib.fake_watchdog(1) == 80  # 10 ms in 125 us units
    st = DeviceState()
    dev.read_state(st)
    np.testing.assert_allclose(st.position, [0.01, -0.02, 0.03])
    np.testing.assert_allclose(st.velocity, [0.1, 0.0, -0.1])
    dev.write_force(np.array([1.0, 2.0, 3.0]))
    np.testing.assert_array_equal(force_of(lib, 1), 0)  # not enabled yet: zero
    dev.enable_forces(True)
    dev.write_force(np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(force_of(lib, 1), [1.0, 2.0, 3.0])
    with pytest.raises(DeviceError, match="above its limit"):
        dev.write_force(np.array([20.0, 0, 0]))
    dev.close()
    np.testing.assert_array_equal(force_of(lib, 1), 0)
    assert lib.fake_is_enabled(1) == 0


def test_open_by_index_and_a_missing_device(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    dev = open_device("dhd", library=path, index=0)
    dev.open()
    assert dev.info.serial == "10001"
    dev.close()
    with pytest.raises(DeviceError, match="no device at index 3; 1 present"):
        open_device("dhd", library=path, index=3).open()
    with pytest.raises(DeviceError, match="no device with this serial number"):
        open_device("dhd", library=path, serial_number=4242).open()


def test_unplug_is_a_device_error_with_the_sdk_message(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    dev = open_device("dhd", library=path)
    dev.open()
    dev.enable_forces(True)
    lib.fake_unplug(0)
    with pytest.raises(DeviceError, match="cannot read the position: USB error: device unplugged"):
        dev.read_state(DeviceState())
    with pytest.raises(DeviceError, match="cannot set the force"):
        dev.write_force(np.ones(3))


def test_missing_library_says_how_to_get_it(monkeypatch, tmp_path):
    monkeypatch.delenv("HAPTICD_LIBDHD", raising=False)
    with pytest.raises(DeviceError, match="cannot load libdhd"):
        open_device("dhd", library=str(tmp_path / "nope.so")).open()
