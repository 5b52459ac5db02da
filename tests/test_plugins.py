"""Plugins from a lab's own package (entry points): the example procedure (PEST) and the
example backend (springtip) installed by pip into a folder of their own and run end to
end; broken, misshapen, doubly registered and built-in-shadowing entry points refused by
name (fake installs: a dist-info folder on the path)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml

from hapticd.allocation import allocate_many
from hapticd.allocation import plugins as allocation_plugins
from hapticd.cli import main
from hapticd.daemon.session import build_session
from hapticd.experiment import ExperimentError, load_experiment, parse_experiment, procedure
from hapticd.experiment.procedure import Procedure
from hapticd.experiment.store import TrialStore
from hapticd.experiment.study import run_model_subject
from hapticd.loop.commands import SetParam
from hapticd.params import PARAMS, ParamError
from hapticd.profile import ProfileError, load_profile
from tests.conftest import GRASP_PROFILE, IN_PROCESS, ROOT

EXAMPLES = ROOT / "examples" / "plugins"
PEST = EXAMPLES / "hapticd-procedure-pest"
SPRINGTIP = EXAMPLES / "hapticd-backend-example"
TIKHONOV = EXAMPLES / "hapticd-allocator-tikhonov"


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """The example packages installed (pip, offline, no dependencies) into a folder of
    their own: on PYTHONPATH for a subprocess, on sys.path for this one; the test venv is
    not touched."""
    target = tmp_path_factory.mktemp("site")
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--disable-pip-version-check",
         "--no-deps", "--no-build-isolation", "--no-index", "--target", str(target),
         str(PEST), str(SPRINGTIP), str(TIKHONOV)],
        check=True, timeout=300, capture_output=True,
    )  # fmt: skip
    return target


@pytest.fixture
def on_path(installed, monkeypatch):
    """The installed examples importable here, the procedures found again (and forgotten
    after the test)."""
    monkeypatch.syspath_prepend(str(installed))
    procedure.reload_plugins()
    allocation_plugins.reload_plugins()
    yield installed
    procedure.reload_plugins()
    allocation_plugins.reload_plugins()
    for name in [m for m in sys.modules if m.startswith(("hapticd_procedure", "hapticd_alloc"))]:
        sys.modules.pop(name)


def _pest_file(tmp_path: Path, **settings) -> Path:
    data = yaml.safe_load((PEST / "stiffness-pest.yaml").read_text())
    data["profile"] = str(ROOT / "configs" / "grasp-stiffness.yaml")
    data["settings"].update(settings)
    path = tmp_path / "pest.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_the_built_ins_register_through_the_same_table():
    assert procedure.names()[:3] == ["constant_stimuli", "staircase", "quest_plus"]
    for name in procedure.BUILTIN:
        cls = procedure.get(name)
        assert issubclass(cls, Procedure) and cls.name == name
        assert procedure.package_of(name) == "hapticd"
        assert procedure.check_plugin(name, cls) is None or cls.plans_ahead


def test_pest_runs_with_the_model_observer_resumes_and_is_analysed(on_path, tmp_path, capsys):
    """The installed PEST: the file checks, the model observer runs a subject into a
    store, a resumed session is the uninterrupted one, analyze reports its tracks."""
    path = _pest_file(tmp_path, max_trials=8, min_step=0.001)
    assert main(["experiment", "check", str(path)]) == 0
    out = capsys.readouterr().out
    assert "procedure    pest (from package hapticd-procedure-pest)" in out
    exp = load_experiment(path)
    proc = exp.proc
    assert type(proc).__name__ == "Pest" and exp.n_blocks == 1 and exp.trials_per_block == 8
    db = tmp_path / "pest.sqlite"
    with TrialStore.for_experiment(db, exp) as store:
        assert run_model_subject(exp, "s01", store, 5) == 8
        rows = [r for r in store.trials(None) if r["status"] == "complete"]
    assert len(rows) == 8 and {r["block"] for r in rows} == {0}
    # Resume: the tracks replayed from the first half of the rows go on as the whole did.
    answers = {r["plan_index"]: bool(r["comparison_more"]) for r in rows}
    rest = proc.session(exp, 5, lambda t: answers[t.index], rows[:4])
    assert [t.comparison for t, _ in rest] == [r["comparison"] for r in rows[4:]]
    assert main(["experiment", "analyze", str(db), "--boot", "0"]) == 0
    out = capsys.readouterr().out
    assert "pest tracks" in out and "s01" in out.split("pest tracks")[1]
    # Where the package is not installed, the store's fit is still analysed, said so.
    sys.path.remove(str(on_path))
    procedure.reload_plugins()
    assert main(["experiment", "analyze", str(db), "--boot", "0"]) == 0
    got = capsys.readouterr()
    assert "unknown procedure 'pest'" in got.err and "pest tracks" not in got.out


def test_pest_moves_by_its_step_rules(on_path):
    """Five correct answers pass the Wald test at the start (5 > 0.75 x 5 + 1): harder by
    the step, the same step again, doubled on the third and fourth moves; then a wrong
    run is a reversal, which halves the step."""
    from hapticd_procedure_pest import Pest, PestSettings

    pest = Pest(PestSettings(start=0.8, step=0.1, min_step=0.01, max_distance=0.9))
    t = pest.new_track(0, "c", 50.0, 1)
    seen = []
    for _ in range(4):
        for _ in range(5):
            pest.update(t, True, pest.comparison(t))
        seen.append(t.distance)
    assert seen == pytest.approx([0.7, 0.6, 0.4, 0.0], abs=1e-9)
    pest.update(t, False, pest.comparison(t))
    pest.update(t, False, pest.comparison(t))  # 0 correct of 2 < 0.75 x 2 - 1: easier
    assert t.reversals == pytest.approx([0.0], abs=1e-9)
    assert (t.step, t.distance) == pytest.approx((0.2, 0.2))
    assert not pest.done(t) and pest.estimate(t)["jnd"] == pytest.approx(10.0)


def test_pest_settings_errors_name_the_key(on_path, tmp_path):
    data = yaml.safe_load(_pest_file(tmp_path).read_text())
    data["settings"]["stepp"] = 0.1
    with pytest.raises(ExperimentError, match=r"settings\.stepp"):
        parse_experiment(data, "x.yaml")
    data["settings"].pop("stepp")
    data["repetitions"] = 4
    with pytest.raises(ExperimentError, match="repetitions are for constant_stimuli"):
        parse_experiment(data, "x.yaml")


def test_the_example_backend_checks_runs_and_is_listed(installed, tmp_path):
    """In a process of its own (the profile schema is made from the registry when hapticd
    is imported): hapticd backends and procedures name the packages, hapticd check takes
    a profile on springtip, and a short unpaced run on --device springtip ends."""
    script = textwrap.dedent(
        f"""
        import sys
        from hapticd.cli import main
        for argv in (["backends"], ["procedures"], ["check", {str(SPRINGTIP / "springtip.yaml")!r}],
                     ["run", {str(ROOT / "configs" / "grasp-stiffness.yaml")!r}, "--device",
                      "springtip", "--unpaced", "--duration", "0.3", "--no-socket",
                      "--no-realtime", "--set", "rendering.kernels=python"]):
            print("rc", argv[0], main(argv), flush=True)
        """
    )
    env = {**os.environ, "PYTHONPATH": str(installed)}
    run = subprocess.run(
        [sys.executable, "-c", script], env=env, timeout=300, capture_output=True, text=True
    )
    out = run.stdout
    assert run.returncode == 0, run.stderr
    for cmd in ("backends", "procedures", "check", "run"):
        assert f"rc {cmd} 0" in out, out + run.stderr
    assert any(
        ln.split()[:2] == ["springtip", "hapticd-backend-example"] for ln in out.splitlines()
    )
    assert any(ln.split()[:2] == ["pest", "hapticd-procedure-pest"] for ln in out.splitlines())
    assert "fingers: thumb (springtip, 1 actuated), index (springtip, 1 actuated)" in out
    assert "300 ticks" in out


# -- bad input: fake installs ------------------------------------------------------------


def _fake_package(root: Path, dist: str, group: str, entries: dict[str, str], module: str = "",
                  source: str = "") -> None:  # fmt: skip
    """A package ``dist`` "installed" in ``root``: its dist-info (METADATA, entry points)
    and, if given, its module's source."""
    info = root / f"{dist.replace('-', '_')}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 1.0\n")
    lines = [f"[{group}]"] + [f"{k} = {v}" for k, v in entries.items()]
    (info / "entry_points.txt").write_text("\n".join(lines) + "\n")
    if module:
        (root / f"{module}.py").write_text(source)


