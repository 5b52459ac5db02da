"""Every frame field has one writer: each stage declares what it reads and writes, the
renderer refuses a plan with two writers of a field, and every plan the bundled profiles
and experiments can make keeps the rule. The declarations are checked against what the
stages really write, tick by tick, on the bundled runs' device positions."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml

from hapticd.allocation import METHODS
from hapticd.daemon.build import build_renderer
from hapticd.loop.pulse import PulseStage
from hapticd.physics.frame import LOOP_WRITERS, NAMES, STATE, STATE_NAMES
from hapticd.physics.render import PlanError, Renderer
from hapticd.profile import load_profile, parse_profile

ROOT = Path(__file__).resolve().parent.parent
PROFILES = sorted((ROOT / "configs").glob("*.yaml")) + sorted(
    (ROOT / "configs" / "rigs").glob("*.yaml")
)
EXPERIMENTS = sorted((ROOT / "configs" / "experiments").glob("*.yaml"))
REFERENCE = ROOT / "tests" / "data" / "reference_physics.npz"
# Read on a tick before its writer runs: the value the last tick left (the pulse reports
# what the safety chain sent).
PREVIOUS_TICK = {("pulse", "device_force")}


def _renderer(path: Path, **change) -> Renderer:
    """The renderer of the profile at ``path`` with the Python stages, its data changed by
    ``change`` (key path with dots -> value; None removes the key)."""
    profile = load_profile(path, ["rendering.kernels=python"])
    if not change:
        return build_renderer(profile)
    data = profile.model_dump(exclude={"source"})
    for key, value in change.items():
        *parents, last = key.split(".")
        d = data
        for p in parents:
            d = d.setdefault(p, {})
        if value is None:
            d.pop(last, None)
        else:
            d[last] = value
    return build_renderer(parse_profile(data, profile.source))


def _assert_one_writer(r: Renderer) -> None:
    """The plan's declarations, read afresh: one writer per field, every field read
    written by the loop or by a stage before the reader (or, declared, the last tick)."""
    writes = Counter(LOOP_WRITERS.keys())
    for stage in r.stages:
        writes.update(getattr(stage, "writes", ()))
    assert max(writes.values()) == 1, [f for f, n in writes.items() if n > 1]
    before = set(LOOP_WRITERS)
    for stage in r.stages:
        for name in getattr(stage, "reads", ()):
            assert name in before or (stage.name, name) in PREVIOUS_TICK, (stage.name, name)
        before.update(getattr(stage, "writes", ()))
    assert "rendered_force" in before and "contact_force" in before
    assert set(r.writers) == set(writes)  # the renderer's own account agrees


def _variants(path: Path) -> list[dict]:
    """The changes of a profile that make different plans: the object fixed or free, with
    friction or without, the passivity controller or not."""
    out: list[dict] = [{}]
    for fixed in (True, False):
        for mu in (0.0, 0.6):
            for passivity in (False, True):
                out.append(
                    {
                        "scene.object.fixed": fixed,
                        "scene.object.mass_kg": 0.1,
                        "scene.object.friction": {"static": mu, "dynamic": mu},
                        "rendering.passivity": {"enabled": passivity},
                    }
                )
    return out


@pytest.mark.parametrize("path", PROFILES, ids=lambda p: p.stem)
def test_every_plan_of_the_bundled_profiles_has_one_writer_per_field(path):
    plans = set()
    for change in _variants(path):
        try:
            r = _renderer(path, **change)
        except Exception as exc:  # a variant the profile's schema refuses makes no plan
            assert "profile" in type(exc).__name__.lower() or isinstance(exc, ValueError), exc
            continue
        for method in METHODS:  # every allocator, as `set allocator` and experiments change
            r.set_param("allocator", method)
            _assert_one_writer(r)
        plans.add(tuple(r.stage_names))
        # The bring-up's plan: its pulse writes the rendered force in the sum's place.
        r.set_output(PulseStage(r.n_fingers, r.dt))
        _assert_one_writer(r)
        assert "output" not in r.stage_names and r.writers["rendered_force"] == "stage 'pulse'"
        assert r.writers["allocated_force"] == "stage 'allocation'"
        plans.add(tuple(r.stage_names))
    assert len(plans) >= 2  # the variants made different plans


@pytest.mark.parametrize("path", EXPERIMENTS, ids=lambda p: p.stem)
def test_every_plan_an_experiment_makes_has_one_writer_per_field(path):
    spec = yaml.safe_load(path.read_text())
    r = _renderer((path.parent / spec["profile"]).resolve())
    param = spec["varied"]["param"]
    for condition in spec["conditions"]:
        for name, value in condition.get("set", {}).items():
            r.set_param(name, value)
        for s in spec["varied"]["standards"]:
            r.set_param(param, s)
            _assert_one_writer(r)


class Writes:
    """A stage declaring it writes ``fields`` (it writes nothing: the plan is refused first)."""

    def __init__(self, name: str, *fields: str, reads: tuple[str, ...] = ()) -> None:
        self.name, self.writes, self.reads = name, fields, reads

    def run(self, frame) -> None:
        raise AssertionError("a refused stage never runs")


def test_a_plan_with_two_writers_of_a_field_is_refused_and_the_plan_stays():
    r = _renderer(ROOT / "configs" / "lift-weight.yaml")
    before = r.stage_names
    assert r.writers["rendered_force"] == "stage 'output'"
    with pytest.raises(PlanError, match="two writers of the frame's 'rendered_force'") as caught:
        r.insert(Writes("clamp", "rendered_force"), after="allocation")
    message = str(caught.value)
    assert "stage 'output'" in message and "stage 'clamp'" in message
    assert "contact -> friction" in message  # the plan it would have made
    assert r.stage_names == before
    # What the loop writes is not the renderer's to write.
    with pytest.raises(PlanError, match="'device_force': the safety chain and stage 'x'"):
        r.insert(Writes("x", "device_force"), after="forces")
    with pytest.raises(PlanError, match="'contact_force': stage 'forces' and stage 'y'"):
        r.insert(Writes("y", "contact_force"), after="scene")
    with pytest.raises(PlanError, match="'nonsense', which is no frame field"):
        r.insert(Writes("z", "nonsense"), after="scene")
    with pytest.raises(PlanError, match="reads 'passivity_force', which nothing writes"):
        r.insert(Writes("w", reads=("passivity_force",)), after="scene")
    with pytest.raises(PlanError, match="reads 'nonsense', which is no frame field"):
        r.insert(Spoils("u", "nonsense"), after="scene")
    with pytest.raises(PlanError, match="does not write 'rendered_force'"):
        r.set_output(Writes("v", "lam_a"))
    assert r.stage_names == before
    # A stage writing its own field is welcome; a fault injector says what it spoils.
    r.insert(Writes("mine", "passivity_force"), after="allocation")
    assert r.writers["passivity_force"] == "stage 'mine'"
    r.insert(Spoils("poison", "rendered_force"), after="output")
    assert r.writers["rendered_force"] == "stage 'output'"
    assert r.stage_names.index("poison") == r.stage_names.index("output") + 1


class Spoils:
    """A test's fault injector declaring the fields it spoils after their writer."""

    def __init__(self, name: str, *fields: str) -> None:
        self.name, self.corrupts = name, fields

    def run(self, frame) -> None:
        for name in self.corrupts:
            getattr(frame, name)[...] = np.nan


