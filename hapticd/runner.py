"""Assemble a servo loop from a profile: devices, scene, renderer, safety, recorder."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from hapticd_drivers import Device, DeviceError, open_device
from hapticd_drivers.delta import load_description
from hapticd_drivers.emulator import DeltaEmulator, FakeHidModule
from hapticd_drivers.path import Path as DevicePath

from hapticd import recording
from hapticd.actuation import Actuation
from hapticd.allocation import METHODS, AdaptiveState, Robustness
from hapticd.profile import (
    FingerConfig,
    HidDeviceConfig,
    Profile,
    ProfileError,
    load_profile,
)
from hapticd.realtime import RealtimeSettings
from hapticd.recording import Recorder, RecordingError
from hapticd.render import Renderer
from hapticd.safety import SafetyChain, SafetyParams
from hapticd.scene import Scene
from hapticd.servo import Applied, ServoLoop, summarize

BUILTIN = "builtin:"
APPLY_TIMEOUT_S = 2.0


def builtin_trajectory(name: str) -> Path:
    """Path of a bundled trajectory, e.g. 'grasp-stiffness'."""
    base = resources.files("hapticd") / "data" / "trajectories"
    path = Path(str(base / f"{name}{recording.SUFFIX}"))
    if not path.is_file():
        known = sorted(
            p.name.removesuffix(recording.SUFFIX) for p in Path(str(base)).glob("*.hrec")
        )
        raise FileNotFoundError(f"no bundled trajectory {name!r}; bundled: {', '.join(known)}")
    return path


def trajectory_path(profile: Profile, ref: str) -> Path:
    if ref.startswith(BUILTIN):
        return builtin_trajectory(ref.removeprefix(BUILTIN))
    return profile.resolve_path(ref)


def _where(profile: Profile, i: int, finger: FingerConfig, key: str) -> str:
    return f"{profile.source or '<profile>'}: fingers[{i}:{finger.name}].device.{key}"


def load_trajectories(profile: Profile) -> list[tuple[Any, Any] | None]:
    """(times, positions) per finger whose device names a trajectory, else None.

    ProfileError names the bad key.
    """
    cache: dict[Path, recording.Recording] = {}
    out: list[tuple[Any, Any] | None] = []
    for i, finger in enumerate(profile.fingers):
        dev = finger.device
        if dev.trajectory is None:
            out.append(None)
            continue
        try:
            path = trajectory_path(profile, dev.trajectory)
            rec = cache.get(path) or recording.read(path)
        except (FileNotFoundError, RecordingError) as exc:
            raise ProfileError(f"{_where(profile, i, finger, 'trajectory')}: {exc}") from None
        cache[path] = rec
        want = dev.finger or finger.name
        missing = [k for k in ("t", "device_pos") if k not in rec]
        if missing:
            raise ProfileError(
                f"{_where(profile, i, finger, 'trajectory')}: {path} lacks field(s) {missing}"
            )
        if want not in rec.fingers:
            raise ProfileError(
                f"{_where(profile, i, finger, 'finger')}: recording {path} has fingers "
                f"{rec.fingers}, not {want!r}"
            )
        j = rec.fingers.index(want)
        out.append((rec["t"], rec["device_pos"][:, j, :]))
    return out


def _emulated_seam(backend: str, emulators: list[DeltaEmulator]) -> dict[str, Any]:
    """The library seam a backend runs on when its devices are emulated."""
    if backend == "hid":
        return {"hid_module": FakeHidModule(emulators)}
    try:
        from hapticd_drivers.usb_emulator import EmulatedUsbBackend
    except ImportError as exc:
        raise DeviceError("emulating usb devices needs pyusb: pip install 'hapticd[usb]'") from exc
    return {"usb_backend": EmulatedUsbBackend(emulators)}


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
        summary = summarize(self.loop, self.loop.renderer.allocator, self.profile.finger_names)
        if rec_status is not None:
            summary["recording"] = rec_status
        return summary

    # -- live changes, called from the control thread (never from the loop) ---------------

    def apply(self, action: dict[str, Any], timeout_s: float = APPLY_TIMEOUT_S) -> Applied:
        """Hand ``action`` to the loop and wait for its tick boundary.

        TimeoutError if the loop does not get there in time (not running); ValueError
        with the loop's reason if it refused (nothing changed).
        """
        done = self.loop.submit(action)
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
            done = self.apply({"cmd": "record_start", "recorder": rec, "value": str(path)})
        except BaseException:
            rec.close()
            Path(path).unlink(missing_ok=True)  # only its header: ours, and useless
            raise
        return {"applied_at_tick": done.tick, "path": str(path)}

    def record_stop(self) -> dict[str, Any]:
        """Stop recording; returns once every tick is in the file."""
        done = self.apply({"cmd": "record_stop"})
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
        renderer = build_renderer(new)
        safety = build_safety(new, self.devices)
        done = self.apply(
            {"cmd": "reload", "renderer": renderer, "safety": safety, "value": str(source)}
        )
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
    trajectories = load_trajectories(profile)
    clock_box: list[ServoLoop] = []
    devices: list[Device] = []
    emulators: list[DeltaEmulator] = []
    where = f"{profile.source or '<profile>'}"
    for i, (finger, traj) in enumerate(zip(profile.fingers, trajectories, strict=True)):
        cfg = finger.device
        backend = device or cfg.backend
        if emulate and backend not in ("hid", "usb"):
            raise ProfileError(f"--emulate works with the hid and usb backends, not {backend!r}")
        try:
            if backend in ("replay", "sim"):
                if traj is None:
                    raise ProfileError(
                        f"{where}: fingers[{i}:{finger.name}].device needs a trajectory"
                    )
                params = {}
                if cfg.backend == backend:
                    params = cfg.model_dump(exclude={"backend", "trajectory", "finger"})
                devices.append(
                    open_device(
                        backend,
                        times=traj[0],
                        positions=traj[1],
                        clock=lambda: clock_box[0].now(),
                        serial=f"{backend}-{finger.name}",
                        **params,
                    )
                )
                continue
            hid_cfg = (
                cfg if isinstance(cfg, HidDeviceConfig) else HidDeviceConfig(backend="hid", index=i)
            )
            kwargs: dict[str, Any] = {
                "description": hid_cfg.description,
                "serial_number": hid_cfg.serial_number,
                "index": hid_cfg.index,
                "device_watchdog_s": hid_cfg.device_watchdog_s,
            }
            if emulate:
                if traj is None:
                    raise ProfileError(
                        f"{where}: fingers[{i}:{finger.name}].device: --emulate needs a trajectory"
                    )
                serial = f"EMU-{finger.name}"
                emulators.append(
                    DeltaEmulator(
                        load_description(hid_cfg.description),
                        DevicePath(traj[0], traj[1], f"emulator {finger.name}"),
                        lambda: clock_box[0].now(),
                        serial=serial,
                    )
                )
                kwargs.update(serial_number=serial, index=0, **_emulated_seam(backend, emulators))
            devices.append(open_device(backend, **kwargs))
        except DeviceError as exc:
            raise ProfileError(f"{where}: fingers[{i}:{finger.name}].device: {exc}") from None
    if emulate and duration_s is None:
        # Emulated devices do not end; stop where the trajectories do.
        duration_s = max(float(t[0][-1] - t[0][0]) for t in trajectories if t is not None)
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


def realtime_settings(profile: Profile) -> RealtimeSettings | None:
    rt = profile.loop.realtime
    if not rt.enabled:
        return None
    return RealtimeSettings(rt.priority, rt.cpu, rt.lock_memory, rt.timer_slack_ns, rt.required)


def build_renderer(profile: Profile) -> Renderer:
    """The scene and rendering pipeline of ``profile`` (ProfileError for a bad scene)."""
    scene = Scene.from_config(profile.scene, profile)
    actuation = Actuation(
        [list(f.actuated_directions) for f in profile.fingers], profile.rendering.actuation_frame
    )
    rc = profile.rendering
    return Renderer(
        scene,
        [f.radius_m for f in profile.fingers],
        actuation,
        rc.allocator,
        robust=Robustness(
            rc.robustness.eps, rc.robustness.min_separation_m, rc.robustness.contact_onset_n
        ),
        adaptive=AdaptiveState(
            rc.adaptive.ratio_low, rc.adaptive.ratio_high, rc.adaptive.time_constant_s
        ),
        dt=1.0 / profile.loop.rate_hz,
    )


def build_safety(profile: Profile, devices: list[Device]) -> SafetyChain:
    """The safety chain of ``profile`` for ``devices`` (limit: the smaller of both)."""
    limits = [min(d.info.max_force_n, profile.safety.max_force_n) for d in devices]
    sc = profile.safety
    return SafetyChain(
        limits,
        SafetyParams(
            ramp_s=sc.ramp_s,
            max_rate_n_per_s=sc.max_force_rate_n_per_s or math.inf,
            workspace_center_m=sc.workspace_center_m,
            workspace_radius_m=sc.workspace_radius_m or math.inf,
            watchdog_s=sc.watchdog_s or math.inf,
        ),
        dt=1.0 / profile.loop.rate_hz,
    )


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
            "allocator": renderer.allocator,
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