@pytest.fixture
def fakes(tmp_path, monkeypatch):
    root = tmp_path / "site"
    root.mkdir()
    monkeypatch.syspath_prepend(str(root))
    yield root
    procedure.reload_plugins()
    allocation_plugins.reload_plugins()


PROC_SOURCE = """
from hapticd.experiment.procedure import Procedure
class Good(Procedure):
    name = "twin"
    max_trials = 5
    def ratio_range(self): return (1.0, 1.5)
    def new_track(self, *a): raise NotImplementedError
    comparison = update = done = estimate = new_track
class Half(Procedure):
    name = "half"
NotAClass = 3
"""


def test_refused_procedures_are_named_with_package_and_entry_point(fakes, tmp_path):
    _fake_package(fakes, "lab-one", "hapticd.procedures",
                  {"twin": "lab_one:Good", "half": "lab_one:Half", "three": "lab_one:NotAClass",
                   "gone": "lab_missing:X", "staircase": "lab_one:Good"},
                  "lab_one", PROC_SOURCE)  # fmt: skip
    _fake_package(fakes, "lab-two", "hapticd.procedures", {"twin": "lab_one:Good"})
    procedure.reload_plugins()
    why = {p.name: p.message() for p in procedure.problems()}
    assert set(why) == {"twin", "half", "three", "gone", "staircase"}
    assert "'lab-one' and package 'lab-two'" in why["twin"]
    assert "package 'lab-one'" in why["gone"] and "cannot be imported" in why["gone"]
    assert "wrong shape" in why["half"] and "does not implement" in why["half"]
    assert "wrong shape" in why["three"]
    assert "built-in" in why["staircase"]
    # The built-in is untouched; none of the refused is usable.
    assert procedure.get("staircase").__module__ == "hapticd.experiment.procedures"
    assert procedure.names() == ["constant_stimuli", "staircase", "quest_plus"]
    # An experiment naming a refused one is refused at check, naming package and entry point.
    data = yaml.safe_load((PEST / "stiffness-pest.yaml").read_text())
    data["procedure"] = "gone"
    with pytest.raises(ExperimentError, match=r"procedure: .*'gone' \(lab_missing:X\) of "
                       r"package 'lab-one': cannot be imported"):  # fmt: skip
        parse_experiment(data, "x.yaml")
    data["procedure"] = "nope"
    with pytest.raises(ExperimentError, match="unknown procedure 'nope'"):
        parse_experiment(data, "x.yaml")


