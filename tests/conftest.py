"""Shared fixtures; every test must leave no thread, child process, socket or ring behind."""

from __future__ import annotations

import contextlib
import ctypes
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

# As the hapticd command does (hapticd.__main__), before numpy loads BLAS: one BLAS thread
# per process, not one per core spinning beside the other test worker.
for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, settings

from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile

ROOT = Path(__file__).resolve().parent.parent
GRASP_PROFILE = ROOT / "configs" / "grasp-stiffness.yaml"
# The profile overrides of a paced loop run in a test's own process: its clients (the
# test's threads) share the loop's process and GIL, and on a loaded machine stalled it
# past the rig's 0.1 s watchdog (102 ms, seen). A 1 s stall still latches a fault. The
# watchdog itself is tested in tests/test_safety.py.
IN_PROCESS_WATCHDOG_S = 1.0
IN_PROCESS = [f"safety.watchdog_s={IN_PROCESS_WATCHDOG_S}"]

pytest_plugins = ["pytester"]


def our_code_filters() -> list:
    """tracemalloc filters that keep only the blocks hapticd's and its drivers' code made:
    the two packages' own folders, wherever the clone lives (a clone named ``hapticd``
    puts the tests under a ``hapticd/`` folder too, which a pattern such as
    ``*/hapticd/*`` would match)."""
    import tracemalloc

    import hapticd_drivers

    import hapticd

    return [
        tracemalloc.Filter(True, os.path.join(os.path.dirname(os.path.abspath(m.__file__)), "*"))
        for m in (hapticd, hapticd_drivers)
    ]


def capture_writes(session) -> list[np.ndarray]:
    """The forces (3,) N each device of ``session`` is sent, in the order sent: a list the
    run fills (the devices' ``write_force`` wrapped, still writing)."""
    written: list[np.ndarray] = []
    for dev in session.devices:
        write = dev.write_force

        def write_force(f, _write=write):
            written.append(np.array(f, dtype=float))
            _write(f)

        dev.write_force = write_force
    return written


def timing_mark_problems(items) -> list[str]:
    """Tests marked ``timing`` without a reason string: each needs
    ``@pytest.mark.timing("why this needs wall-clock time")``."""
    out = []
    for item in items:
        for mark in item.iter_markers("timing"):
            reason = mark.args[0] if mark.args else mark.kwargs.get("reason")
            if len(mark.args) > 1 or not isinstance(reason, str) or not reason.strip():
                out.append(item.nodeid)
    return out


