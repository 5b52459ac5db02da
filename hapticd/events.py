"""The loop's events, each kind declared once (docs/control.md, "Events").

``EVENTS`` names every kind a client of ``events_subscribe`` can receive, the
fields it carries besides ``event``, ``tick`` (the tick it happened on) and
``t`` (that tick's nominal time, s), and what it means. The servo loop writes
fixed-size records holding a kind's ``code`` (its index here) to a ring
(hapticd.loop.event_ring); the control server turns them into JSON lines by these
names; the client and the command line read them by name. ``FAULT_CAUSES``
names the causes a ``fault_latched`` event carries (the ring holds the index).

Standard library only: the control client imports this.
"""

from __future__ import annotations

from dataclasses import dataclass

# The optional fields an event may carry, in the order the docs list them.
OPTIONAL_FIELDS: dict[str, str] = {
    "finger": "the finger's index (the recording's finger axis); `finger_name` its name",
    "button": "the button's index on the finger's device (bit `button` of `buttons`)",
    "response": "the button's response label, when the profile maps it to `response`",
    "cause": "a name from the fault causes below; `message` the fault's text",
    "param": "the parameter's name (hapticd.params)",
    "count": "how many events were lost",
    "prompt": "the subject prompt's id (`prompt` command; null: the prompt was cleared)",
    "choice": "the answer chosen, one of the prompt's `choices`",
    "text": "a `mark`'s text",
}


@dataclass(frozen=True)
class EventKind:
    """One kind of event: its name, the optional fields it carries, what it means, and
    whether the servo loop (``loop``) or the control server (``server``) makes it."""

    name: str
    fields: tuple[str, ...]
    doc: str
    source: str = "loop"


EVENTS: tuple[EventKind, ...] = (
    EventKind(
        "contact_begin",
        ("finger",),
        "the finger touches: the frame's `in_contact` went from 0 on the tick before to 1",
    ),
    EventKind("contact_end", ("finger",), "the finger lets go: `in_contact` went from 1 to 0"),
    EventKind(
        "button_down",
        ("finger", "button", "response"),
        "a button of the finger's device was pressed: its bit of `buttons` went from 0 to 1",
    ),
    EventKind("button_up", ("finger", "button", "response"), "a button was released: 1 to 0"),
    EventKind(
        "fault_latched",
        ("cause",),
        "a safety fault latched on this tick: forces are zero until `enable`",
    ),
    EventKind(
        "trajectory_end",
        (),
        "every device's trajectory has ended (with its `hold_s`): the run ends on this tick",
    ),
    EventKind(
        "recording_started",
        (),
        "a recording began: this tick is its first record (`record_start`, or `--record` at 0)",
    ),
    EventKind(
        "recording_stopped",
        (),
        "a recording stopped: this tick is the first not recorded (`record_stop`)",
    ),
    EventKind(
        "param_changed",
        ("param",),
        "a `set` applied on this tick (its reply's `applied_at_tick`)",
    ),
    EventKind(
        "events_lost",
        ("count",),
        "the loop's event ring was full: `count` events were dropped, the last on this tick; "
        "it follows every event made before them",
        source="server",
    ),
    EventKind(
        "prompt",
        ("prompt",),
        "the subject prompt was set (`prompt` = its id) or cleared (`prompt` null); "
        "`status` shows the whole prompt",
        source="server",
    ),
    EventKind(
        "response",
        ("prompt", "choice"),
        "a `respond` answered the current prompt: `prompt` its id, `choice` the answer; "
        "the prompt is cleared",
        source="server",
    ),
    EventKind(
        "screen",
        (),
        "the subject's screen changed (`screen` command); `status` shows it",
        source="server",
    ),
    EventKind(
        "mark",
        ("text",),
        "a client's `mark` (the experiment runner's trial and interval starts and ends, "
        "the condition set), stamped with the tick it was served on",
        source="server",
    ),
)

CODES: dict[str, int] = {k.name: i for i, k in enumerate(EVENTS)}
NAMES: tuple[str, ...] = tuple(k.name for k in EVENTS)

# Why a fault latched (the ring stores the index); every other text is in the message.
FAULT_CAUSES: dict[str, str] = {
    "nonfinite_force": "a stage produced a NaN or infinite force",
    "workspace": "a finger left the safety workspace",
    "watchdog": "too long between two ticks (a stalled loop)",
    "overrun": "too many late ticks in a row (`loop.max_consecutive_overruns`)",
    "device": "a device failed (read or write error, unplugged)",
    "device_state": "a device reported a non-finite position or velocity, or a speed above "
    "`safety.max_device_speed_m_per_s` (a glitched sample)",
    "object_state": "the free object's position, velocity or spin became non-finite or absurd "
    "(the scene's dynamics diverged)",
    "exception": "a stage raised an exception",
    "setup": "the devices could not be opened",
    "realtime": "a required real-time setting could not be applied",
    "shutdown": "zeroing or closing the devices at the end failed",
    "other": "anything else",
}
CAUSE_CODES: dict[str, int] = {name: i for i, name in enumerate(FAULT_CAUSES)}

if any(f not in OPTIONAL_FIELDS for k in EVENTS for f in k.fields):
    raise RuntimeError("events: a kind names a field that OPTIONAL_FIELDS does not declare")


def kind(name: str) -> EventKind:
    """The kind called ``name``; KeyError naming the kinds there are."""
    try:
        return EVENTS[CODES[name]]
    except KeyError:
        raise KeyError(f"unknown event {name!r}; events: {', '.join(NAMES)}") from None


def markdown_table() -> str:
    """The event table and the fault-cause table of docs/control.md."""
    rows = ["| event | also carries | meaning |", "|---|---|---|"]
    for k in EVENTS:
        also = ", ".join(f"`{f}`" for f in k.fields)
        made = " (made by the control server)" if k.source == "server" else ""
        rows.append(f"| `{k.name}` | {also} | {k.doc}{made} |")
    rows += ["", "| field | meaning |", "|---|---|"]
    rows += [f"| `{name}` | {doc} |" for name, doc in OPTIONAL_FIELDS.items()]
    rows += ["", "| fault cause | meaning |", "|---|---|"]
    rows += [f"| `{name}` | {doc} |" for name, doc in FAULT_CAUSES.items()]
    return "\n".join(rows) + "\n"


if __name__ == "__main__":
    print(markdown_table(), end="")