BACKEND_SOURCE = """
from hapticd_drivers.registry import Backend
from hapticd_drivers.base import Device
class Partial(Device):
    def open(self): pass
WRONG = {"name": "wrong"}
HALF = Backend("half", "lab_dev", "Partial", "a device that cannot write", ())
"""


def test_refused_backends_are_named_and_a_profile_naming_one_is_refused(
    fakes, monkeypatch, grasp_data, write_profile, capsys
):
    from hapticd_drivers import registry

    _fake_package(fakes, "lab-dev", "hapticd.backends",
                  {"wrong": "lab_dev:WRONG", "half": "lab_dev:HALF", "broken": "lab_nope:B",
                   "sim": "lab_dev:HALF"},
                  "lab_dev", BACKEND_SOURCE)  # fmt: skip
    monkeypatch.setattr(registry, "PROBLEMS", [])
    monkeypatch.setattr(registry, "PLUGINS", {})
    monkeypatch.setattr(registry, "BACKENDS", dict(registry.BACKENDS))
    registry.load_plugins()
    why = {p.name: p.message() for p in registry.PROBLEMS}
    assert set(why) == {"wrong", "half", "broken", "sim"}
    assert "expected a hapticd_drivers.registry.Backend" in why["wrong"]
    assert "does not implement" in why["half"] and "write_force" in why["half"]
    assert "package 'lab-dev'" in why["broken"] and "cannot be imported" in why["broken"]
    assert "built-in" in why["sim"]
    assert registry.BACKENDS["sim"].module == "hapticd_drivers.sim"
    assert set(registry.BACKENDS) == set(registry.BUILTIN)
    with pytest.raises(registry.BackendUnavailableError, match=r"'broken' \(lab_nope:B\) of"):
        registry.backend("broken")
    grasp_data["fingers"][0]["device"] = {"backend": "broken"}
    with pytest.raises(ProfileError, match=r"backend 'broken' is refused: .*package 'lab-dev'"):
        load_profile(write_profile(grasp_data))
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["run", str(write_profile(grasp_data)), "--device", "broken"])
    assert "--device: hapticd.backends entry point 'broken'" in capsys.readouterr().err


