"""From a profile to the objects a run is made of: scene, renderer, safety chain, devices.

Everything that reads the profile's configuration lives here (and in the
daemon's session), so the physics and allocation modules never see it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from hapticd_drivers import Device, DeviceError, registry
from hapticd_drivers.delta import load_description
from hapticd_drivers.emulator import DeltaEmulator, FakeHidModule
from hapticd_drivers.trajectory import Trajectory, check_samples

from hapticd import recording
from hapticd.allocation import AdaptiveState, Robustness
from hapticd.allocation.actuation import Actuation
from hapticd.loop.mount import Mount
from hapticd.loop.realtime import RealtimeSettings
from hapticd.physics import jit
from hapticd.physics.passivity import PassivityParams
from hapticd.physics.render import Renderer
from hapticd.physics.safety import Deadman, SafetyChain, SafetyParams
from hapticd.physics.scene import ConvexShape, Material, Scene, SceneObject, Surface, rpy_matrix
from hapticd.profile import (
    FingerConfig,
    ObjectConfig,
    Profile,
    ProfileError,
    SceneConfig,
    SurfaceConfig,
)
from hapticd.recording import RecordingError

log = logging.getLogger("hapticd")

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


def load_trajectories(profile: Profile) -> list[tuple[Any, Any, Any] | None]:
    """(times (N,) s, positions (N, 3) m, buttons (N,) bit sets or None) per finger whose
    device names a trajectory, else None. A recording made by the loop carries its
    ``buttons``; a trajectory without that field has none (every button up). Each is
    checked as a device playing it checks it (hapticd_drivers.trajectory.check_samples):
    at least 2 samples, finite, strictly increasing times.

    ProfileError names the profile, the key and the file.
    """
    cache: dict[Path, recording.Recording] = {}
    out: list[tuple[Any, Any, Any] | None] = []
    for i, finger in enumerate(profile.fingers):
        ref = getattr(finger.device, "trajectory", None)  # not every backend has one
        if ref is None:
            out.append(None)
            continue
        try:
            path = trajectory_path(profile, ref)
            rec = cache.get(path) or recording.read(path)
        except (OSError, ValueError, RecordingError) as exc:  # ValueError: a NUL in the path
            raise ProfileError(f"{_where(profile, i, finger, 'trajectory')}: {exc}") from None
        cache[path] = rec
        want = finger.device.finger or finger.name
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
        buttons = None
        if "buttons" in rec:
            if rec["buttons"].shape != (rec.ticks, len(rec.fingers)):
                raise ProfileError(
                    f"{_where(profile, i, finger, 'trajectory')}: {path}'s buttons field has "
                    f"shape {rec['buttons'].shape[1:]}, expected ({len(rec.fingers)},): one "
                    "bit set per finger"
                )
            buttons = rec["buttons"][:, j]
        try:
            # The devices' own check, here too: what check passes, run plays.
            out.append(check_samples(rec["t"], rec["device_pos"][:, j, :], buttons))
        except DeviceError as exc:
            raise ProfileError(
                f"{_where(profile, i, finger, 'trajectory')}: {path}, finger {want!r}: {exc}"
            ) from None
    return out


def _emulated_seam(backend: str, emulators: list[Any]) -> dict[str, Any]:
    """The library seam a backend runs on when its devices are emulated."""
    if backend == "falcon":
        from hapticd_drivers.falcon_emulator import EmulatedFalconBackend

        return {"usb_backend": EmulatedFalconBackend(emulators)}
    if backend == "hid":
        return {"hid_module": FakeHidModule(emulators)}
    try:
        from hapticd_drivers.usb_emulator import EmulatedUsbBackend
    except ImportError as exc:
        raise DeviceError("emulating usb devices needs pyusb: pip install 'hapticd[usb]'") from exc
    return {"usb_backend": EmulatedUsbBackend(emulators)}


def check_watchdog(profile: Profile, *, device: str | None = None, emulate: bool = False) -> None:
    """A real device (a hardware backend, not under ``--emulate``) runs only with the loop's
    wall-clock watchdog (``safety.watchdog_s``): ProfileError naming the finger and its
    backend if it is off, unless ``safety.allow_no_watchdog``, then a warning (every
    start). ``device`` is the ``--device`` override of every finger's backend."""
    safety = profile.safety
    if safety.watchdog_s is not None or emulate:
        return
    where = f"{profile.source or '<profile>'}"
    real = []
    for i, finger in enumerate(profile.fingers):
        name = device or finger.device.backend
        entry = registry.BACKENDS.get(name)  # an unknown name is told below, by its finger
        if entry is not None and entry.hardware:
            real.append(f"fingers[{i}:{finger.name}] on {name!r}")
    if not real:
        return
    if not safety.allow_no_watchdog:
        raise ProfileError(
            f"{where}: safety.watchdog_s is none (no watchdog), but {', '.join(real)} drives "
            "a real device: a stalled loop would leave its last force on; set "
            "safety.watchdog_s (the rigs' is 0.1 s), or safety.allow_no_watchdog: true for "
            "bench work without a subject"
        )
    log.warning(
        "%s: no watchdog (safety.allow_no_watchdog) with %s: a stalled loop leaves its "
        "last force on the device",
        where,
        ", ".join(real),
    )


