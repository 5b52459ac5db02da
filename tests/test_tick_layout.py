"""The tick's interface generated from its stages' declarations (hapticd.physics.tick): the
call's frame fields, state blocks, plan blocks, switches and parameter slots follow from
what each stage module declares, and agree with the frame and the renderer's stages."""

from __future__ import annotations

import itertools
import math

import pytest

from hapticd.physics import frame, kernels, stages
from hapticd.physics.tick import layout, step
from hapticd.physics.tick.layout import Declaration


def test_every_field_the_call_addresses_is_a_frame_field():
    assert set(step.FIELDS) <= frame.NAMES
    assert len(set(step.FIELDS)) == len(step.FIELDS)
    for d in step.DECLARATIONS:
        assert set(d.reads) | set(d.writes) <= frame.NAMES, d.name


def test_the_renderers_stages_read_and_write_what_their_modules_declare():
    by_name = {d.name: d for d in step.STAGES}
    for cls in (stages.Friction, stages.Forces, stages.Environment, stages.Dynamics):
        assert (cls.reads, cls.writes) == (by_name[cls.name].reads, by_name[cls.name].writes)
    for cls in (stages.Contact, stages.Friction, stages.Forces, stages.Environment):
        assert cls.kernel_stage == step.STAGE[cls.name]


def test_parameter_slots_are_disjoint_and_follow_the_switches():
    spans = sorted(step.PARAMS_AT.values())
    assert spans[0][0] == len(step.FLAG)
    for (_, hi), (lo, _) in itertools.pairwise(spans):
        assert hi == lo  # one after the other, no gap, no overlap
    by_name = {d.name: d for d in step.STAGES}
    for name, (lo, hi) in step.PARAMS_AT.items():
        assert hi - lo == len(by_name[name].params)
    assert spans[-1][1] == kernels.TICK_PARAMS
    assert kernels.TICK_FRICTION_AT + kernels.FRICTION_PARAMS == kernels.TICK_FORCES_AT


@pytest.mark.parametrize(("n", "d"), [(1, 1), (2, 3), (3, 7)])
def test_the_state_layout_tiles_its_blocks(n, d):
    got = kernels.state_layout(n, d)
    assert tuple(got) == step.STATE_BLOCKS
    at = 0
    for at_block, shape in got.values():
        assert at_block == at
        at += math.prod(shape)
    assert got["contact"][1] == (n, kernels.CONTACT_STATE)
    assert got["loop"][1] == (kernels.LOOP_HEAD + 8 * n,)


def test_a_new_stage_gets_its_slots_fields_and_state_from_its_declaration():
    """What a lab's stage (a new friction model, say) declares is all the layout needs."""
    mine = Declaration(
        "stickiness",
        fields=("device_pos", "contact_force"),
        state=(("glue", lambda n, d: (n, 2)),),
        blocks=(("table", True),),
        params=("k", "tau"),
        flag="sticky",
    )
    decls = (*step.STAGES[:3], mine, *step.STAGES[3:], *step.EXTRAS)
    assert layout.fields(decls) == step.FIELDS  # both fields were addressed already
    assert "glue" in layout.state_blocks(decls)
    assert layout.plan_blocks(decls).count("table") == 1
    slots = layout.param_slots(decls, (*step.PARAM_ORDER, "stickiness"), 9)
    assert slots["stickiness"][1] - slots["stickiness"][0] == 2
    switches = layout.flags(decls, ("first", "last"))
    assert "sticky" in switches and sorted(switches.values()) == list(range(len(step.FLAG) + 1))
    with pytest.raises(RuntimeError, match="stickiness"):
        layout.param_slots(decls, step.PARAM_ORDER, 9)


def test_every_helper_the_stages_declare_is_compiled_into_the_call():
    names = {h for h in kernels.KERNEL_HELPERS if isinstance(h, str)}
    for d in step.DECLARATIONS:
        for h in d.helpers:
            assert (h in names) if isinstance(h, str) else (h in kernels.KERNEL_HELPERS)
    assert all(hasattr(kernels, h) for h in names)
