"""The trial plan: every trial of one subject's session, in order, from an experiment
file and a seed (deterministic for the same seed)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from hapticd.experiment.spec import Experiment


@dataclass(frozen=True)
class PlannedTrial:
    """One trial: its place (``index`` in the session, ``block``, ``position`` in the
    block), the condition, the standard and comparison values (the varied parameter's
    SI unit), the ratio, whether the comparison is the first interval, and the break (s)
    to take before it (0: none)."""

    index: int
    block: int
    position: int
    condition: str
    standard: float
    ratio: float
    comparison: float
    comparison_first: bool
    break_before_s: float

    def as_dict(self) -> dict:
        return asdict(self)


def _block_order(exp: Experiment, rng: np.random.Generator) -> list[tuple[str, float]]:
    b = exp.blocks
    conditions = [c.name for c in exp.conditions]
    if b.condition_order == "random":
        conditions = [conditions[i] for i in rng.permutation(len(conditions))]
    standards = list(exp.varied.standards)
    if b.standard_order == "ascending":
        standards.sort()
    out = []
    if b.nesting == "condition_outer":
        for c in conditions:
            ss = (
                [standards[i] for i in rng.permutation(len(standards))]
                if (b.standard_order == "random")
                else standards
            )
            out += [(c, s) for s in ss for _ in range(b.per_standard)]
    else:
        if b.standard_order == "random":
            standards = [standards[i] for i in rng.permutation(len(standards))]
        out = [(c, s) for s in standards for c in conditions for _ in range(b.per_standard)]
    return out


def _within_block(exp: Experiment, rng: np.random.Generator) -> list[tuple[int, bool]]:
    """(ratio index, comparison first) for one block's trials, in order."""
    n_cmp = exp.comparisons
    reps = exp.repetitions // exp.blocks.per_standard
    if exp.interval.order == "standard_first":
        first = {i: [False] * reps for i in range(n_cmp)}
    else:
        # Each comparison first in half of its presentations (a block with an odd number
        # of them tips the odd one at random; the whole session stays balanced when the
        # repetitions are even, which the file's validation requires).
        first = {}
        for i in range(n_cmp):
            f = [True] * (reps // 2) + [False] * (reps // 2)
            if reps % 2:
                f.append(bool(rng.integers(2)))
            first[i] = [f[j] for j in rng.permutation(reps)]
    if exp.blocks.within == "shuffle":
        order = [int(i) for i in rng.permutation(np.repeat(np.arange(n_cmp), reps))]
    else:
        order = []
        for _ in range(reps):
            cycle = [int(i) for i in rng.permutation(n_cmp)]
            # No comparison twice in a row across a cycle boundary.
            if order and cycle[0] == order[-1]:
                cycle[0], cycle[-1] = cycle[-1], cycle[0]
            order += cycle
    used = dict.fromkeys(range(n_cmp), 0)
    out = []
    for i in order:
        out.append((i, first[i][used[i]]))
        used[i] += 1
    return out


def make_plan(exp: Experiment, seed: int) -> list[PlannedTrial]:
    """Every trial of one session of ``exp``, in order; the same list for the same seed.

    Blocks follow ``exp.blocks`` (a block: one condition and one standard); within a
    block each comparison appears repetitions / blocks.per_standard times in
    pseudo-random order; breaks follow ``exp.breaks``.
    """
    rng = np.random.default_rng(seed)
    trials: list[PlannedTrial] = []
    br = exp.breaks
    for b, (cond, standard) in enumerate(_block_order(exp, rng)):
        for pos, (ri, cfirst) in enumerate(_within_block(exp, rng)):
            pause = 0.0
            if pos == 0 and b > 0 and br.every_blocks and b % br.every_blocks == 0:
                pause = br.duration_s
            if pos > 0 and br.every_trials and pos % br.every_trials == 0:
                pause = br.duration_s
            ratio = exp.varied.ratios[ri]
            trials.append(
                PlannedTrial(
                    index=len(trials),
                    block=b,
                    position=pos,
                    condition=cond,
                    standard=float(standard),
                    ratio=float(ratio),
                    # 60 x 1.05 is 63.00000000000001 in binary; the file meant 63.
                    comparison=float(f"{standard * ratio:.12g}"),
                    comparison_first=cfirst,
                    break_before_s=float(pause),
                )
            )
    return trials