def build_devices(
    profile: Profile,
    *,
    device: str | None = None,
    emulate: bool = False,
    clock: Callable[[], float],
) -> tuple[list[Device], list[Any]]:
    """The devices of ``profile`` (created, not opened), and the emulators under them.

    ``device`` overrides every finger's backend; ``emulate`` puts the device emulator
    under the hid, usb or falcon backend, moved along each finger's trajectory; ``clock`` is
    the loop's nominal time (s) for devices that play a trajectory.
    """
    where = f"{profile.source or '<profile>'}"
    check_watchdog(profile, device=device, emulate=emulate)
    trajectories = load_trajectories(profile)
    devices: list[Device] = []
    emulators: list[Any] = []  # DeltaEmulator, or FalconEmulator under the falcon backend
    for i, (finger, traj) in enumerate(zip(profile.fingers, trajectories, strict=True)):
        cfg = finger.device
        name = device or cfg.backend
        loc = f"{where}: fingers[{i}:{finger.name}].device"
        try:
            entry = registry.backend(name)
            if emulate and not entry.emulated:
                emulable = [b.name for b in registry.BACKENDS.values() if b.emulated]
                names = ", ".join(emulable[:-1]) + f" and {emulable[-1]}"
                raise ProfileError(f"--emulate works with the {names} backends, not {name!r}")
            # The profile's keys for its own backend; another backend (--device) runs on its
            # defaults, the n-th device for the n-th finger.
            if cfg.backend == name:
                kwargs = cfg.model_dump()
            else:
                kwargs = dict(entry.defaults)
                if "index" in kwargs:
                    kwargs["index"] = i
            kwargs.pop("backend", None)
            kwargs.pop("mount", None)  # hapticd's, applied by the device bank
            kwargs.pop("trajectory", None)
            kwargs.pop("finger", None)
            if (entry.plays_trajectory or emulate) and traj is None:
                raise ProfileError(f"{loc}: backend {name!r} needs a trajectory")
            if entry.plays_trajectory:
                kwargs.update(times=traj[0], positions=traj[1], clock=clock)
                if traj[2] is not None:
                    kwargs["buttons"] = traj[2]
                kwargs["serial"] = f"{name}-{finger.name}"
            elif emulate:
                serial = f"EMU-{finger.name}"
                path = Trajectory(traj[0], traj[1], f"emulator {finger.name}")
                if name == "falcon":
                    from hapticd_drivers.falcon_emulator import FalconEmulator

                    # A Falcon whose firmware was loaded and which was homed (hapticd
                    # calibrate) before the run; its time is the loop's nominal time.
                    emulators.append(
                        FalconEmulator(path, clock, serial, firmware_loaded=True, homed=True)
                    )
                    kwargs["clock"] = clock
                else:
                    desc = load_description(kwargs["description"])
                    emulators.append(DeltaEmulator(desc, path, clock, serial=serial))
                kwargs.update(serial_number=serial, index=0, **_emulated_seam(name, emulators))
            else:
                registry.preflight(name, **kwargs)
                if entry.takes_clock:
                    kwargs["clock"] = clock
            devices.append(registry.open_device(name, **kwargs))
        except DeviceError as exc:
            raise ProfileError(f"{loc}: {exc}") from None
    return devices, emulators