# -- allocators ---------------------------------------------------------------------------

LIFT_PROFILE = ROOT / "configs" / "lift-weight.yaml"
# Each finger 2 mm into the 5 cm cube (radius 8 mm), on either side along x.
SQUEEZE = np.array([[0.031, 0.0, 0.0], [-0.031, 0.0, 0.0]])


def _lift(kernels: str, allocator: str):
    """A loop on the lift profile with ``allocator``, not running: ticks made by hand."""
    sets = [f"rendering.kernels={kernels}", f"rendering.allocator={allocator}"]
    profile = load_profile(LIFT_PROFILE, [*IN_PROCESS, *sets])
    return build_session(profile, paced=False).loop


def _squeezes(loop, n: int = 150) -> np.ndarray:
    """``n`` ticks of a squeeze that varies and lifts: each tick's rendered force, lam_a and
    object position."""
    out = []
    for k in range(n):
        squeeze = 0.002 + 0.001 * np.sin(k / 10.0)
        frame = loop.frame
        frame.device_pos[:] = SQUEEZE + np.array([[-squeeze, 0, 5e-4 * k], [squeeze, 0, 5e-4 * k]])
        frame.device_vel[:] = 0.0
        loop.renderer.run(frame)
        out.append(np.concatenate([frame.rendered_force.ravel(), frame.lam_a, frame.object_pos]))
    return np.array(out)


def test_the_example_allocator_runs_compiled_in_the_tick_as_its_python_does(on_path):
    """tikhonov, installed: named in the profile, compiled into the one call (no Python
    stage), the same forces as its Python form; the frame names it by its index in the
    allocators' list, and its lam_a is its formula on the grasp (beyond contact onset)."""
    from hapticd_allocator_tikhonov import MU

    fast = _lift("compiled", "tikhonov")
    alloc = fast.renderer.allocator
    assert alloc.native_problem is None and alloc.in_kernel
    assert fast.renderer.one_call._single  # one call: allocation is not a Python part
    python = _lift("python", "tikhonov")
    got, want = _squeezes(fast), _squeezes(python)
    assert np.abs(want[:, 6:8]).max() > 0.1  # the actuators push
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    frame = python.frame
    assert allocation_plugins.names()[int(frame.allocator)] == "tikhonov"
    # Its formula on the grasp: M_a of the actuated directions in the world, both contacts.
    act = python.renderer.allocator.actuation
    M, cols = act.submatrix(act.world_directions(frame.device_pos.tolist()), [0, 1])
    lam = frame.contact_force.reshape(-1)
    assert np.linalg.norm(lam) > 0.5 and frame.in_contact.all()
    want = np.linalg.solve(M.T @ M + MU * MU * np.eye(len(cols)), M.T @ lam)
    np.testing.assert_allclose(frame.lam_a[cols], want, rtol=1e-9)


