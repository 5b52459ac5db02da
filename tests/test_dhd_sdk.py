"""The dhd backend against the SDK as its documentation and public callers describe it:
the declarations against the recorded prototypes, DRD state only on DRD opens, the
velocity estimator's window, devices without serial numbers, the documented error codes,
an open device's ID returned by a second open, the brakes, the SDK version, the model
table; each failure a message naming the device."""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import re
from pathlib import Path

import numpy as np
import pytest
from hapticd_drivers import DeviceError, DeviceLostError, DeviceState, models, open_device
from hapticd_drivers import dhd_backend as dhd

ROOT = Path(__file__).resolve().parent.parent
PROTOTYPES = json.loads((ROOT / "tests" / "data" / "fd_sdk_prototypes.json").read_text())

# C type names as the recorded prototypes write them, to the ctypes type that passes them.
_C_TYPES = {
    "void": None,
    "int": ctypes.c_int,
    "unsigned int": ctypes.c_uint,
    "char": ctypes.c_byte,  # 'char ID': signed, as the SDK's IDs are (-1: the default device)
    "unsigned char": ctypes.c_ubyte,
    "bool": ctypes.c_bool,
    "double": ctypes.c_double,
    "const char*": ctypes.c_char_p,
    "double*": ctypes.POINTER(ctypes.c_double),
    "int*": ctypes.POINTER(ctypes.c_int),
    "unsigned short*": ctypes.POINTER(ctypes.c_ushort),
}


def mismatches(api) -> list[str]:
    """Where the declarations ``api`` (name: (restype, argtypes)) differ from the recorded
    prototypes: one line per call."""
    recorded = PROTOTYPES["prototypes"]
    out = [f"{n}: declared, no prototype" for n in sorted(set(api) - set(recorded))]
    out += [f"{n}: prototype, not declared" for n in sorted(set(recorded) - set(api))]
    for name in sorted(set(api) & set(recorded)):
        restype, argtypes = api[name]
        ret, args = recorded[name]
        if restype is not _C_TYPES[ret] or list(argtypes) != [_C_TYPES[a] for a in args]:
            out.append(f"{name}: not {ret} {name}({', '.join(args)})")
    return out


def test_every_declaration_matches_the_sdk_prototype():
    assert mismatches(dhd._API) == []


def test_a_declaration_that_differs_from_its_prototype_is_found():
    wrong = dict(dhd._API)
    wrong["dhdSetBrakes"] = (ctypes.c_int, [ctypes.c_ubyte, ctypes.c_byte])
    wrong["drdIsInitialized"] = (ctypes.c_int, [ctypes.c_byte])
    del wrong["dhdErrorGetLast"]
    assert mismatches(wrong) == [
        "dhdErrorGetLast: prototype, not declared",
        "dhdSetBrakes: not int dhdSetBrakes(int, char)",
        "drdIsInitialized: not bool drdIsInitialized(char)",
    ]


def _opened(path, **kw):
    dev = open_device("dhd", library=path, **kw)
    dev.open()
    return dev


def test_devices_open_through_drd_so_its_state_is_theirs(libdhd):
    """The fake answers drdIsInitialized only for a device opened through drdOpenID, as the
    documentation leaves it; the backend opens through DRD, so the state is known."""
    path, lib = libdhd
    lib.fake_reset(1)
    lib.dhdOpenID.argtypes = lib.drdIsInitialized.argtypes = [ctypes.c_byte]
    lib.drdIsInitialized.restype = ctypes.c_bool
    raw = lib.dhdOpenID(0)
    assert raw == 0 and not lib.drdIsInitialized(0)  # a DHD handle: DRD does not know it
    lib.dhdClose(0)
    dev = _opened(path)
    assert dev.calibrated() is True
    dev.enable_forces(True)
    dev.write_force(np.array([0.0, 1.0, 0.0]))
    assert lib.fake_is_enabled(0) == 1
    dev.close()
    assert lib.fake_is_open(0) == 0


@pytest.mark.parametrize("how", ["index", "serial_number"])
def test_a_device_without_a_serial_number_opens_by_index_and_says_so(libdhd, how):
    path, lib = libdhd
    lib.fake_reset(2)
    for i in range(2):
        lib.fake_set_serial(i, 0)
    if how == "serial_number":
        with pytest.raises(DeviceError) as info:
            _opened(path, serial_number=10002)
        msg = str(info.value)
        assert "no device with serial number 10002 among 2" in msg
        assert "without a readable serial number, to be picked by 'index': index 0, 1" in msg
        lib.fake_set_in_use(0, 1)
        with pytest.raises(
            DeviceError, match=r"could not be opened to ask: index 0 \(DHD_ERROR_DEVICE_IN_USE"
        ):
            _opened(path, serial_number=10002)
        assert [lib.fake_is_open(i) for i in range(2)] == [0, 0]
        return
    dev = _opened(path, index=1)
    assert dev.info.serial == "index 1" and dev.info.model == "omega.3"
    lib.fake_unplug(1)
    with pytest.raises(DeviceLostError, match=r"dhd omega\.3 index 1 \(no serial number\)"):
        dev.read_state(DeviceState())
    dev.close()


