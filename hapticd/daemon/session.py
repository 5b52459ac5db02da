"""A run of the daemon: the servo loop built from a profile, and its live changes."""

from __future__ import annotations

import logging
import os
import platform
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from hapticd_drivers import Device, registry
from hapticd_drivers.emulator import DeltaEmulator

from hapticd import recording
from hapticd.allocation import plugins as allocation_plugins
from hapticd.daemon.build import (
    build_devices,
    build_mounts,
    build_renderer,
    build_safety,
    load_trajectories,
    realtime_settings,
)
from hapticd.daemon.summary import summarize
from hapticd.loop.commands import Command, RecordStart, RecordStop, Reload
from hapticd.loop.event_ring import DEFAULT_CAPACITY
from hapticd.loop.servo import Applied, ServoLoop, TickClock
from hapticd.physics.frame import Frame
from hapticd.physics.render import Renderer
from hapticd.physics.safety import SafetyChain
from hapticd.profile import Profile, ProfileError, load_profile
from hapticd.protocol import ProtocolError
from hapticd.recording import Recorder, RecordingError, files, ring

log = logging.getLogger("hapticd")

APPLY_TIMEOUT_S = 2.0
APPLY_POLL_S = 0.05  # how often a command's wait looks whether the loop has ended, s
MAX_PROFILE_BYTES = 1 << 20  # a profile to reload is a few KiB; more is not a profile


def record_directory(profile: Profile, given: str | Path | None = None) -> Path:
    """Where ``record_start`` over the socket may write: ``given`` (``--record-dir``), else
    the profile's ``recording.directory``, else the service's state directory."""
    if given is not None:
        return Path(given).absolute()
    if profile.recording.directory is not None:
        return profile.resolve_path(profile.recording.directory).absolute()
    return files.state_directory().absolute()


