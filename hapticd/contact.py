"""God-object (proxy) contact of a spherical fingertip against a convex polytope.

The proxy is the sphere centre the finger *should* have: it follows the device
position but never enters the object inflated by the sphere radius. Each update
moves the proxy from its previous position toward the device position, stopping
at the first face the path enters and then sliding on up to three active
constraint planes (face, edge, corner), after Zilles & Salisbury (1995). A fast
finger therefore cannot pop through a thin part of the object. The proxy ends on
the projection of the device onto its active planes, so proxy - device is their
multipliers times their normals and frictionless contact is conservative in any
orientation (k x depth along a face's normal). A path that runs along a plane to
rounding (within ``_ON_PLANE``) does not enter through it.

Units: m. Planes are half-spaces n . x <= d with unit outward normals n.
Pure functions on numpy arrays; the only state is the proxy position, passed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

# A point within this distance (m) of a plane counts as on it. A proxy that slides on a
# face lies on its plane only to rounding (some 1e-17 m at hand scale, whatever the face's
# orientation), and so does the projection of the device onto it: a path between two such
# points lies on the plane, it does not enter the object through it.
_ON_PLANE = 1e-13
# Segment parameters closer than this count as touching, not entering: keeps a path that
# grazes an edge from capturing the proxy there.
_T_EPS = 1e-12
_MAX_CONSTRAINTS = 3


@dataclass(frozen=True)
class Polytope:
    """Convex polytope as half-spaces: normals (m, 3) unit, offsets (m,) in m."""

    normals: np.ndarray
    offsets: np.ndarray
    center: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "obstacle_set", None)

    # Plain-float copies for the Python proxy update, which runs per finger per tick (numpy's
    # per-call overhead on 3-vectors would dominate it); made on first use, so that a free
    # object's polytope, new every tick, costs them only when the Python code reads them.
    @cached_property
    def normals_list(self) -> list[tuple[float, float, float]]:
        """The unit normals as tuples of floats (m, 3)."""
        return [tuple(n) for n in self.normals.tolist()]

    @cached_property
    def offsets_list(self) -> list[float]:
        """The offsets as floats (m,), m."""
        return self.offsets.tolist()

    def inflated(self, radius: float) -> Polytope:
        """The polytope grown by ``radius`` (m) along every face normal."""
        return Polytope(self.normals, self.offsets + radius, self.center)

    def signed_distance(self, x: np.ndarray) -> float:
        """max_i (n_i . x - d_i): > 0 outside, < 0 inside (exact inside, a lower bound outside)."""
        return float(np.max(self.normals @ np.asarray(x, dtype=float) - self.offsets))


def box_polytope(center: np.ndarray, rotation: np.ndarray, size: np.ndarray) -> Polytope:
    """Box with edge lengths ``size`` (3,) m at ``center``, axes the columns of ``rotation``."""
    c = np.asarray(center, dtype=float).reshape(3)
    R = np.asarray(rotation, dtype=float).reshape(3, 3)
    h = 0.5 * np.asarray(size, dtype=float).reshape(3)
    normals = np.vstack([R.T, -R.T])  # +x, +y, +z, -x, -y, -z faces in world frame
    offsets = np.concatenate([R.T @ c + h, -(R.T @ c) + h])
    return Polytope(normals, offsets, c)


@dataclass
class ProxyResult:
    """Outcome of one proxy update.

    proxy (3,) m: new proxy (sphere centre); in_contact: at least one active
    constraint; normal (3,): unit outward contact normal (zeros when free);
    n_active: number of active constraint planes (0-3).
    """

    proxy: np.ndarray
    in_contact: bool
    normal: np.ndarray
    n_active: int


Vec = tuple[float, float, float]


def _dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _first_entry(
    normals: list[Vec], offsets: list[float], p: Vec, d: Vec
) -> tuple[float, int] | None:
    """First t in [0, 1) where p + t d enters the open interior, and the plane entered.

    None when the segment stays outside, or on the surface to ``_ON_PLANE``: a segment
    whose two ends are both outside or on one plane never enters. A crossing time is
    computed only when it lies on the segment (no ratio of two rounding errors, no
    overflow for a path parallel to a far plane).
    """
    t_enter = 0.0
    t_exit = math.inf
    plane = -1
    # The hottest loop of a tick: components in locals.
    dx, dy, dz = d
    px, py, pz = p
    for i, (nx, ny, nz) in enumerate(normals):
        num = offsets[i] - (nx * px + ny * py + nz * pz)  # how far p is inside plane i
        denom = nx * dx + ny * dy + nz * dz
        if num <= _ON_PLANE:
            if num - denom <= _ON_PLANE:
                return None  # both ends outside or on plane i: never inside
            # Enters plane i's half-space on the segment (at t <= 0 when p is on it).
            if num < 0.0:
                t = num / denom
                if t > t_enter:
                    t_enter, plane = t, i
            elif plane < 0:
                plane = i
        elif denom > num:
            t = num / denom  # leaves plane i's half-space on the segment
            if t < t_exit:
                t_exit = t
    if plane < 0:
        # Inside every plane by more than _ON_PLANE (only if a push-out could not clear
        # another obstacle): in at once, through the nearest plane.
        return 0.0, _signed_distance(normals, offsets, p)[1]
    if t_exit <= t_enter + _T_EPS:
        return None
    return t_enter, plane


# Below this Gram determinant (two planes: sin^2 of their angle, within 3e-5 rad of
# parallel; three: the squared volume their normals span) the Gram system counts as
# singular and ``_gram_solve`` takes its minimum-norm rule instead of the inverse.
_GRAM_MIN = 1e-9


def _gram_solve(ns: list[Vec], rhs: list[float]) -> list[float]:
    """mu (k,) solving G mu = rhs for the Gram matrix G = N N^T of k = 1-3 unit normals.

    Plain float sums in a fixed order (``hapticd.kernels.contact_step`` repeats them
    bit for bit): the 2 x 2 and 3 x 3 systems by their adjugates (Cramer's rule), the
    unit diagonal taken as exactly 1. A singular system (determinant <= ``_GRAM_MIN``)
    takes a closed-form minimum-norm rule instead of an inverse that would throw the
    proxy far away:

    - two (nearly) parallel or antiparallel planes (cosine c, s its sign): G's
      pseudo-inverse with its small eigenvalue 1 - |c| dropped, mu = (m, s m) with
      m = (r0 + s r1) / (2 (1 + |c|)) (numpy's ``lstsq`` for exactly parallel planes).
      Parallel planes share the push; antiparallel ones (a finger between two faces
      that face each other) get multipliers of opposite signs, so one is released;
    - three planes of which two, u and v, are (nearly) parallel: those two act as one
      plane (normal n_u, right-hand side (r_u + s r_v) / 2), solved with the third;
      their multiplier a is split evenly, (a / 2, s a / 2). All three parallel: the
      rank-one pseudo-inverse, mu_i = s_i (sum_j s_j r_j) / 9;
    - three pairwise distinct normals in (nearly) one plane: the best-conditioned
      pair (the largest 2 x 2 determinant, the first on a tie), the third's multiplier 0.

    Multipliers keep their meaning: mu_i > 0 where plane i pushes outward.
    """
    if len(ns) == 1:
        return [rhs[0]]
    if len(ns) == 2:
        r0, r1 = rhs[0], rhs[1]
        c = _dot(ns[0], ns[1])
        det = 1.0 - c * c
        if det > _GRAM_MIN:
            return [(r0 - c * r1) / det, (r1 - c * r0) / det]
        s = 1.0 if c >= 0.0 else -1.0
        m = (r0 + s * r1) / (2.0 * (1.0 + abs(c)))
        return [m, s * m]
    a = _dot(ns[0], ns[1])
    b = _dot(ns[0], ns[2])
    c = _dot(ns[1], ns[2])
    # The adjugate of [[1, a, b], [a, 1, c], [b, c, 1]] and its determinant.
    a00 = 1.0 - c * c
    a11 = 1.0 - b * b
    a22 = 1.0 - a * a
    a01 = b * c - a
    a02 = a * c - b
    a12 = a * b - c
    det = a00 + a * a01 + b * a02
    r0, r1, r2 = rhs[0], rhs[1], rhs[2]
    if det > _GRAM_MIN:
        return [
            (a00 * r0 + a01 * r1 + a02 * r2) / det,
            (a01 * r0 + a11 * r1 + a12 * r2) / det,
            (a02 * r0 + a12 * r1 + a22 * r2) / det,
        ]
    mu = [0.0, 0.0, 0.0]
    # The pairs' 2 x 2 determinants: 1 - a^2 (planes 0, 1), 1 - b^2 (0, 2), 1 - c^2 (1, 2).
    if a22 <= _GRAM_MIN or a11 <= _GRAM_MIN or a00 <= _GRAM_MIN:
        # A (nearly) parallel pair u, v (the most parallel), w the third; cuw = n_u . n_w.
        if a22 <= a11 and a22 <= a00:
            u, v, w, cuv, cuw, ru, rv, rw = 0, 1, 2, a, b, r0, r1, r2
        elif a11 <= a00:
            u, v, w, cuv, cuw, ru, rv, rw = 0, 2, 1, b, a, r0, r2, r1
        else:
            u, v, w, cuv, cuw, ru, rv, rw = 1, 2, 0, c, a, r1, r2, r0
        s = 1.0 if cuv >= 0.0 else -1.0
        rm = (ru + s * rv) / 2.0
        d2 = 1.0 - cuw * cuw
        if d2 > _GRAM_MIN:
            am = (rm - cuw * rw) / d2
            mu[w] = (rw - cuw * rm) / d2
        else:  # all three (anti)parallel
            t = 1.0 if cuw >= 0.0 else -1.0
            m = (ru + s * rv + t * rw) / 9.0
            mu[u] = m
            mu[v] = s * m
            mu[w] = t * m
            return mu
        mu[u] = am / 2.0
        mu[v] = s * am / 2.0
        return mu
    # Three distinct normals in (nearly) one plane: the best-conditioned pair.
    if a22 >= a11 and a22 >= a00:
        u, v, cc, ru, rv = 0, 1, a, r0, r1
    elif a11 >= a00:
        u, v, cc, ru, rv = 0, 2, b, r0, r2
    else:
        u, v, cc, ru, rv = 1, 2, c, r1, r2
    d2 = 1.0 - cc * cc
    mu[u] = (ru - cc * rv) / d2
    mu[v] = (rv - cc * ru) / d2
    return mu


def _project_on_planes(
    dev: Vec, normals: list[Vec], offsets: list[float], active: list[int]
) -> tuple[Vec, list[float]]:
    """Closest point to ``dev`` on the intersection of the active planes, and the multipliers.

    Returns (x, mu) with x - dev = sum_i mu_i n_i; mu_i >= 0 means plane i pushes
    outward (a true contact), mu_i < 0 means it would pull and must be released.
    Singular systems (near-parallel planes) take ``_gram_solve``'s minimum-norm rule.
    """
    if len(active) == 1:
        n = normals[active[0]]
        mu = offsets[active[0]] - _dot(n, dev)
        return (dev[0] + mu * n[0], dev[1] + mu * n[1], dev[2] + mu * n[2]), [mu]
    ns = [normals[i] for i in active]
    mus = _gram_solve(ns, [offsets[i] - _dot(normals[i], dev) for i in active])
    x0, x1, x2 = dev
    for m, n in zip(mus, ns, strict=True):
        x0 += m * n[0]
        x1 += m * n[1]
        x2 += m * n[2]
    return (x0, x1, x2), mus


def _signed_distance(normals: list[Vec], offsets: list[float], x: Vec) -> tuple[float, int]:
    best, arg = -math.inf, 0
    x0, x1, x2 = x
    for i, (nx, ny, nz) in enumerate(normals):
        v = nx * x0 + ny * x1 + nz * x2 - offsets[i]
        if v > best:
            best, arg = v, i
    return best, arg


# Proxy moves per update: each face a fast finger crosses on a convex mesh takes two (slide
# off, re-enter), and 2 cm per tick over a sphere of 5 mm faces took up to 14.
_MAX_ITER = 16
_FREE_TOL = 1e-12


Obstacle = tuple[list[Vec], list[float]]  # (unit normals, offsets) of one convex obstacle


@dataclass
class MultiResult:
    """Proxy against several convex obstacles: position, active (obstacle, plane) pairs and,
    per pair, the multiplier mu with proxy - device = sum mu n (m)."""

    proxy: Vec
    active: list[tuple[int, int]]
    mu: list[float]


def _distance(prepared: ObstacleSet, j: int, p: Vec) -> float:
    arr = prepared.arrays[j]
    if arr is not None:
        return float(np.max(arr[0] @ np.asarray(p) - arr[1]))
    return _signed_distance(*prepared.obstacles[j], p)[0]


def _push_out_of(obstacles: list[Obstacle], p: Vec, prepared: ObstacleSet) -> Vec:
    """``p`` moved out of every obstacle it is inside (a first tick, or a moving object).

    Out through the nearest plane of each; once a push has gone through the planes of two
    or three obstacles (a crease, where one push undoes another: slowly, in an acute one),
    onto the projection of the starting point onto all those planes instead.
    """
    if not prepared.may_be_inside(p):
        return p
    start = p
    pushed: list[int] = []  # the planes pushed through (indices into prepared's flat lists)
    for _ in range(len(obstacles) + 1):
        moved = False
        for j, (normals, offsets) in enumerate(obstacles):
            arr = prepared.arrays[j]
            if arr is not None:
                dists = arr[0] @ np.asarray(p) - arr[1]
                i = int(np.argmax(dists))
                dist = float(dists[i])
            else:
                dist, i = _signed_distance(normals, offsets, p)
            if dist < 0.0:
                moved = True
                k = prepared.index[(j, i)]
                if k not in pushed and len(pushed) < _MAX_CONSTRAINTS:
                    pushed.append(k)
                if len(pushed) > 1:
                    x, mu = _project_on_planes(start, prepared.normals, prepared.offsets, pushed)
                    if min(mu) >= 0.0:
                        p = x
                        continue
                n = normals[i]
                p = (p[0] - dist * n[0], p[1] - dist * n[1], p[2] - dist * n[2])
        if not moved:
            break
    return p


# Obstacles with more planes than this take the vectorised tests (numpy beats a Python loop).
_VECTOR_PLANES = 200


def _first_entry_np(N: np.ndarray, off: np.ndarray, p: Vec, d: Vec) -> tuple[float, int] | None:
    """``_first_entry`` vectorised over the planes of one large obstacle."""
    num = off - N @ np.asarray(p)
    denom = N @ np.asarray(d)
    near = num <= _ON_PLANE
    end = num - denom
    if np.any(near & (end <= _ON_PLANE)):
        return None
    if not near.any():
        return 0.0, int(np.argmin(num))
    # Crossing times only where they lie on the segment: every divisor is away from 0.
    crossing = near & (num < 0.0)
    t = np.zeros_like(num)
    np.divide(num, denom, out=t, where=crossing)
    plane = int(np.argmax(np.where(near, t, -1.0)))
    t_enter = float(t[plane])
    leaving = ~near & (end < 0.0)
    t_exit = float(np.min(num[leaving] / denom[leaving])) if leaving.any() else math.inf
    if t_exit <= t_enter + _T_EPS:
        return None
    return t_enter, plane


def _first_entry_any(
    obstacles: list[Obstacle],
    p: Vec,
    d: Vec,
    arrays: list[tuple[np.ndarray, np.ndarray] | None] | None = None,
) -> tuple[float, int, int] | None:
    best: tuple[float, int, int] | None = None
    for j, (normals, offsets) in enumerate(obstacles):
        arr = arrays[j] if arrays is not None else None
        hit = (
            _first_entry_np(*arr, p, d) if arr is not None else _first_entry(normals, offsets, p, d)
        )
        if hit is not None and (best is None or hit[0] < best[0]):
            best = (hit[0], j, hit[1])
    return best


def _multipliers(
    obstacles: list[Obstacle], active: list[tuple[int, int]], p: Vec, dev: Vec
) -> list[float]:
    """mu with p - dev = sum mu_i n_i over the ``active`` planes, in the least-squares
    sense (G mu = N (p - dev), ``_gram_solve``)."""
    diff = (p[0] - dev[0], p[1] - dev[1], p[2] - dev[2])
    ns = [obstacles[j][0][i] for j, i in active]
    return _gram_solve(ns, [_dot(diff, n) for n in ns])


class ObstacleSet:
    """Obstacles prepared for ``proxy_step_multi``: their planes flattened once."""

    def __init__(self, obstacles: list[Obstacle]) -> None:
        self.obstacles = obstacles
        self.planes = [
            (j, i) for j, (normals, _) in enumerate(obstacles) for i in range(len(normals))
        ]
        self.normals = [obstacles[j][0][i] for j, i in self.planes]
        self.offsets = [obstacles[j][1][i] for j, i in self.planes]
        self.index = {pi: k for k, pi in enumerate(self.planes)}
        self.arrays = [
            (np.array(n), np.array(o)) if len(n) > _VECTOR_PLANES else None for n, o in obstacles
        ]
        self.spans = _spans(obstacles, self.arrays)

    def may_be_inside(self, p: Vec) -> bool:
        """False when ``p`` is outside or on every obstacle (some plane of each has
        n . p - d >= 0, the same sums as ``_signed_distance``): one pass over the flat
        planes, leaving each obstacle at its first plane that clears ``p``. True when
        it is inside one, for a NaN, or with a large (vectorised) obstacle."""
        if self.spans is None:
            return True
        normals, offsets = self.normals, self.offsets
        x0, x1, x2 = p
        for lo, hi in self.spans:
            for i in range(lo, hi):
                nx, ny, nz = normals[i]
                if nx * x0 + ny * x1 + nz * x2 - offsets[i] >= 0.0:
                    break
            else:
                return True
        return False

    def with_first(self, normals: list[Vec], offsets: list[float]) -> ObstacleSet:
        """The same set with obstacle 0 (the object) replaced by one of as many planes:
        what a moving object needs each tick, without re-flattening the static ones."""
        if len(normals) != len(self.obstacles[0][0]):
            return ObstacleSet([(normals, offsets), *self.obstacles[1:]])
        new = object.__new__(ObstacleSet)
        new.obstacles = [(normals, offsets), *self.obstacles[1:]]
        n0 = len(normals)
        new.planes = self.planes
        new.normals = normals + self.normals[n0:]
        new.offsets = offsets + self.offsets[n0:]
        new.index = self.index
        first = (np.array(normals), np.array(offsets)) if n0 > _VECTOR_PLANES else None
        new.arrays = [first, *self.arrays[1:]]
        new.spans = self.spans if first is None else None
        return new


def _spans(
    obstacles: list[Obstacle], arrays: list[tuple[np.ndarray, np.ndarray] | None]
) -> list[tuple[int, int]] | None:
    """Each obstacle's range in the flat plane lists; None if any is vectorised."""
    if any(a is not None for a in arrays):
        return None
    spans, lo = [], 0
    for normals, _ in obstacles:
        spans.append((lo, lo + len(normals)))
        lo += len(normals)
    return spans


def proxy_step_multi(
    obstacles: list[Obstacle] | ObstacleSet, proxy_prev: Vec, device: Vec
) -> MultiResult:
    """God-object step against the union of convex ``obstacles`` (each inflated by the radius).

    The proxy moves from ``proxy_prev`` toward ``device``, stops where the path
    enters any obstacle, then slides on at most three active planes (which may
    belong to different obstacles: a finger in the crease between the object and
    the ground has two), releasing planes that would pull and obstacles it has
    slid off.
    """
    prepared = obstacles if isinstance(obstacles, ObstacleSet) else ObstacleSet(obstacles)
    obstacles = prepared.obstacles
    all_normals, all_offsets, index = prepared.normals, prepared.offsets, prepared.index
    dev = device  # the device (fingertip centre) position
    p = _push_out_of(obstacles, proxy_prev, prepared)
    active: list[tuple[int, int]] = []
    held: list[float] | None = None  # the multipliers, once the proxy rests on the projection
    for _ in range(_MAX_ITER):
        if active:
            target, mu = _project_on_planes(
                dev, all_normals, all_offsets, [index[a] for a in active]
            )
        else:
            target, mu = dev, []
        d = (target[0] - p[0], target[1] - p[1], target[2] - p[2])
        hit = _first_entry_any(obstacles, p, d, prepared.arrays)
        if hit is not None:
            t, j, i = hit
            p = (p[0] + t * d[0], p[1] + t * d[1], p[2] + t * d[2])
            if (j, i) in active or len(active) == _MAX_CONSTRAINTS:
                break  # numerically stuck in a corner: stay at the contact point
            active.append((j, i))
            continue
        p = target
        if not active:
            break
        # Slid off an obstacle into free space: its planes no longer hold the proxy.
        touching = {j for j, _ in active if _distance(prepared, j, p) <= _FREE_TOL}
        keep = [a for a, m in zip(active, mu, strict=True) if a[0] in touching and m >= 0.0]
        if len(keep) == len(active):
            held = mu
            break
        active = keep
    if held is not None:
        # The proxy is the projection: proxy - device = sum mu n over the planes that push
        # (mu > 0), whether or not the device is inside that obstacle (a finger pressed into
        # the ground that slides into the cube pushes it).
        if all(m > 0.0 for m in held):
            return MultiResult(p, active, held)
        keep = [k for k, m in enumerate(held) if m > 0.0]
        return MultiResult(p, [active[k] for k in keep], [held[k] for k in keep])
    # Stopped short of a projection (stuck, or out of moves): a plane the device is outside
    # of does not push.
    pushing = [(j, i) for j, i in active if _dot(obstacles[j][0][i], dev) < obstacles[j][1][i]]
    mu = _multipliers(obstacles, pushing, p, dev) if pushing else []
    return MultiResult(p, pushing, mu)


def _normal(normals: list[Vec], res: MultiResult, dev: Vec) -> Vec:
    p = res.proxy
    if not res.active:
        return (0.0, 0.0, 0.0)
    diff = (p[0] - dev[0], p[1] - dev[1], p[2] - dev[2])
    depth = math.sqrt(_dot(diff, diff))
    if depth > 1e-15:
        return (diff[0] / depth, diff[1] / depth, diff[2] / depth)
    s = [sum(normals[i][k] for _, i in res.active) for k in range(3)]
    ns = math.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    return (s[0] / ns, s[1] / ns, s[2] / ns)


def proxy_step(
    normals: list[Vec], offsets: list[float], proxy_prev: Vec, device: Vec
) -> tuple[Vec, int, Vec]:
    """Single-obstacle ``proxy_step_multi``: (proxy, n_active, unit normal or zeros)."""
    res = proxy_step_multi(ObstacleSet([(normals, offsets)]), proxy_prev, device)
    return res.proxy, len(res.active), _normal(normals, res, device)


def update_proxy(poly: Polytope, proxy_prev: np.ndarray, device: np.ndarray) -> ProxyResult:
    """Move the proxy from ``proxy_prev`` toward ``device`` without entering ``poly``.

    ``poly`` must already be inflated by the fingertip radius. If ``proxy_prev``
    is inside (first tick, or a moved object), it is first pushed out through
    the nearest face. Every move either stops where the path enters the
    interior or ends at a target it reaches without entering, so the proxy is
    never inside.
    """
    dev: Vec = (float(device[0]), float(device[1]), float(device[2]))
    p: Vec = (float(proxy_prev[0]), float(proxy_prev[1]), float(proxy_prev[2]))
    if poly.obstacle_set is None:
        object.__setattr__(
            poly, "obstacle_set", ObstacleSet([(poly.normals_list, poly.offsets_list)])
        )
    res = proxy_step_multi(poly.obstacle_set, p, dev)
    p = res.proxy
    n_active = len(res.active)
    normal = _normal(poly.normals_list, res, dev)
    return ProxyResult(np.array(p), n_active > 0, np.array(normal), n_active)


def spring_force(
    stiffness: float, damping: float, proxy: np.ndarray, device: np.ndarray, velocity: np.ndarray
) -> np.ndarray:
    """Force on the finger (3,) N: k (proxy - device) - b v, with k in N/m and b in N s/m."""
    return stiffness * (proxy - device) - damping * velocity
