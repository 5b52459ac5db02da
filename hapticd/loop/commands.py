"""Control commands: each checks and applies itself to the servo loop at a tick boundary,
through the loop's verbs (enable, disable, start_recording, stop_recording, reload,
prepare_set and apply_change), never by writing or reading its fields.

The control thread builds a command and hands it to the loop
(``ServoLoop.submit``), which lets it prepare itself first, in the control thread
(``Command.prepare``: a set checks its value and works out what it stores); the
loop applies it at the start of its next tick, before the devices are read, so a
change is seen by the whole tick. A command raises ``ValueError`` (changing
nothing) when it cannot be made.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from hapticd.params import PARAMS

if TYPE_CHECKING:
    from hapticd.loop.servo import ServoLoop
    from hapticd.physics.frame import Frame
    from hapticd.physics.live import Change
    from hapticd.physics.render import Renderer
    from hapticd.physics.safety import SafetyChain
    from hapticd.recording import Recorder


# Each parameter's index, the value of its param_changed event.
_INDEX = {name: i for i, name in enumerate(PARAMS)}


class Command:
    """A change to the running loop. ``while_stopping``: may it apply during a stop ramp?
    ``event``: the kind of event (hapticd.events) the loop reports when it applies, if any."""

    while_stopping = True
    event: str | None = None

    def event_value(self) -> int:
        """The event's value (a parameter's index; -1: none)."""
        return -1

    def prepare(self, loop: ServoLoop) -> None:
        """Do what can be done before the tick, in the submitting thread (ValueError:
        refused, nothing queued); nothing by default."""

    def apply(self, loop: ServoLoop, t: float) -> Any:
        """Make the change at nominal time ``t`` (s); return a result for the caller."""
        raise NotImplementedError

    def describe(self) -> str:
        """One line for the event log."""
        return type(self).__name__.lower()


@dataclass
class SetParam(Command):
    """Set a scene, rendering or safety parameter (already checked against its spec):
    prepared when submitted (checked by the part that holds it, its stores worked out),
    applied at the tick boundary by those stores."""

    name: str
    value: Any
    change: Change | None = field(default=None, repr=False)

    event = "param_changed"

    def event_value(self) -> int:
        return _INDEX.get(self.name, -1)

    def prepare(self, loop: ServoLoop) -> None:
        self.change = loop.prepare_set(self.name, self.value)

    def apply(self, loop: ServoLoop, t: float) -> Any:
        if self.change is None:  # applied without being submitted
            loop.set_param(self.name, self.value)
        else:
            loop.apply_change(self.change)

    def describe(self) -> str:
        return f"set {self.name} {self.value}"


class Enable(Command):
    """Clear a latched fault and enable forces again (they ramp up from zero)."""

    while_stopping = False  # it would restart the force ramp and undo the stop's

    def apply(self, loop: ServoLoop, t: float) -> Any:
        loop.enable(t)

    def describe(self) -> str:
        return "enable"


class Disable(Command):
    """Turn every device's forces off."""

    def apply(self, loop: ServoLoop, t: float) -> Any:
        loop.disable()

    def describe(self) -> str:
        return "disable"


@dataclass
class RecordStart(Command):
    """Start recording every tick with ``recorder`` (its writer already running)."""

    recorder: Recorder

    event = "recording_started"

    def apply(self, loop: ServoLoop, t: float) -> Any:
        loop.start_recording(self.recorder)

    def describe(self) -> str:
        return f"record_start {self.recorder.path}"


class RecordStop(Command):
    """Stop recording; the result is the recorder, for the caller to close."""

    event = "recording_stopped"

    def apply(self, loop: ServoLoop, t: float) -> Any:
        return loop.stop_recording()

    def describe(self) -> str:
        return "record_stop"


@dataclass
class Reload(Command):
    """Switch to a renderer and safety chain built from another profile (off the loop)."""

    renderer: Renderer
    safety: SafetyChain
    source: str = ""
    frame: Frame | None = None  # built off the loop too: at the tick only a swap

    while_stopping = False  # it would restart the force ramp and undo the stop's

    def apply(self, loop: ServoLoop, t: float) -> Any:
        loop.reload(self.renderer, self.safety, t, self.frame)

    def describe(self) -> str:
        return f"reload {self.source}"
