"""The Novint Falcon's wire format and mechanism: pure functions, numpy in, numpy out.

Packets (both directions 16 bytes): ``<``, twelve nibble bytes, one status byte, one
spare byte, ``>``; every byte between the brackets is a 4-bit value plus 0x41 (``A``).
The host sends three signed 16-bit motor values (least significant nibble first), the
LED bits and the homing request; the firmware answers with three signed 16-bit encoder
values, the homed bit of each encoder (high nibble of the status byte) and the grip's
buttons (low nibble). The facts come from libnifalcon (docs/devices.md names the files).

The mechanism is Stamper's model of the Falcon's parallel arms: leg ``i`` turns its
thigh by ``theta1`` about an axis in a frame rotated by ``LEG_ANGLES[i]`` about z; the
shin parallelogram (``theta2``, ``theta3``) carries the end effector. For leg frame
coordinates (u, v, w) of the end effector,

    u = A cos theta1 - C + L cos theta2,  v = B cos theta3 - F,
    w = A sin theta1 + L sin theta2,      L = D + E + B sin theta3.

Inverse kinematics solves each leg in closed form; the Jacobian dtheta1/dp follows by
differentiating the loop closure (u + C - A cos theta1)^2 + (w - A sin theta1)^2 = L^2;
forward kinematics is Newton's method on the inverse. Positions are m in the device
frame: libnifalcon's axes (x right, y up, z toward the user) with the origin moved to
``CENTER``; angles rad; torques N m at the thigh.
"""

from __future__ import annotations

import math

import numpy as np
from hapticd_drivers import models

# -- packets ------------------------------------------------------------------------------

# The Falcon's FTDI chip: its row of the model table (libnifalcon FalconComm.h).
_ROW = models.by_name("Falcon")
assert _ROW is not None and _ROW.usb_ids
FALCON_VENDOR_ID, FALCON_PRODUCT_ID = _ROW.usb_ids[0]

PACKET_SIZE = 16
START, END = ord("<"), ord(">")
NIBBLE_OFFSET = 0x41
STATUS_BYTE = 13
HOMING_REQUEST = 0x01
LED_GREEN, LED_BLUE, LED_RED = 0x02, 0x04, 0x08
ALL_HOMED = 0x7
# The firmware takes signed 16-bit motor values; libnifalcon documents them capped at
# 4096 (FalconKinematic.h), which is the limit applied here before any value is sent.
MOTOR_LIMIT = 4096
# libnifalcon's getForces: motor value = -10000 x thigh torque (N m).
MOTOR_UNITS_PER_NM = 10000.0


class FalconPacketError(ValueError):
    """A packet that is not a Falcon packet: its length, frame or nibbles are wrong."""


def _nibbles(value: int) -> list[int]:
    v = value & 0xFFFF
    return [NIBBLE_OFFSET + ((v >> (4 * k)) & 0xF) for k in range(4)]


def _word(raw: bytes, first: int) -> int:
    v = 0
    for k in range(4):
        b = raw[first + k] - NIBBLE_OFFSET
        if not 0 <= b <= 0xF:
            raise FalconPacketError(
                f"byte {first + k} is 0x{raw[first + k]:02x}, not a nibble (0x41-0x50)"
            )
        v |= b << (4 * k)
    return v - 0x10000 if v & 0x8000 else v


def _frame(raw: bytes) -> None:
    if len(raw) != PACKET_SIZE:
        raise FalconPacketError(f"{len(raw)} bytes, expected {PACKET_SIZE}")
    if raw[0] != START or raw[-1] != END:
        raise FalconPacketError(f"frame {raw[:1]!r}...{raw[-1:]!r}, expected b'<'...b'>'")
    for i in (STATUS_BYTE, STATUS_BYTE + 1):
        if not NIBBLE_OFFSET <= raw[i] <= NIBBLE_OFFSET + 0x7F:
            raise FalconPacketError(f"byte {i} is 0x{raw[i]:02x}, outside 0x41-0xc0")


