"""A run of the daemon: the servo loop built from a profile, and its live changes."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hapticd_drivers import Device
from hapticd_drivers.emulator import DeltaEmulator

from hapticd import recording
from hapticd.allocation import METHODS
from hapticd.build import (
    build_devices,
    build_renderer,
    build_safety,
    load_trajectories,
    realtime_settings,
)
from hapticd.commands import Command, RecordStart, RecordStop, Reload
from hapticd.daemon.summary import summarize
from hapticd.frame import Frame
from hapticd.profile import Profile, ProfileError, load_profile
from hapticd.recording import Recorder
from hapticd.render import Renderer
from hapticd.safety import SafetyChain
from hapticd.servo import Applied, ServoLoop

APPLY_TIMEOUT_S = 2.0


@dataclass
class Session:
    """Everything one run needs, built from a profile."""

    profile: Profile
    devices: list[Device]
    renderer: Renderer
    safety: SafetyChain
    loop: ServoLoop
    recorder: Recorder | None
    emulators: list[DeltaEmulator] = field(default_factory=list)

    def run(self) -> dict[str, Any]:
        """Run the loop to its end; then flush and close whatever recording is open."""
        rec_status = None
        try:
            self.loop.run()
        finally:
            rec = self.loop.recorder
            if rec is not None:
                self.loop.recorder = None
                rec_status = rec.close()
        summary = summarize(self.loop, self.profile.finger_names)
        if rec_status is not None:
            summary["recording"] = rec_status
        return summary

    # -- live changes, called from the control thread (never from the loop) ---------------

    def apply(self, command: Command, timeout_s: float = APPLY_TIMEOUT_S) -> Applied:
        """Hand ``command`` to the loop and wait for its tick boundary.

        TimeoutError if the loop does not get there in time (not running); ValueError
        with the loop's reason if it refused (nothing changed).
        """
        done = self.loop.submit(command)
        if not done.wait(timeout_s):
            raise TimeoutError("the loop did not reach a tick boundary in time (is it running?)")
        if done.error is not None:
            raise ValueError(done.error)
        return done

    def record_start(self, path: str | Path, *, overwrite: bool = False) -> dict[str, Any]:
        """Start recording every tick to ``path``; the reply names the first recorded tick."""
        if self.loop.recorder is not None:
            raise ValueError(f"already recording to {self.loop.recorder.path}; stop it first")
        rec = make_recorder(
            self.profile,
            path,
            self.loop.renderer,
            self.loop.safety,
            paced=self.loop.paced,
            overwrite=overwrite,
        )
        try:
            done = self.apply(RecordStart(rec))
        except BaseException:
            rec.close()
            Path(path).unlink(missing_ok=True)  # only its header: ours, and useless
            raise
        return {"applied_at_tick": done.tick, "path": str(path)}

    def record_stop(self) -> dict[str, Any]:
        """Stop recording; returns once every tick is in the file."""
        done = self.apply(RecordStop())
        rec: Recorder = done.result
        status = rec.close()
        return {"applied_at_tick": done.tick, **status}

    def reload(self, path: str | Path | None = None) -> dict[str, Any]:
        """Load ``path`` (default: the running profile's file) and switch to its scene,
        rendering and safety settings at a tick boundary. ProfileError for an invalid
        profile or one that changes what needs a restart; the old profile keeps running."""
        source = Path(path) if path is not None else self.profile.source
        if source is None:
            raise ProfileError("the running profile has no file to reload")
        new = load_profile(source)
        where = str(source)
        old = self.profile
        if new.loop != old.loop:
            raise ProfileError(f"{where}: loop settings changed; restart hapticd to change them")
        if len(new.fingers) != len(old.fingers):
            raise ProfileError(f"{where}: the number of fingers changed; restart hapticd")
        for i, (a, b) in enumerate(zip(old.fingers, new.fingers, strict=True)):
            if a.name != b.name or a.device != b.device:
                raise ProfileError(
                    f"{where}: fingers[{i}] name or device changed; restart hapticd to change "
                    "devices"
                )
        # Everything is parsed and built here, in the control thread; the loop only swaps.
        renderer = build_renderer(new)
        safety = build_safety(new, self.devices)
        frame = Frame(len(new.fingers), renderer.actuation.n_actuators)
        done = self.apply(Reload(renderer, safety, str(source), frame))
        self.profile = new
        return {"applied_at_tick": done.tick, "profile": new.name, "path": str(source)}


def build_session(
    profile: Profile,
    *,
    paced: bool = True,
    duration_s: float | None = None,
    record_path: str | Path | None = None,
    device: str | None = None,
    emulate: bool = False,
) -> Session:
    """Create devices, renderer, safety chain, recorder and loop for ``profile``.

    ``device`` overrides every finger's backend; ``emulate`` puts the device
    emulator under the hid backend, moved along each finger's trajectory.
    """
    clock_box: list[ServoLoop] = []
    devices, emulators = build_devices(
        profile, device=device, emulate=emulate, clock=lambda: clock_box[0].now()
    )
    if emulate and duration_s is None:
        # Emulated devices do not end; stop where the trajectories do.
        duration_s = max(float(t[0][-1] - t[0][0]) for t in load_trajectories(profile) if t)
    renderer = build_renderer(profile)
    safety = build_safety(profile, devices)
    recorder = None
    if record_path is not None:
        recorder = make_recorder(profile, record_path, renderer, safety, paced=paced)
    loop = ServoLoop(
        devices,
        renderer,
        safety,
        profile.loop.rate_hz,
        paced=paced,
        duration_s=duration_s,
        recorder=recorder,
        reconnect=profile.safety.reconnect,
        max_consecutive_overruns=profile.loop.max_consecutive_overruns,
        stop_ramp_s=profile.safety.stop_ramp_s,
        switch_interval_s=profile.loop.gil_switch_interval_s,
        realtime_settings=realtime_settings(profile) if paced else None,
    )
    clock_box.append(loop)
    return Session(profile, devices, renderer, safety, loop, recorder, emulators)


def make_recorder(
    profile: Profile,
    path: str | Path,
    renderer: Renderer,
    safety: SafetyChain,
    *,
    paced: bool = True,
    overwrite: bool = True,
) -> Recorder:
    """A recorder of every tick to ``path``, its writer process started (RecordingError)."""
    rate = profile.loop.rate_hz
    rec = Recorder(
        path,
        recording.loop_fields(len(profile.fingers), renderer.actuation.n_actuators),
        profile.finger_names,
        {
            "profile": profile.name,
            "profile_path": str(profile.source),
            "rate_hz": rate,
            "allocator": renderer.method,
            "allocators": list(METHODS),
            "paced": paced,
            "force_limits_n": list(safety.limits),
        },
        capacity=max(4096, int(2.0 * rate)),  # 2 s of ticks: the writer may pause that long
        block_when_full=not paced,
        overwrite=overwrite,
    )
    rec.wait_running()
    return rec
