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
from hapticd.allocation import AdaptiveState, Robustness
from hapticd.profile import (
    FingerConfig,
    HidDeviceConfig,
    Profile,
    ProfileError,
)
from hapticd.recording import Recorder, RecordingError
from hapticd.render import Renderer
from hapticd.safety import SafetyChain, SafetyParams
from hapticd.scene import Scene
from hapticd.servo import ServoLoop, summarize

BUILTIN = "builtin:"


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
        try:
            self.loop.run()
        finally:
            if self.recorder is not None:
                self.recorder.close()
        return summarize(self.loop, self.renderer.allocator, self.profile.finger_names)


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
    scene = Scene.from_config(profile.scene, profile)
    actuation = Actuation(
        [list(f.actuated_directions) for f in profile.fingers], profile.rendering.actuation_frame
    )
    rc = profile.rendering
    renderer = Renderer(
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
    limits = [min(d.info.max_force_n, profile.safety.max_force_n) for d in devices]
    sc = profile.safety
    safety = SafetyChain(
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
    recorder = None
    if record_path is not None:
        recorder = Recorder(
            record_path,
            recording.loop_fields(len(devices), actuation.n_actuators),
            profile.finger_names,
            {
                "profile": profile.name,
                "profile_path": str(profile.source),
                "rate_hz": profile.loop.rate_hz,
                "allocator": profile.rendering.allocator,
                "paced": paced,
                "force_limits_n": limits,
            },
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
    )
    clock_box.append(loop)
    return Session(profile, devices, renderer, safety, loop, recorder, emulators)
