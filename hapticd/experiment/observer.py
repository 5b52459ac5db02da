"""The model observer: a simulated subject that feels only what the devices render.

Its hand is the ``sim`` device (hapticd_drivers.sim: each fingertip a mass pulled along
a planned path by a spring-damper, pushed back by the rendered force). For each
interval of a trial it plans an exploration with trial-to-trial motor variability
(``squeeze``: close on the fixed cube to a depth and back; ``lift``: pinch the free cube,
lift it and hold it), runs the servo loop on the base profile, unpaced and in process
(the renderer, safety chain, device bank and loop the daemon runs, built by
hapticd.daemon.build), with the condition's parameters and the interval's value of the varied
parameter set through the same parameter path the control socket uses, and keeps every
tick's frame in memory.

From the frames it reads a cue, the one a person could read at the fingertips:

- stiffness: the slope of the force's magnitude (N, both fingers' mean) over
  the finger closure (m, half the decrease of the fingers' distance since both
  touched), fitted by least squares over the ticks in contact: N/m;
- weight: the mean vertical load the forces put on the fingers (N, summed over the
  fingers, downward positive) over the hold;

both from the force the devices were sent (``device_force``: the rendered force after
the safety chain), the force that reached the fingertips.

The sensory model (``SensoryModel``) adds Gaussian noise of sd sqrt((w c)^2 + floor^2)
to each interval's cue c (Weber's law with an absolute floor) and answers "was the
second more?" by comparing the two noisy cues. That is the default judgement
(``weber``); ``JUDGEMENTS`` declares the others an observer may use instead (a Weber
fraction that rises at small forces; stiffness from force and finger displacement
together), and ``ObserverConfig.actuation_angle_deg`` tilts the profile's actuated
directions. Everything is drawn from one generator seeded per trial: the same seed gives
the same answers. It is a model, not subjects: docs/experiments.md says what it assumes
and what it predicts.
"""

from __future__ import annotations

import json
import math
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from hapticd_drivers import registry

from hapticd import params
from hapticd.allocation import DEFAULT_ROBUSTNESS, AdaptiveState, Robustness
from hapticd.allocation.actuation import Actuation
from hapticd.allocation.contacts import ContactAllocator
from hapticd.daemon.build import build_mounts, build_renderer, build_safety
from hapticd.experiment.plan import PlannedTrial
from hapticd.experiment.spec import Experiment, ExperimentError
from hapticd.loop.servo import ServoLoop, TickClock
from hapticd.loop.trajectory import Hold, MinJerk, Segment, two_finger
from hapticd.physics.frame import Frame
from hapticd.profile import (
    Profile,
    apply_overrides,
    load_profile,
    parse_profile,
    read_document,
)

# 2 x 0.6745: a cue difference with noise sd s on each interval gives a psychometric
# function of sigma sqrt(2) s, whose JND is 0.6745 sigma.
JND_PER_NOISE_SD = math.sqrt(2.0) * 0.6744897501960817
PATH_RATE_HZ = 1000.0  # samples of the planned hand path (the device interpolates)


@dataclass(frozen=True)
class SensoryModel:
    """Noise on a cue c: Gaussian, sd = sqrt((weber_noise c)^2 + floor^2), in the cue's
    unit (N/m for stiffness, N for weight). ``weber`` is the Weber fraction (JND /
    standard) the model gives when the cue is proportional to the stimulus and the floor
    negligible: weber_noise = weber / (sqrt(2) 0.6745)."""

    cue: str  # "stiffness" or "weight"
    weber: float
    floor: float
    unit: str
    source: str

    @property
    def weber_noise(self) -> float:
        return self.weber / JND_PER_NOISE_SD

    def sd(self, cue: float) -> float:
        return math.hypot(self.weber_noise * cue, self.floor)


# Weber fractions from the notes' literature (docs/experiments.md says why these).
STIFFNESS_SENSE = SensoryModel(
    "stiffness",
    weber=0.15,
    floor=2.0,
    unit="N/m",
    source="pinched compliance, Bergmann Tiest & Kappers 2009 (~15 %)",
)
WEIGHT_SENSE = SensoryModel(
    "weight",
    weber=0.08,
    floor=0.01,
    unit="N",
    source="actively lifted weight, ~5-10 % (mid value)",
)


@dataclass(frozen=True)
class Motor:
    """The hand's exploration and its trial-to-trial variability (each a mean and an sd;
    lengths m, times s). Drawn anew for every interval."""

    start_gap_m: float = 0.002  # fingertips this far from the faces at the start
    squeeze_depth_m: tuple[float, float] = (0.008, 0.0012)
    squeeze_in_s: tuple[float, float] = (0.30, 0.05)
    squeeze_hold_s: float = 0.10
    squeeze_out_s: float = 0.20
    grip_depth_m: tuple[float, float] = (0.008, 0.001)
    grip_margin: float = 1.4  # grip over slip (Johansson & Westling 1984: ~1.2-2)
    grip_s: float = 0.15
    lift_height_m: tuple[float, float] = (0.030, 0.005)
    lift_s: tuple[float, float] = (0.25, 0.04)
    hold_s: float = 0.45
    settle_s: float = 0.15  # the first part of the hold is not judged (the lift's transient)
    # Finger offsets (m) across the grasp line, as real fingers are not exactly opposite.
    offset_sd_m: float = 0.0008