def build_mounts(profile: Profile) -> list[Mount]:
    """Each finger's device mount (device frame to world), in the profile's order."""
    out = []
    for f in profile.fingers:
        m = f.device.mount
        out.append(Mount.from_rpy(m.position_m, m.orientation_rpy_rad, m.workspace_scale))
    return out


def mesh_shape(path: Path, scale: float = 1.0) -> ConvexShape:
    """The convex hull of a mesh file (any format trimesh reads), centred on its centroid,
    scaled by ``scale`` (mesh units to m). Here, not in hapticd.physics.scene: reading files is
    the configuration's business, and the physics stays free of I/O."""
    import trimesh

    mesh = trimesh.load(path, force="mesh")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: no triangle mesh found")
    hull = mesh.convex_hull
    hull.apply_scale(scale)
    if hull.volume <= 0:
        raise ValueError(f"{path}: the convex hull has no volume")
    com = hull.center_mass
    verts = hull.vertices - com
    normals = hull.face_normals
    offsets = np.einsum("ij,ij->i", normals, verts[hull.faces[:, 0]])
    # Coplanar triangles share a plane: keep one copy.
    key = np.round(np.column_stack([normals, offsets]), 9)
    _, keep = np.unique(key, axis=0, return_index=True)
    keep.sort()
    inertia = hull.moment_inertia / hull.volume  # trimesh assumes density 1
    return ConvexShape(normals[keep], offsets[keep], verts, float(hull.volume), inertia)


def build_object(cfg: ObjectConfig, base: Path | None = None) -> SceneObject:
    """The grasped object of a profile's scene (ProfileError for a mesh it cannot use)."""
    if cfg.shape == "box":
        assert cfg.size_m is not None
        shape = ConvexShape.box(np.array(cfg.size_m))
    else:
        assert cfg.mesh is not None
        path = Path(cfg.mesh)
        if not path.is_absolute() and base is not None:
            path = base / path
        try:
            shape = mesh_shape(path, cfg.mesh_scale)
        except (OSError, ValueError) as exc:
            raise ProfileError(f"scene.object.mesh: cannot use {path}: {exc}") from None
    mat = Material(
        cfg.stiffness_n_per_m,
        cfg.damping_n_s_per_m,
        cfg.friction.static,
        cfg.friction.dynamic,
        cfg.friction.torsion_m,
    )
    return SceneObject(
        shape,
        mat,
        np.array(cfg.position_m),
        rpy_matrix(cfg.orientation_rpy_rad),
        fixed=cfg.fixed,
        mass=cfg.mass_kg or 0.0,
    )


def _material(cfg: SurfaceConfig) -> Material:
    return Material(
        cfg.stiffness_n_per_m, cfg.damping_n_s_per_m, cfg.friction.static, cfg.friction.dynamic
    )


def build_scene(cfg: SceneConfig, profile: Profile | None = None) -> Scene:
    """The scene of a profile: object, ground and walls, gravity (ProfileError naming the file)."""
    base = profile.source.parent if profile is not None and profile.source else None
    try:
        obj = build_object(cfg.object, base)
    except ProfileError as exc:
        where = profile.source if profile is not None and profile.source else "<profile>"
        raise ProfileError(f"{where}: {exc}") from None
    surfaces: list[Surface] = []
    if cfg.ground is not None:
        surfaces.append(
            Surface("ground", (0.0, 0.0, 1.0), cfg.ground.height_m, _material(cfg.ground))
        )
    if cfg.walls is not None:
        wx, wy = cfg.walls.half_width_m
        m = _material(cfg.walls)
        # Solid beyond each wall; the normal points back into the workspace.
        surfaces += [
            Surface("wall +x", (-1.0, 0.0, 0.0), -wx, m),
            Surface("wall -x", (1.0, 0.0, 0.0), -wx, m),
            Surface("wall +y", (0.0, -1.0, 0.0), -wy, m),
            Surface("wall -y", (0.0, 1.0, 0.0), -wy, m),
        ]
    gravity = None if cfg.gravity_m_s2 is None else np.array(cfg.gravity_m_s2, dtype=float)
    if gravity is not None and not np.any(gravity):
        gravity = None
    return Scene(obj, surfaces, gravity, 0 if cfg.substeps == "auto" else int(cfg.substeps))


