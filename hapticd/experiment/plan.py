"""The trial plan: every trial of one subject's session, in order, from an experiment
file and a seed (deterministic for the same seed)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hapticd.experiment.spec import Experiment, ExperimentError
from hapticd.experiment.trial import PlannedTrial


def williams_rows(n: int) -> list[list[int]]:
    """A balanced Latin square (Williams 1949) of ``n`` conditions (0..n-1): ``n`` rows
    for an even ``n``, ``2n`` for an odd one (the rows and their reverses: an odd square
    cannot balance first-order carryover in ``n`` rows). Over all rows each condition
    holds each position equally often and each ordered pair of conditions is
    neighbours equally often (once for an even ``n``, twice for an odd one)."""
    first, lo, hi = [0], 1, n - 1
    while len(first) < n:  # 0, 1, n-1, 2, n-2, ...
        if len(first) % 2:
            first.append(lo)
            lo += 1
        else:
            first.append(hi)
            hi -= 1
    rows = [[(c + i) % n for c in first] for i in range(n)]
    return rows + [r[::-1] for r in rows] if n % 2 else rows


def condition_order(
    exp: Experiment, rng: np.random.Generator, subject_index: int | None = None
) -> list[str]:
    """The order in which a subject meets the conditions, by
    ``randomization.counterbalance``: none: ``blocks.condition_order`` (random draws
    from ``rng``); latin_square: row ``subject_index`` (mod the rows) of
    ``williams_rows``; abba: the listed order then its reverse (A B B A), reversed for
    every other subject (B A A B). ExperimentError when a counterbalanced design gets no
    subject index."""
    names = [c.name for c in exp.conditions]
    scheme = exp.randomization.counterbalance
    if scheme == "none":
        if exp.blocks.condition_order == "random":
            return [names[i] for i in rng.permutation(len(names))]
        return names
    if subject_index is None:
        raise ExperimentError(
            f"{exp.source}: randomization.counterbalance {scheme} needs the subject's index "
            "(its place in the file's subjects, or --subject-index)"
        )
    if scheme == "latin_square":
        rows = williams_rows(len(names))
        return [names[i] for i in rows[subject_index % len(rows)]]
    half = names if subject_index % 2 == 0 else names[::-1]
    return half + half[::-1]


def _block_order(
    exp: Experiment, rng: np.random.Generator, subject_index: int | None
) -> list[tuple[str, float]]:
    b = exp.blocks
    # Each entry is one pass of a condition: abba presents each condition twice, each
    # pass holding half of its blocks of every standard.
    passes = condition_order(exp, rng, subject_index)
    per_pass = b.per_standard * len(set(passes)) // len(passes)
    standards = list(exp.varied.standards)
    if b.standard_order == "ascending":
        standards.sort()
    out = []
    if b.nesting == "condition_outer":
        for c in passes:
            ss = (
                [standards[i] for i in rng.permutation(len(standards))]
                if (b.standard_order == "random")
                else standards
            )
            out += [(c, s) for s in ss for _ in range(per_pass)]
    else:
        if b.standard_order == "random":
            standards = [standards[i] for i in rng.permutation(len(standards))]
        out = [(c, s) for s in standards for c in passes for _ in range(per_pass)]
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


def make_plan(exp: Experiment, seed: int, subject_index: int | None = None) -> list[PlannedTrial]:
    """Every trial of one session of ``exp``, in order; the same list for the same seed
    (and subject index).

    Blocks follow ``exp.blocks`` (a block: one condition and one standard), the
    conditions in ``condition_order`` (a counterbalanced design needs the subject's
    ``subject_index``); within a block each comparison appears repetitions /
    blocks.per_standard times in pseudo-random order; breaks follow ``exp.breaks``.
    """
    rng = np.random.default_rng(seed)
    trials: list[PlannedTrial] = []
    br = exp.breaks
    for b, (cond, standard) in enumerate(_block_order(exp, rng, subject_index)):
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


@dataclass(frozen=True)
class Balance:
    """How balanced a list of condition orders is: ``positions[c][p]`` counts the
    orders with condition ``c`` at position ``p``, ``carryover[a][b]`` the times ``b``
    directly follows ``a`` (conditions in ``conditions``' order); the spreads are max
    minus min of a position's counts (the worst position) and of the counts of ordered
    pairs of different conditions. Balanced: both spreads 0."""

    conditions: tuple[str, ...]
    positions: tuple[tuple[int, ...], ...]
    carryover: tuple[tuple[int, ...], ...]
    position_spread: int
    pair_spread: int

    @property
    def balanced(self) -> bool:
        return self.position_spread == 0 and self.pair_spread == 0


def balance(orders: Sequence[Sequence[str]], conditions: Sequence[str]) -> Balance:
    """The ``Balance`` of ``orders`` (each a sequence of names from ``conditions``, all
    of one length)."""
    k = {c: i for i, c in enumerate(conditions)}
    n, length = len(conditions), len(orders[0]) if orders else 0
    pos = np.zeros((n, length), dtype=int)
    pairs = np.zeros((n, n), dtype=int)
    for order in orders:
        idx = [k[c] for c in order]
        pos[idx, np.arange(length)] += 1
        np.add.at(pairs, (idx[:-1], idx[1:]), 1)
    off = pairs[~np.eye(n, dtype=bool)]
    return Balance(
        conditions=tuple(conditions),
        positions=tuple(map(tuple, pos.tolist())),
        carryover=tuple(map(tuple, pairs.tolist())),
        position_spread=int((pos.max(axis=0) - pos.min(axis=0)).max()) if length else 0,
        pair_spread=int(off.max() - off.min()) if off.size else 0,
    )


def make_practice(exp: Experiment, seed: int) -> list[PlannedTrial]:
    """The practice trials of ``exp`` (its ``practice`` section; none without one), in
    order; the same list for the same seed. They cycle through every practised
    (condition, standard, level), each cycle shuffled; indices run from -n to -1 (the
    session's own trials keep 0 on), block -1."""
    pr = exp.practice
    if pr is None:
        return []
    rng = np.random.default_rng(np.random.SeedSequence([seed, PRACTICE_STREAM]))
    cells = [
        (c, float(s), float(r))
        for c in (pr.conditions or [c.name for c in exp.conditions])
        for s in exp.practice_standards()
        for r in exp.practice_ratios()
    ]
    order: list[tuple[str, float, float]] = []
    while len(order) < pr.trials:
        order += [cells[i] for i in rng.permutation(len(cells))]
    out = []
    for k, (cond, standard, ratio) in enumerate(order[: pr.trials]):
        first = exp.interval.order == "randomized" and bool(rng.integers(2))
        out.append(
            PlannedTrial(
                index=k - pr.trials,
                block=-1,
                position=k,
                condition=cond,
                standard=standard,
                ratio=ratio,
                comparison=float(f"{standard * ratio:.12g}"),
                comparison_first=first,
                break_before_s=0.0,
                practice=True,
            )
        )
    return out


# The practice's random stream: apart from the session's (the same seed orders both).
PRACTICE_STREAM = 0x5052414354  # "PRACT"
