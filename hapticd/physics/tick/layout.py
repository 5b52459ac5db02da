"""The tick's interface, generated from the stages' declarations: the frame fields the one
call addresses (``FIELDS``), the carried state's blocks (``STATE_BLOCKS``, ``state_layout``),
the plan's blocks (``PLAN``), the stages' indices (``STAGE``), the plan's switches
(``FLAG``) and each stage's parameter slots (``PARAMS_AT``). Nothing here is written by
hand but the order of the stages (``STAGES``) and of the parameters' blocks.

A stage module declares itself with ``Declaration``; this module only lays them out.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

Shape = Callable[[int, int], tuple[int, ...]]


@dataclass(frozen=True)
class Declaration:
    """What one stage of the tick is to the one call.

    ``name``: the stage's (hapticd.physics.stages'). ``reads``/``writes``: the frame fields
    it reads and writes (for a stage whose outputs depend on the plan, the renderer's stage
    says which). ``fields``: the frame fields its kernel addresses in the record (the call
    is handed their offsets). ``state``: its carried-state blocks, (name, shape(F, D)) for
    F fingers and D actuated directions in all. ``blocks``: the plan's blocks it reads,
    (name, whether the block's rows are in the plan). ``params``: its parameter slots in the
    call, in order. ``flag``: the plan's switch that turns it on (1.0), if it has one.
    ``helpers``: the functions compiled into the call for it (names of
    hapticd.physics.kernels' exports)."""

    name: str
    reads: tuple[str, ...] = ()
    writes: tuple[str, ...] = ()
    fields: tuple[str, ...] = ()
    state: tuple[tuple[str, Shape], ...] = ()
    blocks: tuple[tuple[str, bool], ...] = ()
    params: tuple[str, ...] = ()
    flag: str = ""
    helpers: tuple[str, ...] = ()


def fields(stages: tuple[Declaration, ...]) -> tuple[str, ...]:
    """Every field the stages' kernels address, in the stages' order, each once."""
    return tuple(dict.fromkeys(f for s in stages for f in s.fields))


def state_blocks(stages: tuple[Declaration, ...]) -> tuple[str, ...]:
    """The carried state's blocks' names, in the stages' order."""
    return tuple(name for s in stages for name, _ in s.state)


def state_shapes(stages: tuple[Declaration, ...], n: int, d: int) -> dict[str, tuple[int, ...]]:
    """Each block's shape for ``n`` fingers with ``d`` actuated directions in all."""
    return {name: shape(n, d) for s in stages for name, shape in s.state}


def plan_blocks(stages: tuple[Declaration, ...]) -> tuple[str, ...]:
    """The plan's blocks in the stages' order, each followed by "rows" when its rows are in
    the plan (hapticd.physics.render.OneCall fills them in this order)."""
    out: list[str] = []
    for s in stages:
        for name, rows in s.blocks:
            out += [name, "rows"] if rows else [name]
    return tuple(out)


def flags(stages: tuple[Declaration, ...], head: tuple[str, ...]) -> dict[str, int]:
    """Each switch's slot in the call's parameters: the tick's own (``head``) first, then the
    stages' in their order."""
    names = (*head, *(s.flag for s in stages if s.flag))
    return {name: i for i, name in enumerate(names)}


def param_slots(
    stages: tuple[Declaration, ...], order: tuple[str, ...], start: int
) -> dict[str, tuple[int, int]]:
    """Each stage's parameters' (first slot, past-last slot), the stages named in ``order``
    laid out one after the other from ``start``; every stage with parameters must be named."""
    by_name = {s.name: s for s in stages}
    missing = [s.name for s in stages if s.params and s.name not in order]
    if missing:
        raise RuntimeError(f"tick layout: stages with parameters but no place: {missing}")
    out, at = {}, start
    for name in order:
        n = len(by_name[name].params)
        out[name] = (at, at + n)
        at += n
    return out


def layout_of(
    blocks: tuple[str, ...], shapes: dict[str, tuple[int, ...]]
) -> dict[str, tuple[int, tuple[int, ...]]]:
    """Each block's (offset in float64 items, shape), one after the other."""
    out, at = {}, 0
    for name in blocks:
        out[name] = (at, shapes[name])
        at += math.prod(shapes[name])
    return out