def _packet(words: tuple[int, int, int], status: int) -> bytes:
    body = [b for w in words for b in _nibbles(w)]
    return bytes([START, *body, NIBBLE_OFFSET + (status & 0x7F), NIBBLE_OFFSET, END])


def encode_command(motor: tuple[int, int, int], leds: int, homing: bool) -> bytes:
    """The host's packet: motor values (each within +-MOTOR_LIMIT), LED bits, homing."""
    if any(not -MOTOR_LIMIT <= int(m) <= MOTOR_LIMIT for m in motor):
        raise ValueError(f"motor values {tuple(motor)} beyond +-{MOTOR_LIMIT}")
    status = (leds & (LED_GREEN | LED_BLUE | LED_RED)) | (HOMING_REQUEST if homing else 0)
    return _packet((int(motor[0]), int(motor[1]), int(motor[2])), status)


def decode_command(raw: bytes) -> tuple[tuple[int, int, int], int, bool]:
    """(motor values, LED bits, homing requested) of a host packet (the emulator's side)."""
    _frame(raw)
    motor = (_word(raw, 1), _word(raw, 5), _word(raw, 9))
    status = raw[STATUS_BYTE] - NIBBLE_OFFSET
    return motor, status & (LED_GREEN | LED_BLUE | LED_RED), bool(status & HOMING_REQUEST)


def encode_state(encoders: tuple[int, int, int], homed: int, grip: int) -> bytes:
    """The firmware's packet: encoder counts (signed 16 bit), homed bits, grip buttons."""
    return _packet(
        (int(encoders[0]), int(encoders[1]), int(encoders[2])),
        ((homed & ALL_HOMED) << 4) | (grip & 0xF),
    )


def decode_state(raw: bytes) -> tuple[tuple[int, int, int], int, int]:
    """(encoder counts, homed bits, grip buttons) of a firmware packet."""
    _frame(raw)
    status = raw[STATUS_BYTE] - NIBBLE_OFFSET
    return (_word(raw, 1), _word(raw, 5), _word(raw, 9)), (status >> 4) & ALL_HOMED, status & 0xF


# -- mechanism ------------------------------------------------------------------------------

# Stamper's geometry as libnifalcon measured the Falcon (FalconGeometry.h), m.
A = 0.060  # thigh: leg base to knee
B = 0.1025  # shin parallelogram side
C = 0.01443  # shin joint to end-effector centre, u
D = 0.01125  # shin to end-effector joint
E = D  # knee to shin joint
F = -0.025  # shin joint to end-effector centre, v
R = 0.0400  # frame origin to leg base, u
S = -0.02309  # frame origin to leg base, v
_TILT = math.pi / 12  # each leg's axis is 15 degrees off the desk plane
LEG_ANGLES = (math.pi / 2 + _TILT, -math.pi / 6 + _TILT, -5 * math.pi / 6 + _TILT)

# Encoders: a 320-slot wheel read in quadrature on the 14.25 mm motor shaft, which
# drives the 110 mm arm drum; count 0 is about 35 degrees of thigh angle.
WHEEL_SLOTS = 320
SHAFT_DIAMETER = 0.01425
ARM_DIAMETER = 0.110
RAD_PER_COUNT = 2.0 * math.pi * SHAFT_DIAMETER / (4 * WHEEL_SLOTS * ARM_DIAMETER)
ANGLE_AT_ZERO = math.radians(35.0)

# The device frame's origin in libnifalcon's frame (m): there the whole 4 cm workspace
# sphere is reachable and well conditioned (docs/devices.md).
CENTER = (0.0, 0.0, 0.11)

# Plain floats, not numpy: three legs of three numbers, solved on every tick, run many
# times faster as scalar arithmetic than as tiny arrays.
_LEGS = tuple((math.cos(a), math.sin(a)) for a in LEG_ANGLES)
_CX, _CY, _CZ = (float(v) for v in CENTER)

Angles = tuple[float, float, float]


class FalconKinematicsError(ValueError):
    """A pose or joint state the Falcon's mechanism cannot take."""