def test_friction_moves_what_contact_found_into_fields_of_its_own():
    lift = _renderer(ROOT / "configs" / "lift-weight.yaml")
    assert lift.writers["proxy_pos"] == "stage 'friction'"
    assert lift.writers["frictionless_proxy"] == "stage 'contact'"
    grasp = _renderer(ROOT / "configs" / "grasp-stiffness.yaml")
    assert "friction" not in grasp.stage_names
    assert grasp.writers["proxy_pos"] == "stage 'contact'"
    assert "frictionless_proxy" not in grasp.writers
    # Without ground, walls or passivity allocation's force is the rendered force itself.
    assert grasp.writers["rendered_force"] == "stage 'allocation'"


def _frame_changes(before: np.ndarray, after: np.ndarray) -> set[str]:
    return {
        n
        for n in NAMES
        if not np.array_equal(before[n], after[n], equal_nan=before[n].dtype.kind == "f")
    }


def _carried(stages) -> dict[str, object]:
    """A copy of every state the stages carry to the next tick (name -> value)."""
    out: dict[str, object] = {}
    for stage in stages:
        for name, value in getattr(stage, "carries", {}).items():
            out[name] = None if value is None else np.array(value, dtype=float)
    return out


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is b
    return a.shape == b.shape and np.array_equal(a, b, equal_nan=True)


def test_the_state_a_tick_carries_is_declared_once_with_one_writer():
    assert len(STATE_NAMES) == len(STATE)
    lift = _renderer(ROOT / "configs" / "lift-weight.yaml", **{"rendering.passivity.enabled": True})
    carriers = {name: stage.name for stage in lift.stages for name in getattr(stage, "carries", {})}
    # Everything the renderer carries, each by the writer the declaration names; the rest is
    # the safety chain's.
    assert carriers == {f.name: f.writer for f in STATE if f.writer != "the safety chain"}
    for f in STATE:
        if f.recorded_as:
            assert set(f.recorded_as.split(", ")) <= NAMES
    # A stage carrying what the declaration gives to another is refused.
    with pytest.raises(PlanError, match=r"'proxies'.* gives to 'contact'"):
        lift.insert(Carries("cache", proxies=np.zeros(3)), after="scene")
    with pytest.raises(PlanError, match=r"'my_cache'.* gives to 'no one'"):
        lift.insert(Carries("cache", my_cache=np.zeros(3)), after="scene")


class Carries:
    """A stage claiming to carry ``state`` from tick to tick."""

    def __init__(self, name: str, **state) -> None:
        self.name, self.carries = name, state

    def run(self, frame) -> None:
        raise AssertionError("a refused stage never runs")