def test_the_velocity_estimator_is_primed_and_a_timeout_keeps_the_last_velocity(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    lib.fake_set_state(0, 0.01, 0.0, 0.0, 0.2, -0.1, 0.0)
    dev = _opened(path)
    dev.enable_forces(True)
    st = DeviceState()
    dev.read_state(st)  # primed: the first read has its velocity
    np.testing.assert_allclose(st.velocity, [0.2, -0.1, 0.0])
    # A window no two updates fall into: every velocity read times out.
    lib.fake_set_velocity_window(0.0)
    lib.fake_set_state(0, 0.02, 0.0, 0.0, 0.5, 0.5, 0.5)
    for _ in range(dhd.MAX_VELOCITY_TIMEOUTS):
        dev.read_state(st)
        np.testing.assert_allclose(st.position, [0.02, 0.0, 0.0])
        np.testing.assert_allclose(st.velocity, [0.2, -0.1, 0.0])  # the last one kept
    lib.fake_set_velocity_window(60.0)
    dev.read_state(st)  # an estimate again: the count starts over
    np.testing.assert_allclose(st.velocity, [0.5, 0.5, 0.5])
    lib.fake_set_velocity_window(0.0)
    for _ in range(dhd.MAX_VELOCITY_TIMEOUTS):
        dev.read_state(st)
    dev.close()


def test_a_velocity_timeout_that_never_ends_fails_the_device_saying_what_happened(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    dev = _opened(path)
    lib.fake_set_velocity_stuck(0, 1)
    st = DeviceState()
    for _ in range(dhd.MAX_VELOCITY_TIMEOUTS):
        dev.read_state(st)
    with pytest.raises(DeviceError) as info:
        dev.read_state(st)
    assert not isinstance(info.value, DeviceLostError)
    msg = str(info.value)
    assert msg.startswith("dhd omega.3 index 0, serial 10001: the SDK's velocity estimator")
    assert f"timed out on {dhd.MAX_VELOCITY_TIMEOUTS + 1} reads in a row" in msg
    assert "DHD_ERROR_TIMEOUT" in msg
    dev.close()


def test_discover_never_closes_a_device_this_process_holds(libdhd, monkeypatch):
    """dhdOpenID on an open device returns its ID: discover() must not close it."""
    path, lib = libdhd
    monkeypatch.setenv("HAPTICD_LIBDHD", path)
    lib.fake_reset(2)
    dev = _opened(path, index=0)
    dev.enable_forces(True)
    (entry,) = dhd.discover()
    assert entry["found"][0] == "10001 (index 0, calibrated, open in this process)"
    assert entry["found"][1] == "10002 (index 1, calibrated)"
    assert lib.fake_is_open(0) == 1 and lib.fake_is_enabled(0) == 1
    dev.read_state(DeviceState())
    dev.write_force(np.array([1.0, 0.0, 0.0]))
    buf = (ctypes.c_double * 3)()
    lib.fake_get_force(0, buf)
    assert list(buf) == [1.0, 0.0, 0.0]
    # Nor does opening another device by serial number (which asks each in turn).
    other = _opened(path, serial_number=10002)
    assert lib.fake_is_open(0) == 1 and lib.fake_is_enabled(0) == 1
    other.close()
    dev.close()
    assert lib.fake_is_open(0) == 0


def test_brakes_are_released_before_forces_after_a_calibration(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    lib.fake_set_calibrated(0, 0)
    dhd.calibrate(library=path, index=0)
    assert lib.fake_brakes(0) == 1
    dev = _opened(path)
    dev.enable_forces(True)
    log = lib.fake_log().decode()
    assert re.search(r"brakes 0 0;enable 0 1;", log), log
    dev.write_force(np.array([0.0, 0.0, 2.0]))
    buf = (ctypes.c_double * 3)()
    lib.fake_get_force(0, buf)
    assert list(buf) == [0.0, 0.0, 2.0]  # braked, it would have rendered nothing
    dev.close()


def test_a_device_without_brakes_or_memory_check_opens_and_renders(libdhd):
    """DHD_ERROR_NOT_AVAILABLE from dhdSetBrakes or dhdCheckControllerMemory: a device
    without them, not a failure."""
    path, lib = libdhd
    lib.fake_reset(1)
    lib.fake_set_basic(0, 1)
    dev = _opened(path)
    dev.enable_forces(True)
    dev.write_force(np.array([0.0, 0.0, 2.0]))
    buf = (ctypes.c_double * 3)()
    lib.fake_get_force(0, buf)
    assert list(buf) == [0.0, 0.0, 2.0]
    dev.close()


def test_an_sdk_older_than_the_minimum_is_refused_naming_both_versions(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    lib.fake_set_sdk_version(3, 14, 0, 1234)
    with pytest.raises(DeviceError) as info:
        _opened(path)
    msg = str(info.value)
    assert "Force Dimension SDK 3.14.0-1234, older than 3.16.0, the minimum" in msg
    assert lib.fake_is_open(0) == 0
    lib.fake_set_sdk_version(3, 16, 0, 0)
    _opened(path).close()


def test_a_library_that_is_not_the_sdk_is_refused():
    libm = ctypes.util.find_library("m")
    if libm is None:
        pytest.skip("no libm to stand for a library that is not the SDK")
    with pytest.raises(DeviceError, match=r"is not Force Dimension's SDK \(it has no dhdGet"):
        dhd.load_libdhd(libm)


def test_a_device_type_not_in_the_table_is_refused_and_closed(libdhd):
    path, lib = libdhd
    lib.fake_reset(2)
    lib.fake_set_type(1, 91)  # DHD_DEVICE_CUSTOM
    with pytest.raises(DeviceError) as info:
        _opened(path, serial_number=10002)
    msg = str(info.value)
    assert msg.startswith("dhd type 91 custom index 1, serial 10002: its device type")
    assert "not in hapticd's model table" in msg and "omega.3" in msg
    assert lib.fake_is_open(1) == 0 and lib.fake_is_enabled(1) == 0


@pytest.mark.parametrize(
    ("system_type", "model", "radius_m", "limit_n"),
    [(33, "omega.3", 0.075, 12.0), (63, "delta.3", 0.15, 20.0), (60, "Falcon", 0.04, 8.0)],
)
def test_the_model_table_gives_each_device_its_workspace_and_limits(
    libdhd, system_type, model, radius_m, limit_n
):
    path, lib = libdhd
    lib.fake_reset(1)
    lib.fake_set_type(0, system_type)
    dev = _opened(path, max_force_n=min(8.0, limit_n))
    row = models.by_name(model)
    assert dev.info.model == model and dev.info.workspace_radius_m == radius_m
    assert dev.info.max_stiffness_n_per_m == row.max_stiffness_n_per_m
    assert dev.info.max_damping_n_s_per_m == row.max_damping_n_s_per_m
    dev.close()
    if limit_n < 12.0:  # the default rated force, 12 N, is above a Falcon's
        with pytest.raises(DeviceError, match=rf"max_force_n 12 N is above the {model}'s"):
            _opened(path)
        assert lib.fake_is_open(0) == 0


def test_a_named_model_is_known_before_opening_and_checked_on_opening(libdhd):
    path, lib = libdhd
    lib.fake_reset(1)
    dev = open_device("dhd", library=path, model="omega.3")
    assert dev.info.workspace_radius_m == 0.075  # before it is opened: hapticd check
    assert np.isnan(open_device("dhd", library=path).info.workspace_radius_m)
    with pytest.raises(DeviceError, match=r"says Falcon, but the device is a omega\.3"):
        open_device("dhd", library=path, model="Falcon", max_force_n=8.0).open()
    assert lib.fake_is_open(0) == 0
    with pytest.raises(DeviceError, match=r"unknown model 'omega\.9'; hapticd knows delta\.3"):
        open_device("dhd", library=path, model="omega.9")
    with pytest.raises(DeviceError, match=r"max_force_n 12 N is above the Falcon's force limit"):
        open_device("dhd", library=path, model="Falcon")  # the default 12 N


def test_the_docs_carry_the_model_table():
    text = (ROOT / "docs" / "devices.md").read_text()
    assert models.markdown_table() in text


def test_error_codes_are_named_as_the_sdk_names_them():
    assert dhd.error_name(dhd.DHD_ERROR_TIMEOUT) == "DHD_ERROR_TIMEOUT"
    assert dhd.error_name(dhd.DHD_ERROR_CONFIGURATION) == "DHD_ERROR_CONFIGURATION"
    assert dhd.error_name(14) == "DHD_ERROR_CONFIGURATION"
    assert dhd.error_name(2) == "DHD_ERROR_COM" and dhd.error_name(5) == "DHD_ERROR_NO_DEVICE_FOUND"
    assert dhd.error_name(99) == "error code 99"


def test_discover_lists_devices_without_serial_numbers_and_of_unknown_types(libdhd, monkeypatch):
    path, lib = libdhd
    monkeypatch.setenv("HAPTICD_LIBDHD", path)
    lib.fake_reset(3)
    lib.fake_set_serial(0, 0)
    lib.fake_set_type(2, 91)
    lib.fake_set_calibrated(2, 0)
    entries = {e["model"]: e for e in dhd.discover()}
    assert entries["omega.3"]["found"] == [
        "index 0 (no serial, calibrated)",
        "10002 (index 1, calibrated)",
    ]
    assert entries["omega.3"]["sdk"] == "3.17.5-0"
    assert entries["type 91 custom"]["found"] == [
        "10003 (index 2, NOT calibrated, NOT in hapticd's model table: refused)"
    ]
    assert [d["serial"] for d in entries["omega.3"]["devices"]] == [None, "10002"]
    assert [lib.fake_is_open(i) for i in range(3)] == [0, 0, 0]
