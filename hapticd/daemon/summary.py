"""The run summary (docs/recording.md) and the control server's read-only views of the loop.

Everything here reads the loop's tick frame, its pacing statistics and its
renderer's parameters from another thread, in the loop's sleep window (see
``hapticd.daemon.server``): plain values only, timing in us, forces in N.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from hapticd.loop.servo import ServoLoop
from hapticd.loop.stats import LogHistogram

# What a telemetry frame carries of the tick frame (see hapticd.physics.frame for units): enough to
# draw the scene (positions, the object's pose) and the forces (full and rendered).
TELEMETRY_FIELDS = (
    "device_pos",
    "proxy_pos",
    "in_contact",
    "object_pos",
    "object_rot",
    "contact_force",
    "rendered_force",
    "residual_internal",
    "residual_external",
    "control_seq",
)


def _us(h: LogHistogram, q: float | None) -> float | None:
    if h.count == 0:
        return None
    v = h.max if q is None else h.percentile(q)
    return round(v * 1e6, 3)


def _fault(loop: ServoLoop) -> dict[str, Any] | None:
    f = loop.safety.fault
    return None if f is None else {"tick": f.tick, "t": f.t, "cause": f.cause, "kind": f.kind}


def _device_counts(loop: ServoLoop, i: int) -> dict[str, int]:
    """What finger ``i``'s device driver counted (Device.counts: e.g. the SDK's saturated
    motors); empty for a device that counts nothing or cannot say."""
    try:
        return {str(k): int(v) for k, v in loop.devices[i].counts().items()}
    except Exception:  # a stand-in device without the method: the summary still comes
        return {}


def pressed(bits: int) -> list[int]:
    """The buttons down in a device's ``buttons`` bit set, as indices (bit i: button i)."""
    return [i for i in range(32) if (bits >> i) & 1]


def summarize(loop: ServoLoop, finger_names: Sequence[str]) -> dict[str, Any]:
    """The run summary: ticks, rate, timing in us, forces in N, the end and any fault."""
    st = loop.stats
    span = st.last_start - st.first_start
    achieved = (st.ticks - 1) / span if st.ticks > 1 and span > 0 else float("nan")
    pe = st.period_error if loop.paced else LogHistogram()
    return {
        "ticks": st.ticks,
        "duration_s": round(st.ticks * loop.period, 6),
        "paced": loop.paced,
        "rate_hz": {"target": loop.rate_hz, "achieved": round(achieved, 3)},
        "period_error_us": {
            "p50": _us(pe, 50),
            "p99": _us(pe, 99),
            "p99.9": _us(pe, 99.9),
            "max": _us(pe, None),
        },
        "period_error_hist_us": [[round(e * 1e6, 4), c] for e, c in pe.nonzero()],
        "overruns": st.overruns if loop.paced else 0,
        "overruns_per_10k": round(1e4 * st.overruns / max(st.ticks - 1, 1), 3) if loop.paced else 0,
        "reanchors": st.reanchors,
        "tick_compute_us": {
            "p50": _us(st.compute, 50),
            "p99": _us(st.compute, 99),
            "p99.9": _us(st.compute, 99.9),
            "max": _us(st.compute, None),
        },
        "allocator": loop.renderer.method,
        "max_rendered_force_n": round(max(st.max_force, default=0.0), 6),
        "fingers": {
            name: {
                "max_force_n": round(st.max_force[i], 6),
                "contact_ticks": st.contact_ticks[i],
                "device_counts": _device_counts(loop, i),
            }
            for i, name in enumerate(finger_names)
        },
        "clamped_ticks": loop.safety.clamped_ticks,
        "rate_limited_ticks": loop.safety.rate_limited_ticks,
        "end_reason": loop.end_reason,
        "events": [{"t": round(t, 6), "event": e} for t, e in loop.events],
        "fault": _fault(loop),
    }


def scene_status(loop: ServoLoop) -> dict[str, Any]:
    """The scene as the loop renders it now, with what a viewer needs to draw it: the
    object's extent in its body frame (m), the ground and walls (solid where normal . x <=
    offset_m) and each finger's radius (m)."""
    r = loop.renderer
    frame = loop.frame
    vertices = r.obj.shape.vertices
    return {
        "shape": type(r.obj.shape).__name__,
        "fixed": r.obj.fixed,
        "mass_kg": r.param("mass_kg"),
        "stiffness_n_per_m": r.param("stiffness_n_per_m"),
        "damping_n_s_per_m": r.param("damping_n_s_per_m"),
        "friction": r.param("friction"),
        "position_m": frame.object_pos.tolist(),
        "bounds_m": [vertices.min(axis=0).tolist(), vertices.max(axis=0).tolist()],
        "surfaces": [
            {"name": s.name, "normal": list(s.normal), "offset_m": s.offset}
            for s in r.scene.surfaces
        ],
        "finger_radii_m": list(r.radii),
    }


def telemetry(loop: ServoLoop) -> dict[str, Any]:
    """A sample of the live tick frame for watchers: positions m, forces N."""
    frame = loop.frame
    sample: dict[str, Any] = {"tick": loop.stats.ticks, "t": loop.now()}
    sample.update(frame.sample(TELEMETRY_FIELDS))
    sample["in_contact"] = [bool(v) for v in sample["in_contact"]]
    sample["buttons"] = [pressed(b) for b in frame.buttons.tolist()]
    sample["force"] = frame.device_force.tolist()
    sample["fault"] = loop.safety.fault is not None
    sample["allocator"] = loop.renderer.method
    sample["overruns"] = loop.stats.overruns
    return sample


def passivity_status(loop: ServoLoop) -> dict[str, Any]:
    """The passivity stage on the last tick: whether it runs, each finger's observed energy
    (J, negative: the display generated energy) and added damping (N s/m); zeros when off."""
    frame = loop.frame
    return {
        "enabled": "passivity" in loop.renderer.stage_names,
        "energy_j": frame.passivity_energy.tolist(),
        "damping_n_s_per_m": frame.passivity_damping.tolist(),
    }


def status(loop: ServoLoop) -> dict[str, Any]:
    """A snapshot of the loop for the control API."""
    st = loop.stats
    pe = st.period_error
    buttons = loop.frame.buttons.tolist()
    deadman = loop.safety.deadman_status()
    return {
        "tick": st.ticks,
        "t": loop.now(),
        "rate_hz": loop.rate_hz,
        "paced": loop.paced,
        "overruns": st.overruns,
        "period_error_us": {
            "p50": pe.percentile(50) * 1e6 if pe.count else None,
            "p99": pe.percentile(99) * 1e6 if pe.count else None,
            "max": pe.max * 1e6,
        },
        "fault": _fault(loop),
        "devices": [
            {
                "serial": d.info.serial,
                "model": d.info.model,
                "connected": loop.bank.lost[i] is None,
                "force_limit_n": loop.safety.limits[i],
                "buttons": pressed(buttons[i]),
                "deadman": deadman[i],
            }
            for i, d in enumerate(loop.devices)
        ],
        # Each finger touching the object now (contact_begin and contact_end follow it).
        "in_contact": [bool(v) for v in loop.frame.in_contact.tolist()],
        "allocator": loop.renderer.method,
        "stages": loop.renderer.stage_names,
        "passivity": passivity_status(loop),
        "scene": scene_status(loop),
        "control_seq": loop.control_seq,
        "recording": None if loop.recorder is None else loop.recorder.status(),
        "realtime": None if loop.rt_report is None else loop.rt_report.to_json(),
        "stopping": loop.stop_reason,
    }