def _leg(c: float, s: float, x: float, y: float, z: float) -> Angles:
    """(theta1, theta2, theta3) rad of the leg whose frame is turned by (cos, sin), at
    libnifalcon-frame position (x, y, z) m."""
    u = c * x + s * y - R
    v = -s * x + c * y - S
    cos3 = (v + F) / B
    if not -1.0 < cos3 < 1.0:
        raise FalconKinematicsError("out of the shins' reach")
    th3 = math.acos(cos3)
    L = D + E + B * math.sin(th3)
    # Loop closure in t = tan(theta1 / 2): k2 t^2 + k1 t + k0 = 0; the Falcon's branch is
    # the root with the minus sign.
    uc = u + C
    k = uc * uc + A * A + z * z - L * L
    k0, k1, k2 = k - 2.0 * A * uc, -4.0 * A * z, k + 2.0 * A * uc
    disc = k1 * k1 - 4.0 * k2 * k0
    if disc < 0.0 or k2 == 0.0:
        raise FalconKinematicsError("out of the thighs' reach")
    th1 = 2.0 * math.atan((-k1 - math.sqrt(disc)) / (2.0 * k2))
    th2 = math.atan2(z - A * math.sin(th1), uc - A * math.cos(th1))
    return th1, th2, th3


def _angles(x: float, y: float, z: float) -> list[Angles]:
    q = (x + _CX, y + _CY, z + _CZ)
    try:
        return [_leg(c, s, *q) for c, s in _LEGS]
    except FalconKinematicsError as exc:
        raise FalconKinematicsError(f"position ({x:.6g}, {y:.6g}, {z:.6g}) m is {exc}") from None


def _jacobian(angles: list[Angles]) -> list[list[float]]:
    rows = []
    for (c, s), (th1, th2, th3) in zip(_LEGS, angles, strict=True):
        s3 = math.sin(th3)
        den = A * math.sin(th1 - th2) * s3
        if abs(den) < 1e-12:
            raise FalconKinematicsError("a singular pose")
        du, dv, dw = -math.cos(th2) * s3 / den, -math.cos(th3) / den, -math.sin(th2) * s3 / den
        # Chain rule through the leg frame: u = c x + s y, v = -s x + c y, w = z.
        rows.append([du * c - dv * s, du * s + dv * c, dw])
    return rows


def _solve(m: list[list[float]], b: tuple[float, float, float]) -> tuple[float, float, float]:
    """x with m x = b for a 3x3 m (Cramer's rule)."""
    (a, b_, c), (d, e, f), (g, h, i) = m
    det = a * (e * i - f * h) - b_ * (d * i - f * g) + c * (d * h - e * g)
    if abs(det) < 1e-300:
        raise FalconKinematicsError("a singular pose")
    r0, r1, r2 = b
    x = (r0 * (e * i - f * h) - b_ * (r1 * i - f * r2) + c * (r1 * h - e * r2)) / det
    y = (a * (r1 * i - f * r2) - r0 * (d * i - f * g) + c * (d * r2 - r1 * g)) / det
    z = (a * (e * r2 - r1 * h) - b_ * (d * r2 - r1 * g) + r0 * (d * h - e * g)) / det
    return x, y, z


def leg_coordinates(p: np.ndarray) -> np.ndarray:
    """(3, 3): row i is device-frame position ``p`` (3,) m in leg i's (u, v, w) frame."""
    x, y, z = (float(v) + c for v, c in zip(p, CENTER, strict=True))
    return np.array([(c * x + s * y - R, -s * x + c * y - S, z) for c, s in _LEGS])


def leg_angles(p: np.ndarray) -> np.ndarray:
    """(3, 3): row i is (theta1, theta2, theta3) of leg i, rad, at device-frame ``p`` (3,) m."""
    x, y, z = (float(v) for v in p)
    return np.array(_angles(x, y, z))


def inverse(p: np.ndarray) -> np.ndarray:
    """Thigh angles (3,) rad at device-frame position ``p`` (3,) m."""
    x, y, z = (float(v) for v in p)
    return np.array([a[0] for a in _angles(x, y, z)])