@dataclass(frozen=True)
class ObserverConfig:
    """What the observer needs beyond the experiment: its sensory model, its motor
    model, its hand (the sim device's keys), the loop rate (Hz) it simulates at, how it
    judges (``judgement``, a name in ``JUDGEMENTS``, with the parameters of the
    judgements that need them) and the actuation geometry it explores
    (``actuation_angle_deg``: None, the profile's own; docs/experiments.md, "Observer
    variants")."""

    sense: SensoryModel
    motor: Motor = field(default_factory=Motor)
    rate_hz: float = 500.0
    hand: Mapping[str, float] = field(
        default_factory=lambda: {
            "mass_kg": 0.05,
            "hand_stiffness_n_per_m": 300.0,
            "hand_damping_n_s_per_m": 3.0,
            "max_step_s": 5e-4,
        }
    )
    judgement: str = "weber"
    # The absolute term c (N) of force discrimination, JND(F) = W F + c: a Weber fraction
    # W + c / F that rises at small forces (Feyzabadi et al. 2013: the smallest force
    # felt, 0.04 N). Used by the judgements that read the force (rising_weber,
    # force_displacement).
    force_threshold_n: float = 0.04
    # force_displacement: the Weber fractions of the force (Pang, Tan & Durlach 1991: ~7 %;
    # Allin et al. 2002: ~10 %) and of the finger closure (our choice: with the force's,
    # sqrt(0.10^2 + 0.11^2) = 0.15, the default stiffness Weber fraction at large forces).
    force_weber: float = 0.10
    closure_weber: float = 0.11
    # Each finger's one actuated direction tilted this far (degrees) up from the grasp
    # line: thumb (cos a, 0, sin a), index (-cos a, 0, sin a); None: the profile's own.
    actuation_angle_deg: float | None = None


# The largest actuation angle (degrees): IF's gain 1 / cos(a) grows without bound at 90.
MAX_ACTUATION_ANGLE_DEG = 80.0


def default_config(
    exp: Experiment, *, judgement: str = "weber", actuation_angle_deg: float | None = None
) -> ObserverConfig:
    """The observer for ``exp``'s question: stiffness (squeeze) or weight (lift), judged
    by ``judgement`` (a name in ``JUDGEMENTS``) on the profile's actuation, or on one
    tilted ``actuation_angle_deg`` up from the grasp line. ExperimentError for a
    judgement that does not exist or cannot judge this exploration, or an angle out of
    [0, MAX_ACTUATION_ANGLE_DEG]."""
    kind = exploration_kind(exp)
    j = JUDGEMENTS.get(judgement)
    if j is None:
        raise ExperimentError(
            f"unknown observer judgement {judgement!r}; judgements: {', '.join(JUDGEMENTS)}"
        )
    if kind not in j.explorations:
        raise ExperimentError(
            f"{exp.source}: the observer judgement {judgement!r} judges a "
            f"{' or '.join(j.explorations)}, not this experiment's {kind}"
        )
    if actuation_angle_deg is not None and not (
        0.0 <= actuation_angle_deg <= MAX_ACTUATION_ANGLE_DEG
    ):
        raise ExperimentError(
            f"observer actuation angle {actuation_angle_deg!r} degrees: expected 0 to "
            f"{MAX_ACTUATION_ANGLE_DEG:g} (up from the grasp line)"
        )
    sense = WEIGHT_SENSE if kind == "lift" else STIFFNESS_SENSE
    return ObserverConfig(sense, judgement=judgement, actuation_angle_deg=actuation_angle_deg)


CUES = {"stiffness_n_per_m": "squeeze", "mass_kg": "lift"}


def check_observable(profile: Profile, exp: Experiment | None = None) -> None:
    """ExperimentError unless the model observer can explore ``profile`` (a box held by
    two fingers) and judge ``exp``'s varied parameter (stiffness or mass)."""
    obj = profile.scene.object
    if obj.shape != "box" or obj.size_m is None or len(profile.fingers) != 2:
        what = f"a {obj.shape}" if obj.shape != "box" else f"{len(profile.fingers)} fingers"
        raise ExperimentError(
            f"{profile.source}: the model observer explores a box with two fingers; this "
            f"profile has {what}"
        )
    if exp is not None and exp.varied.param not in CUES:
        raise ExperimentError(
            f"{exp.source}: varied.param: the model observer judges "
            f"{' or '.join(CUES)}, not {exp.varied.param}"
        )