def pytest_collection_modifyitems(config, items):
    bad = timing_mark_problems(items)
    if bad:
        raise pytest.UsageError(
            "@pytest.mark.timing needs one reason string, why the test needs wall-clock "
            'time, as in @pytest.mark.timing("the achieved rate is measured"): ' + ", ".join(bad)
        )


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: half again as many workers as cores (at least 2). Part of the suite
    waits on wall-clock time (paced daemons, a rehearsal's touches, a compiler at the
    lowest priority), which a core's second worker fills: on 2 cores, quiet, the suite
    took 333 s with 2 workers and 310 s with 3. The tests that once failed so (a worker's
    stall tripping a loop's watchdog) stall their own clock now, or give an in-process
    loop a 1 s watchdog (IN_PROCESS)."""
    cores = os.cpu_count() or 1
    return max(2, cores + cores // 2)


# Deterministic generated cases in CI; more examples on demand (HYPOTHESIS_PROFILE=thorough).
# The session's own numba cache: compiled kernels (hapticd.physics.jit) neither come from nor go
# into the source tree's or the user's cache, and a background compiler that a test's auto
# run starts writes here; the session waits for it at its end (pytest_sessionfinish).
# One cache for the whole run: the first process to compile a kernel (pytest-xdist runs the
# tests in several worker processes) leaves it for the others to load. The main process
# makes it before the workers start, and they inherit it through the environment.
# A developer may name a lasting one (HAPTICD_TEST_NUMBA_CACHE=DIR): kept across runs, so
# repeated runs load the kernels instead of compiling them (numba recompiles what changed).
_SHARED_CACHE = "HAPTICD_TEST_NUMBA_CACHE"
_CACHE_MADE_HERE = _SHARED_CACHE not in os.environ
if _CACHE_MADE_HERE:
    os.environ[_SHARED_CACHE] = tempfile.mkdtemp(prefix="hapticd-tests-numba-")
NUMBA_CACHE = Path(os.environ[_SHARED_CACHE])
os.environ["NUMBA_CACHE_DIR"] = str(NUMBA_CACHE)
COMPILER_WAIT_S = 180.0

# The tree's bytecode, compiled once by the process that starts the run: where the machine
# sets PYTHONDONTWRITEBYTECODE, no process writes it, and every one of the suite's few
# hundred hapticd processes (daemons, runners, workers) compiled hapticd from source again
# (0.2 s of CPU each). Python still recompiles a module whose source is newer. The
# folders are __pycache__, which git ignores.
if _CACHE_MADE_HERE and sys.flags.dont_write_bytecode:
    import compileall

    for _tree in ("hapticd", "drivers", "tests"):
        compileall.compile_dir(ROOT / _tree, quiet=2)


def _compile_kernels_once() -> None:
    """Every kernel compiled into the run's cache before the workers start, by two
    compilers at once (``python -m hapticd.physics.jit``), the kernels shared out by source length.
    Left to the tests, each worker compiled what it first needed (10 s of CPU for all of
    them), and every run in auto mode before that rendered with the slower Python code
    and started a compiler of its own: 100 s of the suite's CPU. A failure here fails no
    test: the tests that need a kernel compile it and say why it does not."""
    import inspect

    from hapticd.physics import jit, kernels

    def size(fn) -> int:
        return len(inspect.getsource(getattr(kernels, fn) if isinstance(fn, str) else fn))

    def entry(name: str) -> int:
        return size(jit._kernel(name))

    sizes = {n: entry(n) for n in jit.SIGNATURES}
    # The one call compiles every stage's kernel and helper into itself: as much work as
    # all of them (every name in KERNEL_HELPERS, not only the entry points among them), so
    # it gets a compiler of its own and the other entry points share the second.
    sizes["tick_step"] += sum(map(size, kernels.KERNEL_HELPERS))
    with contextlib.suppress(jit.JitUnavailableError):  # one failed before: try again
        if jit.cached(list(sizes), __import__("numba").__version__):
            return  # a lasting cache (HAPTICD_TEST_NUMBA_CACHE) that holds them
    groups: list[list[str]] = [[], []]
    for name in sorted(sizes, key=sizes.get, reverse=True):
        min(groups, key=lambda g: sum(map(sizes.get, g))).append(name)
    procs = [subprocess.Popen([sys.executable, "-m", "hapticd.physics.jit", *g]) for g in groups]
    for proc in procs:
        try:
            proc.wait(timeout=COMPILER_WAIT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


if os.environ.get("PYTEST_XDIST_WORKER") is None:  # the run's first process, not a worker
    _compile_kernels_once()


def pytest_sessionfinish(session, exitstatus):
    """No background compiler outlives the session: wait (bounded) for its lock to go,
    fail the session if it does not; then the process that made the run's cache removes it."""
    from hapticd.physics import jit

    deadline = time.monotonic() + COMPILER_WAIT_S
    while jit.compiling(NUMBA_CACHE) and time.monotonic() < deadline:
        time.sleep(0.2)
    if jit.compiling(NUMBA_CACHE):
        print(f"\na background kernel compiler still runs after {COMPILER_WAIT_S:.0f} s")
        session.exitstatus = 1
        return
    if _CACHE_MADE_HERE:  # the main process (xdist's workers inherit the folder), last
        shutil.rmtree(NUMBA_CACHE, ignore_errors=True)


settings.register_profile(
    "ci",
    derandomize=True,
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("thorough", max_examples=5000, deadline=None)
# HYPOTHESIS_PROFILE=thorough (or pytest's --hypothesis-profile thorough) for a deliberate
# search: random cases, 5000 each. The ci profile: 150 derandomized cases per property,
# the same every run (300 before: every event the properties report, the rare branches
# they count, still occurs at 150; the properties of the seven heaviest files took 153 s
# of CPU at 300, 100 s at 150).
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


class AtTick:
    """A stage that calls ``action(frame)`` on tick ``tick``: insert it into a renderer's
    plan (``renderer.insert(AtTick(...), after="allocation")``) to act at a known tick."""

    name = "test hook"

    def __init__(self, tick, action) -> None:
        self.tick, self.action = tick, action

    def run(self, frame) -> None:
        if int(frame.tick) == self.tick:
            self.action(frame)


def _children() -> set[int]:
    """Live (or unreaped) child processes of this test process."""
    me = os.getpid()
    out = set()
    # Each thread's children, from the kernel's own list (no walk of every process's stat).
    tasks = f"/proc/{me}/task"
    read = False
    for tid in os.listdir(tasks):
        with contextlib.suppress(OSError), open(f"{tasks}/{tid}/children") as f:
            out.update(int(p) for p in f.read().split())
            read = True
    if read:
        return out
    for entry in os.scandir("/proc"):  # a kernel without the children lists
        if not entry.name.isdigit():
            continue
        try:
            stat = Path(entry.path, "stat").read_text()
        except OSError:
            continue
        # Field 4 is the parent pid; the name in field 2 may hold spaces, so split after ')'.
        if int(stat.rpartition(")")[2].split()[1]) == me:
            out.add(int(entry.name))
    return out


def _sockets() -> set[str]:
    out = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:"):
            out.add(f"{fd}:{target}")
    return out


def _rings() -> set[str]:
    """Recording rings this process holds open (anonymous memory files), or left by name."""
    out = {p.name for p in Path("/dev/shm").glob(f"hapticd-ring-{os.getpid()}-*")}
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            if os.readlink(f"/proc/self/fd/{fd}").startswith("/memfd:hapticd-ring"):
                out.add(f"fd {fd}")
    return out


@pytest.fixture(autouse=True)
def private_socket(tmp_path, monkeypatch):
    """A daemon started without --socket serves here, never in the user's runtime dir."""
    monkeypatch.setenv("HAPTICD_SOCKET", str(tmp_path / "default.sock"))


@pytest.fixture(autouse=True)
def no_real_usb_libraries(monkeypatch):
    """No test opens the machine's libusb or hidapi (there is no hardware here, and their
    contexts keep a netlink socket for the life of the process): the usb and hid backends
    run on their emulated library seams, and discovery reports the libraries as missing."""
    monkeypatch.setitem(sys.modules, "libusb_package", None)
    monkeypatch.setitem(sys.modules, "hid", None)


@pytest.fixture(autouse=True)
def no_leaks():
    """Fail a test that leaves threads, child processes, sockets or recording rings behind."""
    before = set(threading.enumerate()), _children(), _sockets(), _rings()
    yield
    deadline = time.monotonic() + 3.0
    while True:
        now = set(threading.enumerate()), _children(), _sockets(), _rings()
        leaked = {
            "threads": [t.name for t in now[0] - before[0] if t.is_alive()],
            "child processes": sorted(now[1] - before[1]),
            "sockets": sorted(now[2] - before[2]),
            "recording rings": sorted(now[3] - before[3]),
        }
        leaked = {k: v for k, v in leaked.items() if v}
        if not leaked:
            return
        if time.monotonic() > deadline:
            pytest.fail(f"test leaked {leaked}")
        time.sleep(0.02)


@pytest.fixture
def grasp_data() -> dict:
    return yaml.safe_load(GRASP_PROFILE.read_text())


@pytest.fixture
def write_profile(tmp_path):
    """Write a profile dict to a YAML file in tmp_path; trajectory paths stay builtin."""

    def _write(data: dict, name: str = "profile.yaml") -> Path:
        path = tmp_path / name
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        return path

    return _write


@pytest.fixture
def live(tmp_path):
    """A paced grasp run serving its control socket in a thread (recording directory: tmp_path):
    session, socket, recording, out (its control server as "server"; the run's summary as
    "summary" when it ends)."""
    sock = tmp_path / "hapticd.sock"
    rec = tmp_path / "live.hrec"
    session = build_session(
        load_profile(GRASP_PROFILE, IN_PROCESS),
        paced=True,
        duration_s=4.0,
        record_path=rec,
        record_dir=tmp_path,
    )
    server = ControlServer(session, sock)
    server.start()
    out = {"server": server}
    runner = threading.Thread(target=lambda: out.update(summary=session.run()), name="test-loop")
    runner.start()
    try:
        yield session, sock, rec, out
    finally:
        session.loop.request_stop("test over")
        runner.join(timeout=10)
        server.close()


def kill_writer(rec) -> None:
    """SIGKILL a Recorder's writer process and wait until it has ended (the recorder reaps
    it, as it would a writer that died); fail after 10 s."""
    pid = rec.status()["writer_pid"]
    fd = os.pidfd_open(pid)
    try:
        os.kill(pid, signal.SIGKILL)
        ended, _, _ = select.select([fd], [], [], 10.0)
        assert ended, f"the writer process {pid} outlived SIGKILL for 10 s"
    finally:
        os.close(fd)


class ServerHold:
    """Holds a control server's thread (appended to its ``periodic`` tasks, run in that
    thread): ``hold()`` and the thread stops at its next periodic round, nothing served
    or drained, until ``release()``; ``held`` is set while it waits."""

    def __init__(self, server) -> None:
        self.armed, self.held, self.released = (threading.Event() for _ in range(3))
        server.periodic.append(self)

    def __call__(self) -> None:
        if self.armed.is_set():
            self.armed.clear()
            self.held.set()
            self.released.wait(10)

    def hold(self) -> None:
        """Hold the server at its next periodic round (within about 0.1 s); wait till then."""
        self.released.clear()
        self.armed.set()
        assert self.held.wait(10), "the server thread did not reach its periodic tasks"

    def release(self) -> None:
        self.held.clear()
        self.released.set()


def wait_for(read, what, *, until=bool, timeout_s=20.0, poll_s=0.02):
    """Call ``read()`` every ``poll_s`` s until ``until(value)`` holds and return that value;
    at ``timeout_s`` s fail the test, naming ``what`` it waited for and the last value read."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = read()
        if until(value):
            return value
        if time.monotonic() >= deadline:
            seen = repr(value)
            seen = seen if len(seen) <= 400 else seen[:400] + "..."
            pytest.fail(f"timed out after {timeout_s:g} s waiting for {what}; last seen: {seen}")
        time.sleep(poll_s)


def wait_for_tick(client, tick, limit_s=5.0):
    """Wait until the daemon behind ``client`` has reached tick ``tick``; fail at ``limit_s``."""
    return wait_for(
        lambda: client.status()["tick"],
        f"tick {tick}",
        until=lambda k: k >= tick,
        timeout_s=limit_s,
    )


def _build_fake_sdk(out_dir: Path, drd: bool) -> tuple[str, ctypes.CDLL]:
    from tests.fakes.fake_sdk import build

    try:
        out = build(out_dir, drd)
    except RuntimeError as exc:
        pytest.skip(str(exc))
    lib = ctypes.CDLL(str(out))
    lib.fake_set_state.argtypes = [ctypes.c_int] + [ctypes.c_double] * 6
    lib.fake_get_force.argtypes = [ctypes.c_int, ctypes.POINTER(ctypes.c_double)]
    lib.fake_get_force_sum.argtypes = [ctypes.c_int, ctypes.POINTER(ctypes.c_double)]
    lib.fake_set_buttons.argtypes = [ctypes.c_int, ctypes.c_uint]
    lib.fake_set_velocity_window.argtypes = [ctypes.c_double]
    dp = ctypes.POINTER(ctypes.c_double)
    lib.fake_set_path.argtypes = [ctypes.c_int, ctypes.c_int, dp, dp]
    lib.fake_force_log.argtypes = [ctypes.c_int, dp, ctypes.c_int]
    lib.fake_set_saturation.argtypes = [ctypes.c_int, ctypes.c_double]
    lib.fake_get_torque_and_gripper.argtypes = [ctypes.c_int, dp]
    for name_ in ("fake_max_force", "fake_effector_mass"):
        getattr(lib, name_).restype = ctypes.c_double
    lib.fake_log.restype = ctypes.c_char_p
    return str(out), lib


# The fake SDK's switches back to older behaviours (tests/fakes/fake_dhd.c, FAKE_LEGACY_*).
FAKE_LEGACY = {"drd_any_handle": 1, "no_velocity_window": 2, "open_twice_fails": 4, "no_codes": 8}
FAKE_LEGACY_ALL = sum(FAKE_LEGACY.values())


@pytest.fixture(scope="session")
def _fake_libdrd(tmp_path_factory):
    return _build_fake_sdk(tmp_path_factory.mktemp("drd"), True)


@pytest.fixture(scope="session")
def _fake_libdhd(tmp_path_factory):
    return _build_fake_sdk(tmp_path_factory.mktemp("dhd"), False)


def _fresh(lib) -> None:
    """No device left open in the fake, and none in the backend's list of devices this
    process holds (a test that ends with a device open leaves it there)."""
    from hapticd_drivers import dhd_backend

    lib.fake_reset(0)
    dhd_backend._HELD.clear()


@pytest.fixture
def libdhd(_fake_libdrd):
    """The fake Force Dimension SDK a profile's ``library`` points at, as the real libdrd:
    the DHD calls and the DRD ones (opening, initialisation state, automatic
    initialisation), compiled from tests/fakes/fake_dhd.c, behaving as the SDK documents:
    (path, ctypes handle with the fake's own controls). Skips when there is no C
    compiler."""
    _fake_libdrd[1].fake_set_legacy(0)
    _fresh(_fake_libdrd[1])
    return _fake_libdrd


@pytest.fixture(params=["documented", "legacy"])
def libdhd_both(request, _fake_libdrd):
    """``libdhd``, once as the SDK documents it and once with every older behaviour the
    fake can switch back to (FAKE_LEGACY): what the backend must survive either way."""
    _fake_libdrd[1].fake_set_legacy(FAKE_LEGACY_ALL if request.param == "legacy" else 0)
    _fresh(_fake_libdrd[1])
    yield _fake_libdrd
    _fake_libdrd[1].fake_set_legacy(0)


@pytest.fixture
def libdhd_only(_fake_libdhd):
    """A fake libdhd without the DRD calls: (path, ctypes handle)."""
    _fake_libdhd[1].fake_set_legacy(0)
    _fresh(_fake_libdhd[1])
    return _fake_libdhd


@pytest.fixture
def idle_server(tmp_path):
    """A control server on a grasp session whose loop does not run (for requests that need
    no ticks: reload, the subject prompt, connection limits)."""
    session = build_session(load_profile(GRASP_PROFILE), paced=False)
    srv = ControlServer(session, tmp_path / "hapticd.sock")
    srv.start()
    try:
        yield srv
    finally:
        srv.close()


def fill_every_place(server):
    """Clients holding every place of the control ``server``: its subscribers' places with
    event subscriptions, the rest with clients that just sent a request (none idle)."""
    from hapticd.control import ControlClient

    clients = []
    try:
        for i in range(server.max_clients):
            c = ControlClient(server.path, timeout_s=5.0)
            clients.append(c)
            if i < server.max_subscribers:
                c.events_subscribe()
            else:
                c.status()
    except BaseException:
        for c in clients:
            c.close()
        raise
    return clients


@pytest.fixture
def chromium() -> str:
    """The system's Chromium (the browser tests' headless page), or skip saying how to
    get it."""
    from tests import cdp

    exe = cdp.find_chromium()
    if exe is None:
        pytest.skip(
            "no chromium (/usr/bin/chromium): apt-get install chromium (.ci/run installs it "
            "when run as root)"
        )
    return exe