def joint_jacobian(p: np.ndarray) -> np.ndarray:
    """(3, 3) dtheta1/dp at ``p`` (rad/m): thigh rates = this @ end-effector velocity,
    and end-effector force = this.T @ thigh torques."""
    x, y, z = (float(v) for v in p)
    return np.array(_jacobian(_angles(x, y, z)))


def forward(theta: np.ndarray, guess: np.ndarray | None = None, tol: float = 1e-13) -> np.ndarray:
    """Device-frame position (3,) m whose thigh angles are ``theta`` (3,) rad, by Newton's
    method from ``guess`` (the last position; default the origin), halving a step that
    leaves the workspace or grows the error. FalconKinematicsError when the angles are
    not a pose of the mechanism."""
    t0, t1, t2 = (float(v) for v in theta)
    x, y, z = (0.0, 0.0, 0.0) if guess is None else (float(v) for v in guess)
    try:
        ang = _angles(x, y, z)
    except FalconKinematicsError:
        x, y, z = 0.0, 0.0, 0.0
        ang = _angles(x, y, z)
    err = (t0 - ang[0][0], t1 - ang[1][0], t2 - ang[2][0])
    size = max(abs(err[0]), abs(err[1]), abs(err[2]))
    for _ in range(60):
        dx, dy, dz = _solve(_jacobian(ang), err)
        for _ in range(30):
            try:
                nang = _angles(x + dx, y + dy, z + dz)
                nerr = (t0 - nang[0][0], t1 - nang[1][0], t2 - nang[2][0])
                nsize = max(abs(nerr[0]), abs(nerr[1]), abs(nerr[2]))
                if nsize <= size or max(abs(dx), abs(dy), abs(dz)) < tol:
                    break
            except FalconKinematicsError:
                pass
            dx, dy, dz = dx * 0.5, dy * 0.5, dz * 0.5
        else:
            break
        x, y, z = x + dx, y + dy, z + dz
        ang, err, size = nang, nerr, nsize
        if max(abs(dx), abs(dy), abs(dz)) < tol:
            return np.array([x, y, z])
    raise FalconKinematicsError(f"thigh angles {list(theta)} rad are not a pose of the mechanism")


def angles_from_counts(counts: np.ndarray) -> np.ndarray:
    """Thigh angles (3,) rad of encoder counts (3,)."""
    return np.asarray(counts, dtype=float) * RAD_PER_COUNT + ANGLE_AT_ZERO


def counts_from_angles(theta: np.ndarray) -> np.ndarray:
    """Encoder counts (3,) int of thigh angles (3,) rad."""
    return np.rint((np.asarray(theta, dtype=float) - ANGLE_AT_ZERO) / RAD_PER_COUNT).astype(int)


def motor_values(p: np.ndarray, force: np.ndarray) -> np.ndarray:
    """Motor values (3,) int for ``force`` (3,) N at ``p`` (3,) m: thigh torques
    tau = J^T f with J = dp/dtheta1, scaled down together so none passes MOTOR_LIMIT
    (the force keeps its direction)."""
    x, y, z = (float(v) for v in p)
    j = _jacobian(_angles(x, y, z))
    jt = [[j[0][k], j[1][k], j[2][k]] for k in range(3)]
    fx, fy, fz = (float(v) for v in force)
    motor = [-MOTOR_UNITS_PER_NM * t for t in _solve(jt, (fx, fy, fz))]
    if not all(math.isfinite(m) for m in motor):
        raise FalconKinematicsError(f"no finite motor values for {force} N at {p} m")
    peak = max(abs(m) for m in motor)
    scale = MOTOR_LIMIT / peak if peak > MOTOR_LIMIT else 1.0
    return np.array([max(-MOTOR_LIMIT, min(MOTOR_LIMIT, round(m * scale))) for m in motor])


def force_from_motor(p: np.ndarray, motor: np.ndarray) -> np.ndarray:
    """End-effector force (3,) N the motors exert at ``p`` for motor values (3,)."""
    tau = -np.asarray(motor, dtype=float) / MOTOR_UNITS_PER_NM
    return joint_jacobian(p).T @ tau