def exploration_kind(exp: Experiment) -> str:
    """``lift`` when the experiment varies the mass, ``squeeze`` for the stiffness."""
    return CUES.get(exp.varied.param, "squeeze")


# -- the hand's path ------------------------------------------------------------------


def _normal(rng: np.random.Generator, spec: tuple[float, float], lo: float) -> float:
    mean, sd = spec
    return max(lo, float(rng.normal(mean, sd)))


def grip_depth(
    profile: Profile, settings: Mapping[str, Any], motor: Motor, hand: Mapping[str, float]
) -> float:
    """How deep (m) a lift must pinch the object in ``settings`` (its mass and friction,
    else the profile's) for its weight to be carried with ``motor.grip_margin``: a
    person's grip scales with the load and the friction (Johansson & Westling 1984).
    Each finger's normal force is about the object's and the hand's springs in series
    times the depth, and two fingers carry at most 2 mu_dynamic N."""
    obj = profile.scene.object
    mass = float(settings.get("mass_kg") or obj.mass_kg or 0.0)
    fr = settings.get("friction")
    mu = float(fr[1]) if fr is not None else float(obj.friction.dynamic)
    k_obj = float(settings.get("stiffness_n_per_m") or obj.stiffness_n_per_m)
    k_hand = float(hand.get("hand_stiffness_n_per_m", 300.0))
    k = k_obj * k_hand / (k_obj + k_hand)
    if mu <= 0 or k <= 0:
        return float("inf")  # no friction: no grip carries it
    return motor.grip_margin * mass * 9.81 / (2 * mu * k)