def test_allocators_lists_and_checks_the_example_and_a_live_set_takes_it(on_path, capsys):
    assert main(["allocators"]) == 0
    rows = [ln.split()[:2] for ln in capsys.readouterr().out.splitlines()]
    assert ["tikhonov", "hapticd-allocator-tikhonov"] in rows and ["pinv", "hapticd"] in rows
    assert main(["allocators", "check", "tikhonov"]) == 0
    out = capsys.readouterr().out
    assert "ok    linear in lam" in out and "FAIL" not in out
    assert "the tick runs it compiled" in out
    # The name is the method's everywhere: a live set, and allocate_many offline.
    loop = _lift("python", "if")
    done = loop.submit(SetParam("allocator", PARAMS["allocator"].check("tikhonov")))
    loop._apply_inbox(1, loop.period)
    assert done.error is None and loop.renderer.method == "tikhonov"
    G, M, lam = allocation_plugins._probe()
    np.testing.assert_allclose(
        allocate_many("tikhonov", G[None], M, lam[None])[0], [2.0, -2.0], rtol=1e-3
    )


ALLOC_SOURCE = """
import numpy as np

def naive(G, M_a, lam):
    # Least squares by the normal equations, undamped: singular where M_a loses rank.
    return np.linalg.solve(M_a.T @ M_a, M_a.T @ lam)
naive.linear = True

# Each fails on one contact (G (6, 3)): the trajectory's first touch, or contact onset.
def boom(G, M_a, lam):
    if G.shape[1] == 3:
        raise ValueError("one contact")
    return M_a.T @ lam

def nan(G, M_a, lam):
    out = M_a.T @ lam
    if G.shape[1] == 3:
        out[0] = np.nan
    return out

def huge(G, M_a, lam):
    return M_a.T @ lam * (1e9 if G.shape[1] == 3 else 1.0)

def longer(G, M_a, lam):
    return np.zeros(M_a.shape[1] + (1 if G.shape[1] == 3 else 0))

def scalar(G, M_a, lam):
    return 0.0

def two(G, M_a):
    return M_a[0]

def _helper(M_a, lam):
    return M_a.T @ lam

def text(G, M_a, lam):
    return _helper(M_a, lam)  # numba cannot compile a call of a plain Python function

NOT_A_FUNCTION = 3
"""


@pytest.fixture
def lab_allocators(fakes):
    """Allocators of a fake package: the fragile, the failing, the misshapen and the ones
    another package or a built-in's name clashes with."""
    names = ("naive", "boom", "nan", "huge", "longer", "scalar", "two", "text")
    entries = {n: f"lab_alloc:{n}" for n in names}
    entries |= {"three": "lab_alloc:NOT_A_FUNCTION", "gone": "lab_nowhere:f"}
    entries["pinv"] = "lab_alloc:naive"
    _fake_package(fakes, "lab-alloc", "hapticd.allocators", entries, "lab_alloc", ALLOC_SOURCE)
    _fake_package(fakes, "lab-twin", "hapticd.allocators", {"naive": "lab_alloc:naive"})
    _fake_package(fakes, "lab-own", "hapticd.allocators", {"own": "lab_alloc:naive"})
    allocation_plugins.reload_plugins()
    yield fakes
    sys.modules.pop("lab_alloc", None)


