"""The device interface every backend implements.

Units: position m, velocity m/s, force N, time s. Vectors are (3,) in the
device's frame, which the profile maps to the world frame.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass, field

import numpy as np
from hapticd_drivers.models import DeviceModel


class DeviceError(RuntimeError):
    """A device failed: read or write error, unplug, bad report, rejected command."""


class DeviceLostError(DeviceError):
    """A device that is gone (unplugged, its connection failed), as its driver documents
    a lost device; any other DeviceError is a device that still answers but failed."""


class BackendUnavailableError(DeviceError):
    """A backend that is unknown, or whose optional dependency is not installed."""


@dataclass(frozen=True)
class DeviceInfo:
    """Identity and limits: model, serial, rated force (N), workspace radius (m; NaN: not
    known until the device is opened), and the largest stiffness (N/m) and damping
    (N s/m) a rendering should ask of the model (inf: no recommendation)."""

    model: str
    serial: str
    max_force_n: float
    workspace_radius_m: float
    n_dof: int = 3
    max_stiffness_n_per_m: float = math.inf
    max_damping_n_s_per_m: float = math.inf

    @classmethod
    def of_model(cls, row: DeviceModel, serial: str, max_force_n: float) -> DeviceInfo:
        """A device of the model table's ``row``: its workspace and recommended maxima."""
        return cls(
            row.name,
            serial,
            max_force_n,
            row.workspace_radius_m,
            max_stiffness_n_per_m=row.max_stiffness_n_per_m,
            max_damping_n_s_per_m=row.max_damping_n_s_per_m,
        )


@dataclass
class DeviceState:
    """Preallocated state a device fills on every read (no allocation per tick).

    ``position`` (m) and ``velocity`` (m/s) are (3,) float64 arrays filled in place, never
    replaced (the owner may hand views of its own arrays); ``pos_view`` and ``vel_view``
    are memoryviews of them, for a device that stores them float by float (a store
    through one costs a fraction of a numpy item assignment)."""

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    buttons: int = 0
    timestamp: float = 0.0
    pos_view: memoryview = field(init=False, repr=False, compare=False)
    vel_view: memoryview = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("position", "velocity"):
            a = getattr(self, name)
            if not (
                isinstance(a, np.ndarray)
                and a.shape == (3,)
                and a.dtype == np.float64
                and a.flags.c_contiguous
                and a.flags.writeable
            ):
                raise ValueError(f"DeviceState.{name} must be a writable (3,) float64 array")
        self.pos_view = memoryview(self.position)
        self.vel_view = memoryview(self.velocity)


class Device(abc.ABC):
    """One haptic device: open, read state, write force, enable forces, close.

    Forces are accepted only while enabled; a disabled device renders zero.
    """

    info: DeviceInfo
    # True for a backend whose driver documents which errors are a lost device: it raises
    # DeviceLostError for those, so any other DeviceError is a device that still answers
    # (reconnect mode does not close and look for it again: the run ends with the fault).
    reports_lost: bool = False

    @abc.abstractmethod
    def open(self) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def read_state(self, state: DeviceState) -> None:
        """Fill ``state`` with the latest position, velocity, buttons and device time."""

    @abc.abstractmethod
    def write_force(self, force: np.ndarray) -> None:
        """Command ``force`` (3,) N. Raises DeviceError on non-finite or over-limit input."""

    @abc.abstractmethod
    def enable_forces(self, enabled: bool) -> None: ...

    def counts(self) -> dict[str, int]:
        """What the device's driver counted so far that is no error but a run's summary
        reports (e.g. the SDK's saturated motors), by name; none by default."""
        return {}

    @property
    def finished(self) -> bool:
        """True when a device that plays a trajectory has reached its end."""
        return False

    def __enter__(self) -> Device:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def check_force(force: np.ndarray, limit_n: float, who: str) -> tuple[float, float, float]:
    """Device-side guard: refuse non-finite or over-limit forces, as firmware would.

    Returns the accepted force's three components (N) as plain numbers, for a device that
    keeps or sends them without reading the array again."""
    # Plain floats, not numpy reductions: this runs for every device on every tick. A
    # (3,) array whose magnitude is within the limit passes with one tolist and one hypot
    # (NaN and inf fail the comparison); anything else takes the full check below.
    try:
        x, y, z = force.tolist()  # type: ignore[union-attr]
        if math.hypot(x, y, z) <= limit_n * (1.0 + 1e-9):
            return x, y, z
    except (AttributeError, TypeError, ValueError):
        pass
    return _check_slowly(force, limit_n, who)


def _check_slowly(force: object, limit_n: float, who: str) -> tuple[float, float, float]:
    """``check_force`` for any input (a list, a tuple, another shape, non-finite values):
    the force as three floats, or the DeviceError that says why it is refused."""
    given = force
    try:
        if getattr(force, "shape", None) is None:
            force = np.asarray(force, dtype=float)  # a list or tuple: the rare path
        if force.shape != (3,):  # type: ignore[union-attr]
            raise ValueError
        # One tolist, then float() of each, as float(force[i]) would convert.
        x, y, z = force.tolist()  # type: ignore[union-attr]
        x, y, z = float(x), float(y), float(z)
    except (TypeError, ValueError):
        x = y = z = math.nan
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise DeviceError(f"{who}: refused force {given!r}: expected 3 finite values in N")
    mag = math.hypot(x, y, z)
    if mag > limit_n * (1.0 + 1e-9):
        raise DeviceError(f"{who}: refused force of {mag:.6g} N above its limit {limit_n:g} N")
    return x, y, z