class Probe:
    """A stage inserted after ``after``: what the frame's fields and the carried state
    became since the probe before it (the stage ``after`` ran between them)."""

    def __init__(self, after: str, stages, log: dict) -> None:
        self.name, self.after, self.stages, self.log = f"probe {after}", after, stages, log

    def run(self, frame) -> None:
        before, held = self.log["last"]
        now = _carried(self.stages())
        changed = {n for n in held if not _same(held[n], now[n])}
        self.log["written"][self.after] |= _frame_changes(before, frame.record)
        self.log["carried"][self.after] |= changed
        self.log["last"] = (frame.record.copy(), now)


@pytest.mark.parametrize("profile", ["grasp-stiffness", "lift-weight"])
def test_each_stage_writes_only_what_it_declares(profile):
    """On the bundled run's device positions (every 6th tick, 1e-3 s apart here), with
    the passivity controller on, a probe inserted after every stage (so the one call runs
    each stage as a part of its own): the fields each stage changes are among those it
    declares, and the state carried to the next tick changes only while its writer runs."""
    data = np.load(REFERENCE)
    pos = data[f"{profile}/replay/device_pos"]
    vel = data[f"{profile}/replay/device_vel"]
    r = _renderer(ROOT / "configs" / f"{profile}.yaml", **{"rendering.passivity.enabled": True})
    names = r.stage_names
    # The call publishes the scene's parameters (the scene stage's stiffness, mass and
    # allocator) when it binds a frame, before its first part: bound here first.
    r.frame.device_pos[:] = pos[0]
    r.run(r.frame)
    log: dict = {"written": {n: set() for n in names}, "carried": {n: set() for n in names}}
    for name in names:
        r.insert(Probe(name, lambda: r.stages, log), after=name)
    assert r.stage_names[1::2] == [f"probe {n}" for n in names]
    frame = r.frame
    touched = 0
    for k in range(0, len(pos), 6):
        frame.device_pos[:] = pos[k]
        frame.device_vel[:] = vel[k]
        frame.tick[()] = k
        log["last"] = (frame.record.copy(), _carried(r.stages))
        r.run(frame)
        touched += int(frame.in_contact.all())
    stages = {s.name: s for s in r.stages}
    for name in names:
        assert log["written"][name] <= set(stages[name].writes), name
        assert log["carried"][name] <= set(getattr(stages[name], "carries", {})), name
    # The run touched the object: the check saw the stages at work.
    assert {"contact_force", "rendered_force", "proxy_pos"} <= set().union(*log["written"].values())
    assert touched > 50
    carried_changed = set().union(*log["carried"].values())
    assert {"proxies", "passivity_energy", "passivity_last_pos"} <= carried_changed
    if profile == "lift-weight":
        assert {"friction_anchors", "object_state"} <= carried_changed


@pytest.mark.parametrize("stale", ["passivity_force", "env_rendered", "allocated_force"])
def test_a_contribution_left_in_the_frame_by_another_renderer_is_not_summed(stale):
    """A reload runs a new renderer on the loop's frame: what the old one's stages left in
    a contribution's field must not reach the rendered force."""
    r = _renderer(ROOT / "configs" / "lift-weight.yaml", **{"rendering.passivity.enabled": True})
    frame = r.frame.copy()
    getattr(frame, stale)[...] = 5.0  # as the last renderer left it
    frame.device_pos[:] = [[-0.06, 0.0, 0.05], [0.06, 0.0, 0.05]]  # touching nothing
    r.run(frame)
    assert not frame.in_contact.any()
    np.testing.assert_array_equal(frame.rendered_force, 0.0)
    np.testing.assert_array_equal(getattr(frame, stale), 0.0)


@pytest.mark.parametrize("path", EXPERIMENTS, ids=lambda p: p.stem)
def test_experiment_plan_prints_a_plan_for_every_bundled_experiment(path, capsys):
    import csv
    import io

    from hapticd.cli import main
    from hapticd.experiment import load_experiment, make_plan

    exp = load_experiment(path)
    assert main(["experiment", "plan", str(path), "--subject", "s1"]) == 0
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    rows = list(csv.DictReader(io.StringIO(out)))
    if exp.adaptive is None:
        assert len(rows) == len(make_plan(exp, exp.subject_seed("s1")))
        return
    # Adaptive: one row per track, in the store's block order, each at most max_trials long.
    assert [int(r["block"]) for r in rows] == list(range(exp.n_blocks))
    assert sum(int(r["max_trials"]) for r in rows) == exp.n_blocks * exp.trials_per_block
    assert {r["condition"] for r in rows} == {c.name for c in exp.conditions}
    assert {float(r["standard"]) for r in rows} == set(exp.varied.standards)
    for r in rows:
        first, standard = float(r["first_comparison"]), float(r["standard"])
        assert first > 0
        if r["side"] == "above":
            assert first > standard
        elif r["side"] == "below":
            assert first < standard
