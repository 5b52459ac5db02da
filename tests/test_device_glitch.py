"""One glitched device sample (a velocity no hand makes, NaN) latches a fault with zero
force and never reaches the scene: the free object stays where the run without the glitch
has it. Behind that, a free object whose state diverges anyway latches a fault and ends the
run, instead of a math error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hapticd.daemon.session import build_session
from hapticd.profile import load_profile
from tests.conftest import ROOT

LIFT = ROOT / "configs" / "lift-weight.yaml"
GLITCH_T = 3.0  # s: the cube is held in the air between both fingers
DURATION_S = 3.2


def _run(glitch=None, *, finger: int = 0, max_speed: float | None = None):
    """Run the lift unpaced; ``glitch(state)`` changes the finger's sample at GLITCH_T."""
    session = build_session(load_profile(LIFT), paced=False, duration_s=DURATION_S)
    loop = session.loop
    if max_speed is not None:
        loop.bank.max_speed_m_per_s = max_speed
    dev = session.devices[finger]
    read = dev.read_state
    forces = []

    def read_state(st):
        read(st)
        if glitch is not None and abs(loop.now() - GLITCH_T) < 1e-9:
            glitch(st)

    dev.read_state = read_state
    write = dev.write_force

    def write_force(f):
        forces.append(np.array(f, dtype=float))
        write(f)

    dev.write_force = write_force
    summary = session.run()
    return session, summary, np.array(forces)


@pytest.fixture(scope="module")
def clean():
    session, summary, _ = _run()
    assert summary["fault"] is None
    return session.loop.frame.object_pos.copy()


@pytest.mark.parametrize(
    ("what", "glitch", "expect"),
    [
        ("huge", lambda st: st.velocity.__setitem__(0, 1e150), "a speed of 1e+150 m/s"),
        ("fast", lambda st: st.velocity.__setitem__(2, -6.0), "a speed of 6 m/s"),
        ("nan velocity", lambda st: st.velocity.__setitem__(1, math.nan), "non-finite velocity"),
        ("inf position", lambda st: st.position.__setitem__(0, math.inf), "non-finite position"),
        ("far position", lambda st: st.position.__setitem__(0, 1e200), "workspace (100 m)"),
    ],
)
def test_a_glitched_sample_latches_a_fault_and_never_reaches_the_object(
    clean, what, glitch, expect
):
    session, summary, forces = _run(glitch)
    fault = summary["fault"]
    assert fault is not None and fault["kind"] == "device_state", fault
    assert fault["tick"] == round(GLITCH_T * 1000)
    assert expect in fault["cause"] and "finger 0" in fault["cause"], fault["cause"]
    if "speed" in expect:
        assert "safety.max_device_speed_m_per_s" in fault["cause"]
    assert summary["end_reason"] == "duration reached"
    assert np.all(np.isfinite(forces))
    assert np.all(forces[round(GLITCH_T * 1000) :] == 0.0)  # from the glitch's tick on
    # The glitch never entered the frame: without forces the cube falls a little, but it
    # was not flung (the unguarded run put it 8 m away, or raised a math domain error).
    pos = session.loop.frame.object_pos
    assert np.all(np.isfinite(pos))
    assert np.linalg.norm(pos - clean) < 0.05, (pos, clean)


def test_a_speed_below_the_bound_is_taken():
    _, summary, _ = _run(lambda st: st.velocity.__setitem__(2, 4.9))
    assert summary["fault"] is None


def test_a_diverged_object_latches_a_fault_and_ends_the_run():
    """With the device check out of the way (no bound), the glitch reaches the object: the
    backstop after the renderer latches ``object_state`` on that tick and ends the run."""
    _, summary, forces = _run(lambda st: st.velocity.__setitem__(0, 1e150), max_speed=math.inf)
    fault = summary["fault"]
    assert fault is not None and fault["kind"] == "object_state", fault
    assert fault["tick"] == round(GLITCH_T * 1000)
    assert "the object's state diverged" in fault["cause"]
    assert summary["end_reason"] == "the object's state diverged"
    assert np.all(np.isfinite(forces)) and np.all(forces[-1] == 0.0)


def test_a_glitch_on_one_finger_lets_the_others_samples_in():
    """The device bank copies the fingers' samples into the frame in one block when all
    pass; a glitch on the second finger still lets the first finger's sample in, and keeps
    the second's last good position, at rest, with its buttons."""
    from hapticd_drivers import DeviceState

    from hapticd.loop.device_bank import DeviceBank
    from hapticd.physics.frame import Frame

    class Scripted:
        info = None
        finished = False

        def __init__(self, samples):
            self.samples, self.k = samples, 0

        def read_state(self, st: DeviceState) -> None:
            st.position[:], st.velocity[:], st.buttons = self.samples[self.k]
            self.k += 1

    good = [((0.01, 0.02, 0.03), (0.1, 0.0, 0.0), 1), ((0.02, 0.02, 0.03), (0.2, 0.0, 0.0), 2)]
    bad = [((0.0, 0.01, 0.0), (0.0, 0.3, 0.0), 4), ((0.0, 0.5, 0.0), (0.0, math.nan, 0.0), 8)]
    faults = []
    bank = DeviceBank(
        [Scripted(good), Scripted(bad)],
        reconnect=False,
        on_fault=lambda *a: faults.append(a),
        on_event=None,
        max_speed_m_per_s=5.0,
    )
    frame = Frame(2, 2)
    bank.read(frame, 0, 0.0)
    assert not faults
    assert frame.device_pos.tolist() == [[0.01, 0.02, 0.03], [0.0, 0.01, 0.0]]
    assert frame.device_vel.tolist() == [[0.1, 0.0, 0.0], [0.0, 0.3, 0.0]]
    bank.read(frame, 1, 1e-3)
    assert len(faults) == 1 and "finger 1" in faults[0][2] and faults[0][3] == "device_state"
    assert frame.device_pos.tolist() == [[0.02, 0.02, 0.03], [0.0, 0.01, 0.0]]
    assert frame.device_vel.tolist() == [[0.2, 0.0, 0.0], [0.0, 0.0, 0.0]]
    assert frame.buttons.tolist() == [2, 8]


@pytest.mark.parametrize("where", range(6))
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_sample_with_one_non_finite_item_among_zeros_is_refused(where, bad):
    """The one check of a sample (the device bank's, and the one call's, compiled) refuses a
    NaN or an infinity in any item, also when every other item is zero."""
    from hapticd.physics.kernels import plausible

    sample = [0.0] * 6
    sample[where] = bad
    assert not plausible(*sample, 5.0, 100.0)
    assert plausible(*[0.0] * 6, 5.0, 100.0)
    assert plausible(0.0, 0.0, 99.0, 0.0, -4.9, 0.0, 5.0, 100.0)
    assert not plausible(0.0, 0.0, 0.0, 0.0, 5.1, 0.0, 5.0, 100.0)