def realtime_settings(profile: Profile) -> RealtimeSettings | None:
    rt = profile.loop.realtime
    if not rt.enabled:
        return None
    return RealtimeSettings(rt.priority, rt.cpu, rt.lock_memory, rt.timer_slack_ns, rt.required)


def build_renderer(profile: Profile) -> Renderer:
    """The scene and rendering pipeline of ``profile`` (ProfileError for a bad scene)."""
    scene = build_scene(profile.scene, profile)
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
        passivity=(
            PassivityParams(
                rc.passivity.velocity_threshold_m_per_s, rc.passivity.max_damping_n_s_per_m
            )
            if rc.passivity.enabled
            else None
        ),
    )
    # The safety chain's kernel (build_safety) is chosen with the renderer's: one message,
    # and one background compiler for all of them.
    choice = jit.choose(rc.kernels, [*renderer.kernel_names, *SafetyChain.kernel_names])
    if choice.message is not None:
        log.warning("%s", choice.message)
    elif choice.note is not None:
        log.info("%s", choice.note)
    elif choice.used == "compiled":
        log.debug("kernels %s compiled or loaded in %.3f s", list(choice.kernels), choice.seconds)
    renderer.use_kernels({n: k for n, k in choice.kernels.items() if n in renderer.kernel_names})
    why = renderer.allocator.native_problem
    if why is not None:  # an allocator plugin numba cannot compile: it runs as Python
        log.warning(
            "allocator %r cannot be compiled by numba (%s): the tick runs it as Python "
            "between its compiled parts (the same forces; a slower tick)",
            rc.allocator,
            why,
        )
    return renderer


def build_safety(profile: Profile, devices: list[Device]) -> SafetyChain:
    """The safety chain of ``profile`` for ``devices`` (limit: the smaller of both), with
    its compiled normal path as ``rendering.kernels`` asks (hapticd.physics.jit.choose)."""
    limits = [min(d.info.max_force_n, profile.safety.max_force_n) for d in devices]
    sc = profile.safety
    chain = SafetyChain(
        limits,
        SafetyParams(
            ramp_s=sc.ramp_s,
            max_rate_n_per_s=sc.max_force_rate_n_per_s or math.inf,
            workspace_center_m=sc.workspace_center_m,
            workspace_radius_m=sc.workspace_radius_m or math.inf,
            watchdog_s=sc.watchdog_s or math.inf,
            max_device_speed_m_per_s=sc.max_device_speed_m_per_s,
            deadman=tuple(
                None if (d := f.deadman) is None else Deadman(d.button, d.ramp_s)
                for f in profile.fingers
            ),
        ),
        dt=1.0 / profile.loop.rate_hz,
        rated_n=[d.info.max_force_n for d in devices],
        max_n=profile.safety.max_force_n,
    )
    # Not a renderer stage, but compiled as the renderer's kernels are (rendering.kernels):
    # the normal path compiled, every trip through the Python chain. build_renderer asked
    # for it with its own and said how that went: here it is in this process already, or
    # Python runs (auto: being compiled; or no working JIT).
    choice = jit.choose(profile.rendering.kernels, list(SafetyChain.kernel_names))
    if choice.message is not None or choice.note is not None:
        log.debug("safety chain: %s", choice.message or choice.note)
    chain.use_kernels(choice.kernels)
    return chain
