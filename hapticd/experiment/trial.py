"""One planned trial: what every procedure decides and the store keeps (a module of its
own, below the experiment file's and the procedures': both use it)."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class PlannedTrial:
    """One trial: its place (``index`` in the session, ``block``, ``position`` in the
    block), the condition, the standard and comparison values (the varied parameter's
    SI unit), the ratio, whether the comparison is the first interval, the break (s)
    to take before it (0: none), and whether it is a practice trial (``make_practice``:
    a negative index, block -1; never analysed)."""

    index: int
    block: int
    position: int
    condition: str
    standard: float
    ratio: float
    comparison: float
    comparison_first: bool
    break_before_s: float
    practice: bool = False

    def as_dict(self) -> dict:
        return asdict(self)