def test_refused_allocators_are_named_and_a_profile_or_set_naming_one_is_refused(
    lab_allocators, capsys
):
    why = {p.name: p.message() for p in allocation_plugins.problems()}
    assert set(why) == {"naive", "scalar", "two", "three", "gone", "pinv"}
    assert "'lab-alloc' and package 'lab-twin'" in why["naive"]
    assert "returned shape ()" in why["scalar"] and "lab_alloc:scalar" in why["scalar"]
    assert "does not take (G, M_a, lam)" in why["two"]
    assert "expected a function" in why["three"]
    assert "cannot be imported" in why["gone"] and "package 'lab-alloc'" in why["gone"]
    assert "built-in" in why["pinv"]
    assert set(allocation_plugins.names()) - set(PARAMS["allocator"].choices) == {
        "boom", "nan", "huge", "longer", "text", "own"
    }  # fmt: skip
    assert main(["allocators"]) == 2  # listed, and the refused said on stderr
    err = capsys.readouterr().err
    assert "'scalar' (lab_alloc:scalar) of package 'lab-alloc'" in err
    with pytest.raises(ProfileError, match=r"allocator 'gone' is refused: .*lab_nowhere:f"):
        load_profile(LIFT_PROFILE, ["rendering.allocator=gone"])
    # A live set: refused by the loop (which knows what is installed), nothing changed.
    loop = _lift("python", "if")
    for name, match in (
        ("nope", "unknown allocator 'nope'"),
        ("two", "'two' is refused: .*does not take"),
    ):
        with pytest.raises(ParamError, match=match):
            loop.submit(SetParam("allocator", PARAMS["allocator"].check(name)))
        assert loop.renderer.method == "if"


def test_check_fails_a_fragile_allocator_naming_each_case_and_passes_its_twin(
    lab_allocators, capsys
):
    """The undamped normal equations: finite on a full-rank grasp, singular where M_a
    loses rank. The suite names the rank-change cases; the same function under another
    name (``own``, one package only) is what fails, the refusal of ``naive`` aside."""
    assert main(["allocators", "check", "own"]) == 1
    captured = capsys.readouterr()
    failed = [ln for ln in captured.out.splitlines() if ln.startswith("FAIL")]
    assert failed and all("raised" in ln or "non-finite" in ln or "jump" in ln or "beyond" in ln
                          for ln in failed)  # fmt: skip
    assert "hapticd: own fails" in captured.err
    assert main(["allocators", "check", "nope"]) == 2
    assert "unknown allocator 'nope'" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("name", "kernels", "what"),
    [
        ("boom", "python", "raised an exception"),
        ("boom", "compiled", "raised an exception"),
        ("nan", "python", "returned a NaN or infinite force"),
        ("huge", "compiled", "returned an absurd force"),
        ("longer", "python", "returned a result of the wrong shape"),
    ],
)
def test_a_failing_allocator_ends_at_zero_force_with_a_fault_naming_it(
    lab_allocators, name, kernels, what
):
    """Each plugin fails at the trajectory's first one-contact grasp: the run ends in a
    latched fault naming plugin, package and entry point; no force beyond the limit or
    non-finite was ever sent, every device ends at zero and disabled."""
    profile = load_profile(
        GRASP_PROFILE, [*IN_PROCESS, f"rendering.kernels={kernels}", f"rendering.allocator={name}"]
    )
    s = build_session(profile, paced=False)
    assert s.renderer.allocator.in_kernel and s.renderer.allocator.native_problem is None
    out = s.run()
    assert out["end_reason"] == "fault", out["end_reason"]
    cause = out["fault"]["cause"]
    assert f"allocator plugin {name!r} (package 'lab-alloc', entry point lab_alloc:{name})" in cause
    assert what in cause
    limit = profile.safety.max_force_n
    for dev in s.devices:
        assert np.all(np.isfinite(dev.forces))
        assert np.linalg.norm(dev.forces, axis=1).max() <= limit + 1e-9
        np.testing.assert_array_equal(dev.last_force, 0)
        assert not dev.enabled


def test_an_allocator_numba_cannot_compile_runs_as_python_and_says_so(lab_allocators, caplog):
    fast = _lift("compiled", "text")
    alloc = fast.renderer.allocator
    assert alloc.native_problem is not None and not alloc.in_kernel
    assert not fast.renderer.one_call._single  # allocation runs between the call's parts
    assert "'text' cannot be compiled by numba" in caplog.text
    np.testing.assert_allclose(
        _squeezes(fast, 60), _squeezes(_lift("python", "text"), 60), rtol=1e-9, atol=1e-12
    )