def plan_path(
    kind: str,
    profile: Profile,
    motor: Motor,
    rng: np.random.Generator,
    *,
    settings: Mapping[str, Any] | None = None,
    hand: Mapping[str, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """The planned hand path of one interval: times (N,) s, positions (N, 2, 3) m (thumb
    on -x, index on +x of the profile's cube), and the phase times (s) the cue reads.
    A lift pinches at least ``grip_depth`` for the interval's ``settings`` (its mass and
    friction; the hand's springs ``hand``), at most the object's half width."""
    check_observable(profile)
    obj = profile.scene.object
    assert obj.size_m is not None
    centre = np.array(obj.position_m, dtype=float)
    half = 0.5 * float(obj.size_m[0])
    radii = [f.radius_m for f in profile.fingers]
    dy, dz = rng.normal(0.0, motor.offset_sd_m, 2)
    starts: list[np.ndarray] = []
    plans: list[list[Segment]] = []
    if kind == "squeeze":
        depth = _normal(rng, motor.squeeze_depth_m, 0.002)
        t_in = _normal(rng, motor.squeeze_in_s, 0.1)
        for sign, r, off in ((-1.0, radii[0], (0.0, 0.0)), (1.0, radii[1], (dy, dz))):
            x_touch = half + r
            start = centre + np.array([sign * (x_touch + motor.start_gap_m), off[0], off[1]])
            pinch = centre + np.array([sign * (x_touch - depth), off[0], off[1]])
            starts.append(start)
            plans.append(
                [
                    MinJerk(t_in, tuple(pinch)),
                    Hold(motor.squeeze_hold_s),
                    MinJerk(motor.squeeze_out_s, tuple(start)),
                ]
            )
        phases = {
            "hold_from": t_in,
            "hold_to": t_in + motor.squeeze_hold_s,
            "end": t_in + motor.squeeze_hold_s + motor.squeeze_out_s,
        }
    else:
        depth = _normal(rng, motor.grip_depth_m, 0.002)
        if settings is not None:
            # Scaled to the load: the nominal pinch, or what the load needs with the same
            # trial-to-trial variation (relative), whichever is deeper.
            need = grip_depth(profile, settings, motor, hand or {})
            depth = min(max(depth, need * depth / motor.grip_depth_m[0]), half)
        height = _normal(rng, motor.lift_height_m, 0.005)
        t_lift = _normal(rng, motor.lift_s, 0.1)
        for sign, r, off in ((-1.0, radii[0], (0.0, 0.0)), (1.0, radii[1], (dy, dz))):
            x_touch = half + r
            start = centre + np.array([sign * (x_touch + motor.start_gap_m), off[0], off[1]])
            pinch = centre + np.array([sign * (x_touch - depth), off[0], off[1]])
            up = pinch + np.array([0.0, 0.0, height])
            starts.append(start)
            plans.append(
                [
                    MinJerk(motor.grip_s, tuple(pinch)),
                    MinJerk(t_lift, tuple(up)),
                    Hold(motor.hold_s),
                ]
            )
        hold_start = motor.grip_s + t_lift
        phases = {
            "judge_from": hold_start + motor.settle_s,
            "end": hold_start + motor.hold_s,
        }
    t, x = two_finger(starts, plans, PATH_RATE_HZ)
    return t, x, phases


# -- one interval in the loop ----------------------------------------------------------


class FrameLog:
    """Every tick's recorded frame, in memory: what the servo loop hands a recorder
    (``append`` of the frame's recorded bytes), kept as a structured array."""

    def __init__(self, frame: Frame, capacity: int) -> None:
        self.rows = np.zeros(capacity, dtype=frame.recorded_dtype)
        self._bytes = self.rows.view(np.uint8).reshape(capacity, frame.recorded_dtype.itemsize)
        self.ticks = 0
        self.path = "<memory>"
        self.clock: dict[str, float] | None = None  # tick 0 on the LSL clock and in UTC

    def append(self, record: np.ndarray) -> None:
        if self.ticks < len(self.rows):
            self._bytes[self.ticks] = record
            self.ticks += 1

    def anchor(self, lsl_s: float, utc_unix_s: float) -> None:
        """Tick 0 on the LSL clock and in UTC, s (as a recording's header holds them)."""
        self.clock = {"lsl_s": lsl_s, "utc_unix_s": utc_unix_s}

    def close(self) -> dict[str, Any]:
        return {"ticks": self.ticks}

    @property
    def data(self) -> np.ndarray:
        return self.rows[: self.ticks]


def interval_settings(exp: Experiment, trial: PlannedTrial, second: bool) -> dict[str, Any]:
    """The parameters of one interval: the condition's, and the varied parameter at the
    standard or the comparison (``second``: the second interval)."""
    cond = {c.name: c for c in exp.conditions}[trial.condition]
    values = dict(cond.values())
    comparison = second != trial.comparison_first
    values[exp.varied.param] = trial.comparison if comparison else trial.standard
    return values


def run_interval(
    profile: Profile,
    settings: Mapping[str, Any],
    path: tuple[np.ndarray, np.ndarray],
    config: ObserverConfig,
) -> np.ndarray:
    """Run the servo loop, unpaced, with sim fingers on ``path`` (times (N,) s, positions
    (N, 2, 3) m) and ``settings`` set as the control socket sets them; every tick's
    recorded frame (structured array), the shutdown's zero left out. RuntimeError if a
    safety fault latched."""
    times, pos = path
    clock = TickClock()
    devices = [
        registry.open_device(
            "sim",
            times=times,
            positions=pos[:, i, :],
            clock=clock.now,
            serial=f"observer-{f.name}",
            max_force_n=float(getattr(f.device, "max_force_n", 12.0)),
            **config.hand,
        )
        for i, f in enumerate(profile.fingers)
    ]
    renderer = build_renderer(profile)
    safety = build_safety(profile, devices)
    rate = profile.loop.rate_hz
    n_ticks = math.floor(float(times[-1]) * rate + 1e-9)
    log = FrameLog(Frame(len(devices), renderer.actuation.n_actuators), n_ticks + 2)
    loop = ServoLoop(
        devices,
        renderer,
        safety,
        rate,
        paced=False,
        duration_s=n_ticks / rate,
        recorder=log,  # type: ignore[arg-type]
        stop_ramp_s=0.0,
        wall_watchdog=False,
        clock=clock,
    )
    loop.bank.set_mounts(build_mounts(profile))
    for name, value in settings.items():
        loop.set_param(name, params.PARAMS[name].check(value))
    loop.run()
    if safety.fault is not None:
        raise RuntimeError(f"the observer's interval latched a fault: {safety.fault.cause}")
    rows = log.data
    # Without the row the loop adds for the zero force of its shutdown: no exploration.
    return rows[rows["tick"] < n_ticks]


# -- the cues --------------------------------------------------------------------------


def stiffness_cue(rows: np.ndarray) -> float:
    """Slope (N/m) of the fingers' mean force magnitude (the force the devices were sent,
    ``device_force``: after the safety chain, what reached the fingertips) over the finger closure
    (half the decrease of the fingertips' distance since both touched), least squares
    over the ticks with both fingers in contact. 0 without enough contact."""
    both = rows["in_contact"].all(axis=1)
    if both.sum() < 5:
        return 0.0
    pos = rows["device_pos"]
    aperture = np.linalg.norm(pos[:, 1] - pos[:, 0], axis=1)
    first = int(np.argmax(both))
    closure = 0.5 * (aperture[first] - aperture[both])
    force = np.linalg.norm(rows["device_force"][both], axis=2).mean(axis=1)
    if np.ptp(closure) <= 0:
        return 0.0
    slope = np.polyfit(closure, force, 1)[0]
    return float(slope)


def weight_cue(rows: np.ndarray, judge_from_s: float) -> float:
    """Mean vertical load (N, downward positive) of the forces sent to both fingers'
    devices (``device_force``) over the hold (ticks from ``judge_from_s``)."""
    held = rows["t"] >= judge_from_s
    if not held.any():
        return 0.0
    return float(-rows["device_force"][held][:, :, 2].sum(axis=1).mean())


def allocator_forces(
    rows: np.ndarray,
    actuation: Actuation,
    method: str,
    *,
    robust: Robustness = DEFAULT_ROBUSTNESS,
    adaptive: AdaptiveState | None = None,
    initial_center: np.ndarray | None = None,
) -> np.ndarray:
    """What allocator ``method`` would have rendered on each tick of a recorded interval
    with both fingers in contact: M_a lam_a per finger (n, 2, 3) N, with lam_a from the
    loop's own allocation (``ContactAllocator.replay``: the same per-tick code, contact
    onset and the adaptive allocator's lag included) on the recorded contact points,
    contact forces and object positions, tick by tick from the interval's start, and
    M_a the actuated directions (``actuation``) where the fingers were. Ground and walls
    are left out. Compares allocators on one and the same exploration
    (docs/experiments.md); for the allocator the interval ran with, equal to what the
    loop's allocation rendered. ``robust`` and ``adaptive`` (its lag and ratios; alpha
    starts at 0): the profile's ``rendering`` settings; ``initial_center`` (3,) m: the
    object's position before the first tick (default: after it)."""
    both = rows["in_contact"].all(axis=1)
    n = int(both.sum())
    if n == 0:
        return np.zeros((0, 2, 3))
    t = rows["t"]
    rate = round(1.0 / float(np.median(np.diff(t)))) if len(t) > 1 else 1.0
    state = AdaptiveState() if adaptive is None else replace(adaptive, alpha=0.0)
    allocator = ContactAllocator(actuation, method, robust, state, 1.0 / rate)
    # A tick allocates about the object's position before its dynamics moved it: the
    # position the previous tick recorded.
    pos = rows["object_pos"]
    first = pos[0] if initial_center is None else np.asarray(initial_center, dtype=float)
    centers = np.concatenate([first[None], pos[:-1]])
    lam_a = allocator.replay(
        rows["in_contact"],
        rows["device_pos"],
        rows["contact_point"],
        rows["contact_force"],
        centers,
    )[both]
    M = np.stack([actuation.matrix(p) for p in rows["device_pos"][both]])
    return np.einsum("nij,nj->ni", M, lam_a).reshape(n, 2, 3)


@dataclass(frozen=True)
class IntervalCues:
    """What one interval delivered at the fingertips: ``cue``, the experiment's cue
    (stiffness_cue N/m, weight_cue N); ``force_n``, the force it was felt at (N: a
    squeeze's mean force magnitude per finger over its hold, a lift's vertical load);
    ``closure_m``, a squeeze's finger closure over its hold (m; 0 for a lift)."""

    cue: float
    force_n: float
    closure_m: float = 0.0


def squeeze_cues(rows: np.ndarray, phases: Mapping[str, float]) -> IntervalCues:
    """A squeeze's cues: the stiffness cue, and the fingers' mean force magnitude (N) and
    closure (m, half the decrease of the fingertips' distance since both touched), each
    averaged over the hold's ticks (``hold_from`` to ``hold_to``) with both fingers in
    contact (0 without any)."""
    both = rows["in_contact"].all(axis=1)
    held = both & (rows["t"] >= phases["hold_from"]) & (rows["t"] <= phases["hold_to"])
    if not held.any():
        return IntervalCues(stiffness_cue(rows), 0.0, 0.0)
    pos = rows["device_pos"]
    aperture = np.linalg.norm(pos[:, 1] - pos[:, 0], axis=1)
    first = int(np.argmax(both))
    closure = 0.5 * (aperture[first] - aperture[held])
    force = np.linalg.norm(rows["device_force"][held], axis=2).mean(axis=1)
    return IntervalCues(stiffness_cue(rows), float(force.mean()), float(closure.mean()))


# -- how the observer judges -------------------------------------------------------------

# A percept: one interval's noisy percept of the varied quantity from its cues, drawn from
# the trial's generator; "was the second more?" is whether the second's is the larger.
Percept = Callable[[IntervalCues, ObserverConfig, np.random.Generator], float]
_TINY = 1e-9  # a force (N) or a length (m) below which the cue is taken as absent


def weber_percept(c: IntervalCues, cfg: ObserverConfig, rng: np.random.Generator) -> float:
    """The cue with noise of sd sqrt((w c)^2 + floor^2) (``SensoryModel``): Weber's law
    with a floor on the cue itself."""
    return c.cue + float(rng.normal(0.0, cfg.sense.sd(c.cue)))


def rising_weber_fraction(force_n: float, weber: float, threshold_n: float) -> float:
    """The Weber fraction at force ``force_n`` (N) of a discrimination whose JND is
    weber F + threshold_n: weber + threshold_n / F, rising at small forces."""
    return weber + threshold_n / max(force_n, _TINY)


def rising_weber_percept(c: IntervalCues, cfg: ObserverConfig, rng: np.random.Generator) -> float:
    """The cue with Gaussian noise whose Weber fraction rises at small forces: sd =
    W(F) |cue| / (sqrt(2) 0.6745), W(F) = sense.weber + force_threshold_n / F, F the force
    the interval was felt at. The absolute term replaces the default's floor."""
    w = rising_weber_fraction(c.force_n, cfg.sense.weber, cfg.force_threshold_n)
    return c.cue + float(rng.normal(0.0, w / JND_PER_NOISE_SD * abs(c.cue)))


def force_displacement_percept(
    c: IntervalCues, cfg: ObserverConfig, rng: np.random.Generator
) -> float:
    """Stiffness as perceived force over perceived finger closure (N/m), each with its own
    Gaussian noise: the force's Weber fraction force_weber + force_threshold_n / F, the
    closure's closure_weber (each sd = W x / (sqrt(2) 0.6745))."""
    w_f = rising_weber_fraction(c.force_n, cfg.force_weber, cfg.force_threshold_n)
    force = c.force_n + float(rng.normal(0.0, w_f / JND_PER_NOISE_SD * c.force_n))
    closure = c.closure_m + float(
        rng.normal(0.0, cfg.closure_weber / JND_PER_NOISE_SD * c.closure_m)
    )
    return force / max(closure, _TINY)


@dataclass(frozen=True)
class Judgement:
    """One way the observer may judge an interval: its name (``ObserverConfig.judgement``),
    the explorations it can judge (``squeeze``, ``lift``), what it assumes, and its
    percept."""

    name: str
    explorations: tuple[str, ...]
    summary: str
    percept: Percept


JUDGEMENTS: dict[str, Judgement] = {
    j.name: j
    for j in (
        Judgement(
            "weber",
            ("squeeze", "lift"),
            "the cue with Weber's-law noise and a floor (the default)",
            weber_percept,
        ),
        Judgement(
            "rising_weber",
            ("squeeze", "lift"),
            "the cue with a Weber fraction that rises at small forces, W + c / F",
            rising_weber_percept,
        ),
        Judgement(
            "force_displacement",
            ("squeeze",),
            "stiffness as perceived force over perceived finger closure, each with its noise",
            force_displacement_percept,
        ),
    )
}


# -- a trial -----------------------------------------------------------------------------


def interval_cues(
    kind: str,
    profile: Profile,
    settings: Mapping[str, Any],
    config: ObserverConfig,
    rng: np.random.Generator,
) -> IntervalCues:
    """One interval: plan the hand's path, run the loop, read the cues."""
    return explore(kind, profile, settings, config, rng)[0]


def explore(
    kind: str,
    profile: Profile,
    settings: Mapping[str, Any],
    config: ObserverConfig,
    rng: np.random.Generator,
) -> tuple[IntervalCues, str | None]:
    """One interval: plan the hand's path, run the loop, read the cues; and why the
    exploration failed (``exploration_failure``), None when it did not."""
    t, x, phases = plan_path(kind, profile, config.motor, rng, settings=settings, hand=config.hand)
    rows = run_interval(profile, settings, (t, x), config)
    if kind == "squeeze":
        cues = squeeze_cues(rows, phases)
    else:
        load = weight_cue(rows, phases["judge_from"])
        cues = IntervalCues(load, load)
    why = exploration_failure(kind, rows, phases, x, profile, settings, cues.cue)
    if why is not None and kind == "lift" and "slipped" in why:
        need = grip_depth(profile, settings, config.motor, config.hand)
        half = 0.5 * float(profile.scene.object.size_m[0])  # type: ignore[index]
        if need > half:  # the cause, computed: no pinch the cube allows carries it
            why += (
                f" (carrying it needs a {need * 1e3:.1f} mm pinch, more than the cube's "
                f"{half * 1e3:.1f} mm half width: a stiffer or rougher object would do)"
            )
    return cues, why


# The pilot check's limits: the fingers on the cube over at least this share of the
# judged part of an interval; a lifted cube up by at least this share of the hand's
# lift (less: it slipped or dropped); the EF vertical cue (the net load, which a held
# still cube makes m g) within this share of m g.
PILOT_CONTACT = 0.9
PILOT_RISE = 0.5
PILOT_EF_TOLERANCE = 0.10


def interval_failure(
    kind: str, rows: np.ndarray, phases: Mapping[str, float], planned: np.ndarray
) -> str | None:
    """Why one simulated interval is no exploration of the task, or None: the fingers
    off the cube over the judged part (a lift's hold from ``judge_from``, a squeeze's
    hold from ``hold_from`` to ``hold_to``), or a lifted cube that did not rise with the
    hand (``planned``: the path's positions)."""
    start = phases.get("judge_from", phases.get("hold_from", 0.0))
    judged = (rows["t"] >= start) & (rows["t"] <= phases.get("hold_to", np.inf))
    if not judged.any():
        return "the interval is empty"
    both = rows["in_contact"][judged].all(axis=1).mean()
    if both < PILOT_CONTACT:
        return f"no contact: both fingers touched the cube in only {both:.0%} of it"
    if kind == "lift":
        rise = float(rows["object_pos"][judged][:, 2].mean() - rows["object_pos"][0, 2])
        want = float(planned[-1, 0, 2] - planned[0, 0, 2])
        if rise < PILOT_RISE * want:
            return (
                f"the cube slipped or dropped: it rose {rise * 1e3:.1f} mm of the hand's "
                f"{want * 1e3:.1f} mm"
            )
    return None


def exploration_failure(
    kind: str,
    rows: np.ndarray,
    phases: Mapping[str, float],
    planned: np.ndarray,
    profile: Profile,
    settings: Mapping[str, Any],
    cue: float,
) -> str | None:
    """Why one interval is no exploration of the task (``interval_failure``: no contact,
    a cube that slipped or dropped), or, a lift rendered by EF (``settings``' allocator,
    else the profile's), a vertical cue more than PILOT_EF_TOLERANCE off m g (a cube not
    held still: "cue off"); None when it is one."""
    why = interval_failure(kind, rows, phases, planned)
    allocator = settings.get("allocator", profile.rendering.allocator)
    if why is None and kind == "lift" and allocator == "ef":
        mass = settings.get("mass_kg") or profile.scene.object.mass_kg or 0.0
        mg = float(mass) * 9.81
        if abs(cue - mg) > PILOT_EF_TOLERANCE * mg:
            why = (
                f"cue off: the EF vertical cue is {cue:.3f} N against m g {mg:.3f} N (more "
                f"than {PILOT_EF_TOLERANCE:.0%} off)"
            )
    return why


def pilot_check(exp: Experiment, profile: Profile, config: ObserverConfig) -> None:
    """Refuse (ExperimentError naming each cause) a design the observer's hand cannot
    perform, before any trial: one pilot interval per condition at the smallest and the
    largest value of the varied parameter the design presents, and for a lift also two
    with the EF allocator, whose vertical cue must be m g within PILOT_EF_TOLERANCE."""
    kind = exploration_kind(exp)
    rng = np.random.default_rng(0)
    lo, hi = _design_range(exp)
    tried: list[tuple[dict[str, Any], str]] = [
        ({**c.values(), exp.varied.param: v}, f"condition {c.name}")
        for c in exp.conditions
        for v in (lo, hi)
    ]
    if kind == "lift":
        tried += [({"allocator": "ef", exp.varied.param: v}, "the EF check") for v in (lo, hi)]
    problems = []
    for settings, what in tried:
        _, why = explore(kind, profile, settings, config, rng)
        if why is not None:
            problems.append(f"{what}, {exp.varied.param} {settings[exp.varied.param]:g}: {why}")
    if problems:
        raise ExperimentError(
            f"{exp.source}: the model observer's hand cannot perform this design (pilot "
            "intervals):\n  " + "\n  ".join(problems)
        )


def _design_range(exp: Experiment) -> tuple[float, float]:
    """The smallest and the largest value of the varied parameter the design presents."""
    lo_s, hi_s = min(exp.varied.standards), max(exp.varied.standards)
    lo_r, hi_r = exp.proc.ratio_range()  # the procedure's farthest comparisons
    return lo_s * lo_r, hi_s * hi_r


@dataclass(frozen=True)
class TrialResult:
    """One trial: the answer to "was the second more?", both intervals' cues (the
    sensory model's unit) and their noisy percepts; or, when an interval's exploration
    failed (``failure``: which interval and why), no answer and no percepts (nan)."""

    index: int
    answer_second_more: bool | None
    cues: tuple[float, float]
    percepts: tuple[float, float]
    failure: str | None = None


def trial_rng(seed: int, subject: str, index: int) -> np.random.Generator:
    """The generator of one trial: from the subject's seed, the subject's id and the
    trial's plan index only, so a trial's answer does not depend on which process runs
    it or in which order."""
    return np.random.default_rng(
        np.random.SeedSequence([int(seed), zlib.crc32(subject.encode()), int(index)])
    )


def observer_overrides(config: ObserverConfig) -> list[str]:
    """What the observer changes in the base profile: the loop rate, and no force ramp
    (``safety.ramp_s``: the ramp after the daemon enables forces is long over when a
    subject's trial starts; each simulated interval is a fresh loop, and would otherwise
    start inside it); with ``actuation_angle_deg``, each finger's actuated direction."""
    out = [f"loop.rate_hz={config.rate_hz:g}", "safety.ramp_s=0"]
    if config.actuation_angle_deg is not None:
        a = math.radians(config.actuation_angle_deg)
        c, s = math.cos(a), math.sin(a)
        out += [
            f"fingers[0].actuated_directions=[[{c!r}, 0.0, {s!r}]]",
            f"fingers[1].actuated_directions=[[{-c!r}, 0.0, {s!r}]]",
        ]
    return out


def _check_angle(exp: Experiment, config: ObserverConfig) -> None:
    """ExperimentError unless the base profile can take ``config.actuation_angle_deg``:
    two fingers of one actuated direction each (the angle replaces it)."""
    if config.actuation_angle_deg is None:
        return
    base = load_profile(exp.profile_path())
    counts = [len(f.actuated_directions) for f in base.fingers]
    if counts != [1, 1]:
        raise ExperimentError(
            f"{base.source}: the observer's actuation angle replaces each of two fingers' one "
            f"actuated direction; this profile's fingers have {counts} directions"
        )


def observer_profile(exp: Experiment, config: ObserverConfig) -> Profile:
    """The experiment's base profile as the observer runs it (``observer_overrides``)."""
    _check_angle(exp, config)
    return load_profile(exp.profile_path(), observer_overrides(config))


def profile_document(exp: Experiment, config: ObserverConfig) -> tuple[str, str]:
    """The observer's profile as (JSON of the validated document, the file's path): a
    picklable form for other processes (a loaded Profile is not picklable), parsed back
    with ``profile_from_document``. The profile is validated here first."""
    # ProfileError or ExperimentError now, in the caller, not in a worker.
    check_observable(observer_profile(exp, config), exp)
    path = exp.profile_path()
    data, _ = read_document(path)
    data = apply_overrides(data, observer_overrides(config), path)
    return json.dumps(data, sort_keys=True), str(Path(path).resolve())


_PARSED: dict[tuple[str, str], Profile] = {}


def profile_from_document(doc: tuple[str, str]) -> Profile:
    """The Profile of ``profile_document``'s output (parsed once per process)."""
    prof = _PARSED.get(doc)
    if prof is None:
        prof = _PARSED[doc] = parse_profile(json.loads(doc[0]), Path(doc[1]))
    return prof


def explore_trial(
    exp: Experiment,
    profile: Profile,
    config: ObserverConfig,
    trial: PlannedTrial,
    rng: np.random.Generator,
) -> tuple[tuple[IntervalCues, IntervalCues], str | None]:
    """Both intervals of ``trial`` explored in the loop, in order: their cues, and which
    interval's exploration failed and why (None when neither did)."""
    kind = exploration_kind(exp)
    got = [
        explore(kind, profile, interval_settings(exp, trial, s), config, rng) for s in (False, True)
    ]
    failed = [f"interval {i + 1}: {why}" for i, (_, why) in enumerate(got) if why is not None]
    return (got[0][0], got[1][0]), ("; ".join(failed) if failed else None)


def judge(
    config: ObserverConfig,
    index: int,
    cues: tuple[IntervalCues, IntervalCues],
    rng: np.random.Generator,
) -> TrialResult:
    """Trial ``index``'s answer from its intervals' cues by ``config.judgement``: a
    percept per interval, in order; "yes" when the second is the larger."""
    percept = JUDGEMENTS[config.judgement].percept
    p = (percept(cues[0], config, rng), percept(cues[1], config, rng))
    return TrialResult(index, bool(p[1] > p[0]), (cues[0].cue, cues[1].cue), p)


def answer_trial(
    exp: Experiment,
    profile: Profile,
    config: ObserverConfig,
    trial: PlannedTrial,
    subject: str,
    seed: int,
) -> TrialResult:
    """The observer's answer to one planned trial (no I/O): two explorations, two cues,
    two noisy percepts; "yes" when the second percept is the larger; no answer and the
    cause (``failure``) when an exploration failed (``exploration_failure``).
    Deterministic for (seed, subject, trial.index)."""
    rng = trial_rng(seed, subject, trial.index)
    cues, failure = explore_trial(exp, profile, config, trial, rng)
    if failure is not None:
        return failed_result(trial.index, cues, failure)
    return judge(config, trial.index, cues, rng)


def failed_result(index: int, cues: tuple[IntervalCues, IntervalCues], failure: str) -> TrialResult:
    """A trial whose exploration failed: never judged from a broken cue."""
    return TrialResult(index, None, (cues[0].cue, cues[1].cue), (math.nan, math.nan), failure)


def answer_trial_judgements(
    exp: Experiment,
    profile: Profile,
    configs: list[ObserverConfig],
    trial: PlannedTrial,
    subject: str,
    seed: int,
) -> list[TrialResult]:
    """``answer_trial`` for each of ``configs`` from one exploration: the configs may
    differ in how they judge, not in what they explore (the motor model, the hand, the
    rate, the actuation angle: ValueError otherwise). Each answer equals its config's
    ``answer_trial``: the explorations draw first from the trial's generator, and every
    judgement continues from the state they left."""
    explores = {(c.motor, tuple(c.hand.items()), c.rate_hz, c.actuation_angle_deg) for c in configs}
    if len(explores) > 1:
        raise ValueError("the configs explore differently: one exploration cannot serve them")
    rng = trial_rng(seed, subject, trial.index)
    cues, failure = explore_trial(exp, profile, configs[0], trial, rng)
    if failure is not None:
        return [failed_result(trial.index, cues, failure) for _ in configs]
    state = rng.bit_generator.state
    out = []
    for config in configs:
        rng.bit_generator.state = state
        out.append(judge(config, trial.index, cues, rng))
    return out