def check_profile_file(path: Path) -> None:
    """ProfileError unless ``path`` is a regular file of at most MAX_PROFILE_BYTES: a reload
    must not read /dev/zero forever or wait on a FIFO in the control thread."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise ProfileError(f"{path}: cannot read profile: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
    finally:
        os.close(fd)
    if not stat.S_ISREG(st.st_mode):
        raise ProfileError(f"{path}: not a regular file; a profile is a YAML file")
    if st.st_size > MAX_PROFILE_BYTES:
        raise ProfileError(
            f"{path}: {st.st_size} bytes; a profile may be at most {MAX_PROFILE_BYTES} bytes"
        )


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
    record_dir: Path = field(default_factory=lambda: files.state_directory().absolute())
    # `hapticd run --set KEY=VALUE` values: a reload of the running file keeps them.
    overrides: list[str] = field(default_factory=list)

    def run(self) -> dict[str, Any]:
        """Run the loop to its end; then flush and close whatever recording is open. A
        recording that failed raises RecordingError with the run's ``summary`` attached;
        its ``recording`` block says what was written and what was ``lost``."""
        rec_status = None
        failed: RecordingError | None = None
        try:
            self.loop.run()
        finally:
            if self.loop.recorder is not None:
                rec = self.loop.stop_recording()
                try:
                    rec_status = rec.close()
                except RecordingError as exc:
                    failed = exc
                    rec_status = rec.status()  # the final counts and the error
        summary = summarize(self.loop, self.profile.finger_names)
        if rec_status is not None:
            # Ticks the loop handed over that are not in the file (the writer failed or
            # the file went); ``dropped`` ones never reached the ring.
            lost = max(rec_status["ticks"] - rec_status["written"], 0)
            summary["recording"] = {**rec_status, "lost": lost}
        if failed is not None:
            failed.summary = summary  # type: ignore[attr-defined]
            raise failed
        return summary

    # -- live changes, called from the control thread (never from the loop) ---------------

    def apply(self, command: Command, timeout_s: float = APPLY_TIMEOUT_S) -> Applied:
        """Hand ``command`` to the loop and wait for its tick boundary.

        ProtocolError ``stopped`` once the loop has ended (the message says why: "the daemon
        stopped: trajectory ended"); TimeoutError if the loop does not get there in time
        (not running); ValueError with the loop's reason if it refused (nothing changed).
        """
        self._check_running()
        done = self.loop.submit(command)
        deadline = time.monotonic() + timeout_s
        while not done.wait(min(APPLY_POLL_S, max(deadline - time.monotonic(), 0.0))):
            self._check_running()  # the loop may end while the command waits
            if time.monotonic() >= deadline:
                raise TimeoutError(
                    "the loop did not reach a tick boundary in time (is it running?)"
                )
        if done.error is not None:
            raise ValueError(done.error)
        return done

    def move(self, finger: str | int, position_m: list[float]) -> dict[str, Any]:
        """Send finger ``finger``'s virtual device (backend virtual) towards ``position_m``
        (3,) m in the world; the reply names the finger and the target taken (in the world,
        brought inside the device's workspace). ProtocolError for an unknown finger or one
        whose device is not virtual. It needs no tick boundary: the device follows its
        latest target when the loop reads it."""
        names = self.profile.finger_names
        i = finger if isinstance(finger, int) else names.index(finger) if finger in names else -1
        if not 0 <= i < len(names):
            raise ProtocolError("bad_value", f"no finger {finger!r}; fingers: {list(names)}")
        dev = self.devices[i]
        move_to = getattr(dev, "move_to", None)
        if move_to is None:
            raise ProtocolError(
                "rejected",
                f"finger {names[i]}'s device ({dev.info.model} {dev.info.serial}) is not "
                "virtual: only a virtual device (backend: virtual) is moved over the socket",
            )
        mount = self.loop.bank.mounts[i]
        taken = move_to(mount.point_to_device(np.asarray(position_m, dtype=float)))
        world = mount.point_to_world(np.asarray(taken, dtype=float))
        return {"finger": names[i], "target_m": [float(c) for c in world]}

    def _check_running(self) -> None:
        """ProtocolError ``stopped`` if the loop has ended: no command will apply any more."""
        loop = self.loop
        if loop.end_reason and not loop.running:
            raise ProtocolError("stopped", f"the daemon stopped: {loop.end_reason}")

    def record_start(self, path: str | Path, *, overwrite: bool = False) -> dict[str, Any]:
        """Start recording every tick to ``path``, inside ``record_dir`` (a relative name
        resolves there; anything outside is refused); the reply names the first tick."""
        if self.loop.recorder is not None:
            raise ValueError(f"already recording to {self.loop.recorder.path}; stop it first")
        rec = make_recorder(
            self.profile,
            path,
            self.loop.renderer,
            self.loop.safety,
            paced=self.loop.paced,
            overwrite=overwrite,
            root=self.record_dir,
            devices=self.devices,
        )
        try:
            done = self.apply(RecordStart(rec))
        except BaseException:
            rec.discard()  # only its header: ours, and useless
            raise
        return {"applied_at_tick": done.tick, "path": str(rec.path)}

    def record_stop(self) -> dict[str, Any]:
        """Stop recording; returns once every tick is in the file. RecordingError (naming
        the file and how many ticks are in it) if the writer failed or the file was lost."""
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
        check_profile_file(source)
        new = load_profile(source, self.overrides if path is None else ())
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
    record_dir: str | Path | None = None,
    event_capacity: int = DEFAULT_CAPACITY,
) -> Session:
    """Create devices, renderer, safety chain, recorder and loop for ``profile``.

    ``device`` overrides every finger's backend; ``emulate`` puts the device
    emulator under the hid backend, moved along each finger's trajectory.
    ``record_path`` (the user's own argument) may be anywhere; ``record_start`` over
    the socket writes only in ``record_directory(profile, record_dir)``.
    ``event_capacity``: events the loop's ring holds until the control server drains it.
    """
    clock = TickClock()
    devices, emulators = build_devices(profile, device=device, emulate=emulate, clock=clock.now)
    if emulate and duration_s is None:
        # Emulated devices do not end; stop where the trajectories do.
        duration_s = max(float(t[0][-1] - t[0][0]) for t in load_trajectories(profile) if t)
    renderer = build_renderer(profile)
    safety = build_safety(profile, devices)
    recorder = None
    if record_path is not None:
        recorder = make_recorder(
            profile, record_path, renderer, safety, paced=paced, devices=devices
        )
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
        spin_s=profile.loop.spin_s,
        realtime_settings=realtime_settings(profile) if paced else None,
        event_capacity=event_capacity,
        wall_watchdog=paced or not on_nominal_clock(profile, device, emulate),
        clock=clock,
    )
    loop.bank.set_mounts(build_mounts(profile))
    return Session(
        profile,
        devices,
        renderer,
        safety,
        loop,
        recorder,
        emulators,
        record_directory(profile, record_dir),
    )


def on_nominal_clock(profile: Profile, device: str | None, emulate: bool) -> bool:
    """Whether every finger's device follows the loop's nominal clock (a backend that plays
    its trajectory, or the emulator under ``--emulate``): no hardware in the loop."""
    if emulate:
        return True
    return all(
        registry.backend(device or f.device.backend).plays_trajectory for f in profile.fingers
    )


def rig_meta(profile: Profile, devices: list[Device]) -> list[dict[str, Any]]:
    """Per finger, its device in the rig, for a recording's header: model and serial (as
    configured; a dhd device is named by its serial number or index), rated force (N), its
    mount (position m, roll/pitch/yaw rad, workspace scale) and its effector mass (kg; None:
    the backend has none or the SDK's default)."""
    out = []
    for f, dev in zip(profile.fingers, devices, strict=True):
        out.append(
            {
                "finger": f.name,
                "model": dev.info.model,
                "serial": dev.info.serial,
                "rated_force_n": dev.info.max_force_n,
                "mount": f.device.mount.model_dump(mode="json"),
                "effector_mass_kg": getattr(dev, "effector_mass_kg", None),
            }
        )
    return out


def make_recorder(
    profile: Profile,
    path: str | Path,
    renderer: Renderer,
    safety: SafetyChain,
    *,
    paced: bool = True,
    overwrite: bool = True,
    root: Path | None = None,
    devices: list[Device] | None = None,
) -> Recorder:
    """A recorder of every tick to ``path`` (confined to ``root`` when given), its writer
    process started (RecordingError); its header holds the rig (``rig_meta``) when
    ``devices`` are given."""
    rate = profile.loop.rate_hz
    every = profile.recording.record_every(rate)
    rec = Recorder(
        path,
        recording.loop_fields(len(profile.fingers), renderer.actuation.n_actuators),
        profile.finger_names,
        {
            "profile": profile.name,
            "profile_path": str(profile.source),
            "rate_hz": rate,
            "allocator": renderer.method,
            "allocators": list(allocation_plugins.names()),
            "paced": paced,
            "force_limits_n": list(safety.limits),
            "record_every": every,
            **({"devices": rig_meta(profile, devices)} if devices is not None else {}),
        },
        capacity=max(4096, int(2.0 * rate)),  # 2 s of ticks: the writer may pause that long
        block_when_full=not paced,
        overwrite=overwrite,
        root=root,
        record_every=every,
    )
    rec.wait_running()
    if not ring.ORDERED_STORES:
        log.warning(
            "recording on %s: the ring relies on x86's store ordering; on this CPU a record "
            "could in principle be read before it is complete (docs/daemon.md)",
            platform.machine(),
        )
    return rec
