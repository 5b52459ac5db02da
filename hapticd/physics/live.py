"""A live change, prepared off the servo thread and made at a tick boundary by stores only.

``Renderer.prepare_set`` and ``SafetyChain.prepare_set`` check a new value and work out
everything it changes (new numbers, a new plan bound to the loop's frame) in the
caller's thread; the ``Change`` they return holds what is left for the servo thread:
item stores into arrays the tick's call already reads (a number's slots) and attribute
stores (the plan swapped in). ``apply`` makes them, allocating nothing, unless what the
change was prepared against has been changed since (another change, a reload): then it
changes nothing and says so, for the caller to prepare it again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class Change:
    """A parameter's new ``value``, prepared: what applying it stores.

    ``guards``: (holder, attribute, object) that must still be the holder's, by identity;
    ``copies``: (holder, attribute, source, its attribute), read at the boundary (state
    the running tick may still move, such as whether the proxies have started);
    ``attrs``: (holder, attribute, value); ``stores``: (item view, index, number), item
    stores into the call's arrays or the frame (hapticd.physics.frame.item_view).
    ``structural``: a new plan (a swap), not a number's slots."""

    name: str
    value: Any
    structural: bool = False
    guards: list[tuple[object, str, object]] = field(default_factory=list)
    copies: list[tuple[object, str, object, str]] = field(default_factory=list)
    attrs: list[tuple[object, str, object]] = field(default_factory=list)
    stores: list[tuple[Any, Any, float | int]] = field(default_factory=list)
    # What ``attrs`` replaced, kept here: the old plan is freed with the change, in the thread
    # that drops it (the submitter's), not on the servo thread.
    replaced: list[object] = field(default_factory=list)

    def apply(self) -> bool:
        """Make the change (at a tick boundary); False, nothing changed, when it is stale."""
        for holder, attr, expected in self.guards:
            if getattr(holder, attr) is not expected:
                return False
        for holder, attr, source, source_attr in self.copies:
            setattr(holder, attr, getattr(source, source_attr))
        replaced = self.replaced
        if len(replaced) < len(self.attrs):  # made by the preparer: the boundary only stores
            replaced.extend([None] * (len(self.attrs) - len(replaced)))
        for j, (holder, attr, value) in enumerate(self.attrs):
            replaced[j] = getattr(holder, attr)
            setattr(holder, attr, value)
        for view, index, x in self.stores:
            view[index] = x
        return True
