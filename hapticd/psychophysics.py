"""Psychometric functions for the method of constant stimuli, and the paired t-test.

A two-interval "was the second stiffer (heavier)?" experiment gives, per comparison
level x (in the varied parameter's SI unit), how often the comparison was judged
more. ``fit_psychometric`` fits, by maximum likelihood on the binomial counts,

    psi(x) = l/2 + (1 - l) Phi((x - mu) / sigma)

with the lapse rate l bounded in [0, lapse_max]. The point of subjective equality is
PSE = mu and the just noticeable difference JND = x(p) - x(0.5) of the curve
without lapse, at the JND point p: 0.75 by default (0.6745 sigma), 0.84 (0.9945
sigma, about one sigma) where a lab defines it so; the Weber fraction is JND /
standard (/work/shared/notes/grasp-math.md, "Psychometrics"). The fit is the global
maximum of the likelihood over the bounded parameters (a grid over PSE, sigma and
lapse, its highest peaks polished). The JND's confidence interval is a parametric
bootstrap: data simulated from the fitted curve, refitted, and the bias-corrected and
accelerated (BCa) percentile interval of the refitted JNDs; an end the refits push to
a search bound is reported unbounded (None), never as the bound.

Data that cannot determine a curve gives ``estimable=False`` and a ``reason``, never
an arbitrary number: fewer than three levels or ``min_trials`` trials, every answer
the same, answers that jump from all "no" to all "yes" between two levels, a flat
curve (sigma at its bound, 4 level ranges), a PSE outside the tested levels, or a
curve steeper than the levels resolve (sigma below a quarter of the smallest
spacing). The optimiser's parameters are bounded, so no fit runs away.

Pure: numpy and scipy in, numbers out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize, special, stats

# x(0.75) - x(0.5) of a cumulative normal with sigma 1.
Z75 = float(stats.norm.ppf(0.75))
# The JND points an experiment may define its JND by (docs/experiments.md).
JND_POINTS = (0.75, 0.84)


def jnd_z(point: float) -> float:
    """x(point) - x(0.5) of a cumulative normal with sigma 1: the JND in sigmas."""
    if not 0.5 < point < 1.0:
        raise ValueError(f"the JND point must be in (0.5, 1), got {point}")
    return float(stats.norm.ppf(point))


# Bounds in normalised units (z = (x - centre) / range of the levels): the PSE may lie
# at most one level range beyond the tested levels; sigma from 1/1000 of the range
# (a step the levels cannot resolve) to 4 ranges (the curve rises from 0.45 to 0.55
# over the tested levels: flat).
_MU_BOUND = 1.5
_SIGMA_LO = 1e-3
_SIGMA_HI = 4.0
_SQRT_2PI = float(np.sqrt(2 * np.pi))
_PEAKS = 8  # grid peaks polished by the global search
_P_EPS = 1e-15  # probabilities are kept in [eps, 1 - eps]: finite log-likelihood


@dataclass(frozen=True)
class PsychometricFit:
    """A fitted psychometric function; the numbers are in the levels' unit (lapse: a
    probability). ``jnd`` is x(jnd_point) - x(0.5). An interval end that is None is
    unbounded (the data do not bound it; the search's bound was reached). When
    ``estimable`` is false, ``reason`` says why and every estimate is None."""

    estimable: bool
    reason: str | None
    pse: float | None
    jnd: float | None
    sigma: float | None
    lapse: float | None
    jnd_ci: tuple[float | None, float | None] | None
    pse_ci: tuple[float | None, float | None] | None
    n_trials: float
    n_levels: int
    log_likelihood: float | None
    jnd_point: float = 0.75

    def predict(self, x: np.ndarray | float) -> np.ndarray:
        """psi(x): the fitted probability of judging the comparison more, shape of x."""
        if not self.estimable:
            raise ValueError(f"no curve to evaluate: {self.reason}")
        assert self.pse is not None and self.sigma is not None and self.lapse is not None
        u = (np.asarray(x, dtype=float) - self.pse) / self.sigma
        return self.lapse / 2 + (1 - self.lapse) * special.ndtr(u)


def _psi(z: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """psi at normalised levels z (L,) for parameters theta (..., 3): shape (..., L)."""
    m, s, lapse = theta[..., 0:1], theta[..., 1:2], theta[..., 2:3]
    return lapse / 2 + (1 - lapse) * special.ndtr((z - m) / s)


def _loglik(p: np.ndarray, k: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Binomial log-likelihood (without the constant) summed over the last axis."""
    p = np.clip(p, _P_EPS, 1 - _P_EPS)
    return np.sum(k * np.log(p) + (n - k) * np.log1p(-p), axis=-1)


def _nll_and_grad(
    theta: np.ndarray, z: np.ndarray, k: np.ndarray, n: np.ndarray
) -> tuple[float, np.ndarray]:
    m, s, lapse = theta
    u = (z - m) / s
    phi = np.exp(-0.5 * u * u) / _SQRT_2PI
    p = np.clip(lapse / 2 + (1 - lapse) * special.ndtr(u), _P_EPS, 1 - _P_EPS)
    nll = -float(np.sum(k * np.log(p) + (n - k) * np.log1p(-p)))
    r = (k - n * p) / (p * (1 - p))
    dp = np.stack([-(1 - lapse) * phi / s, -(1 - lapse) * phi * u / s, 0.5 - special.ndtr(u)])
    return nll, -(dp @ r)


def _bounds(lapse_max: float) -> np.ndarray:
    return np.array([[-_MU_BOUND, _MU_BOUND], [_SIGMA_LO, _SIGMA_HI], [0.0, lapse_max]])


def _grid_peaks(z: np.ndarray, k: np.ndarray, n: np.ndarray, lapse_max: float) -> np.ndarray:
    """The highest local maxima of the log-likelihood on a grid over the whole bounded
    parameter space, best first: (<= _PEAKS, 3). The grid's PSE step (1/40 of the level
    range) is finer than any level spacing, and sigma runs over its whole range (64
    log steps), so every hill of the likelihood, a near-step curve's too, has a grid
    point on its slope."""
    m = np.linspace(-_MU_BOUND, _MU_BOUND, 121)
    s = np.geomspace(_SIGMA_LO, _SIGMA_HI, 64)
    lapses = np.linspace(0.0, lapse_max, 7) if lapse_max > 0 else np.zeros(1)
    grid = np.stack(np.meshgrid(m, s, lapses, indexing="ij"), axis=-1)
    ll = _loglik(_psi(z, grid.reshape(-1, 3)), k, n).reshape(grid.shape[:3])
    peak = ll >= ndimage.maximum_filter(ll, size=3, mode="nearest")
    idx = np.flatnonzero(peak)
    idx = idx[np.argsort(-ll.reshape(-1)[idx], kind="stable")[:_PEAKS]]
    return grid.reshape(-1, 3)[idx]


def _fit_one(z: np.ndarray, k: np.ndarray, n: np.ndarray, lapse_max: float) -> np.ndarray:
    """The global maximum-likelihood parameters (normalised units): every high peak of a
    grid over the bounded parameter space (``_grid_peaks``) and the near-step curves
    polished by Fisher scoring, then L-BFGS-B from each; the best of all. Starting from
    the grid's best point alone finds a lower hill in about 1 % of series."""
    bounds = _bounds(lapse_max)
    starts = np.vstack([_grid_peaks(z, k, n, lapse_max), *_steep_starts(z, k, n, lapse_max)])
    cands = _fit_batch(z, np.tile(k, (len(starts), 1)), n, starts, lapse_max)
    polished = [cands]
    # Starts on one hill reach the same point by scoring: polish each point once.
    distinct: list[np.ndarray] = []
    for c in cands:
        if all(np.max(np.abs(c - d)) > 1e-7 for d in distinct):
            distinct.append(c)
    for start in distinct:
        res = optimize.minimize(
            _nll_and_grad,
            start,
            args=(z, k, n),
            jac=True,
            method="L-BFGS-B",
            bounds=bounds,
            options={"maxiter": 500, "ftol": 1e-14, "gtol": 1e-10},
        )
        polished.append(np.clip(res.x, bounds[:, 0], bounds[:, 1])[None])
    every = np.vstack(polished)
    return every[int(np.argmax(_loglik(_psi(z, every), k, n)))]


def _fit_batch(
    z: np.ndarray, k: np.ndarray, n: np.ndarray, theta0: np.ndarray, lapse_max: float
) -> np.ndarray:
    """Maximum-likelihood parameters of B data sets at once (k (B, L), n (L,) or (B, L),
    theta0 (B, 3)): projected Fisher scoring with a backtracking line search, bounded like
    ``_fit_one``. For the bootstrap, whose data sets start near the generating
    parameters; each data set stops when its log-likelihood stops rising."""
    bounds = _bounds(lapse_max)
    lo, hi = bounds[:, 0], bounds[:, 1]
    theta = np.clip(theta0.astype(float), lo, hi)
    n = np.broadcast_to(n, k.shape)
    ll = _loglik(_psi(z, theta), k, n)
    alphas = 0.5 ** np.arange(6)
    diag = np.arange(3)
    todo = np.arange(len(theta))
    for _ in range(40):
        if len(todo) == 0:
            break
        th, kk, nn = theta[todo], k[todo], n[todo]
        m, s, lapse = th[:, 0:1], th[:, 1:2], th[:, 2:3]
        u = (z - m) / s
        phi = np.exp(-0.5 * u * u) / _SQRT_2PI
        p = np.clip(lapse / 2 + (1 - lapse) * special.ndtr(u), _P_EPS, 1 - _P_EPS)
        dp = np.stack(
            [-(1 - lapse) * phi / s, -(1 - lapse) * phi * u / s, 0.5 - special.ndtr(u)], axis=-1
        )  # (b, L, 3)
        v = p * (1 - p)
        g = np.einsum("bl,blj->bj", (kk - nn * p) / v, dp)
        info = np.einsum("bl,bli,blj->bij", nn / v, dp, dp)
        # A parameter at a bound whose gradient points outward stays there.
        active = ((th <= lo + 1e-12) & (g < 0)) | ((th >= hi - 1e-12) & (g > 0))
        g = np.where(active, 0.0, g)
        keep = ~active
        info = info * keep[:, :, None] * keep[:, None, :]
        info[:, diag, diag] += np.where(active, 1.0, 0.0)
        scale = np.maximum(np.trace(info, axis1=1, axis2=2), 1e-300)
        info[:, diag, diag] += 1e-10 * scale[:, None]
        newton = np.linalg.solve(info, g[..., None])[..., 0]
        # Clipping a Newton step to the bounds can turn it away from the ascent; the
        # diagonally scaled gradient step cannot. Both are tried, at several lengths.
        grad = g / np.maximum(info[:, diag, diag], 1e-300)
        steps = np.concatenate(
            [alphas[None, :, None] * newton[:, None, :], alphas[None, :, None] * grad[:, None, :]],
            axis=1,
        )
        cand = np.clip(th[:, None, :] + steps, lo, hi)
        cand_ll = _loglik(_psi(z, cand), kk[:, None, :], nn[:, None, :])  # (b, 2A)
        rows = np.arange(len(th))
        best = np.argmax(cand_ll, axis=1)
        gain = cand_ll[rows, best] - ll[todo]
        better = gain > 0
        theta[todo] = np.where(better[:, None], cand[rows, best], th)
        ll[todo] = np.where(better, cand_ll[rows, best], ll[todo])
        # Stop where the log-likelihood no longer rises: on a flat ridge (a bound, a
        # separated replicate) the parameters may still creep, to no purpose.
        todo = todo[gain > 1e-9]
    return theta


def _refit(
    z: np.ndarray, kb: np.ndarray, n: np.ndarray, theta: np.ndarray, lapse_max: float
) -> np.ndarray:
    """Bootstrap refits of the data sets kb (B, L) simulated from theta: (B, 3). Four
    starts each, the best kept: theta, theta with another lapse (the lapse's likelihood
    may have two hills) and the two near-step curves of ``_steep_starts``."""
    b = len(kb)
    other = theta.copy()
    other[2] = lapse_max / 2 if theta[2] < lapse_max / 4 else 0.0
    n = np.broadcast_to(n, kb.shape)
    steep = _steep_starts(z, kb, n, lapse_max)  # (2, B, 3)
    starts = np.concatenate([np.tile(theta, (b, 1)), np.tile(other, (b, 1)), *steep])
    k4, n4 = np.concatenate([kb] * 4), np.concatenate([n] * 4)
    fits = _fit_batch(z, k4, n4, starts, lapse_max).reshape(4, b, 3)
    ll = _loglik(_psi(z, fits.reshape(-1, 3)), k4, n4).reshape(4, b)
    return fits[np.argmax(ll, axis=0), np.arange(b)]


def _steep_starts(z: np.ndarray, k: np.ndarray, n: np.ndarray, lapse_max: float) -> np.ndarray:
    """Near-step curves at each data set's largest jump between neighbouring levels,
    without and with the most lapse: (2, B, 3) for k (B, L). A step elsewhere has no
    gradient in mu (the curve is flat at every level), so these start where it is."""
    k = np.atleast_2d(k)
    n = np.broadcast_to(n, k.shape)
    frac = np.divide(k, n, out=np.zeros(k.shape), where=n > 0)
    jump = np.argmax(np.diff(frac, axis=1), axis=1)
    mu = (z[jump] + z[jump + 1]) / 2
    sigma = np.full_like(mu, float(np.min(np.diff(z))) / 4)
    return np.stack(
        [np.stack([mu, sigma, np.full_like(mu, lapse)], axis=1) for lapse in (0.0, lapse_max)]
    )


def _acceleration(
    z: np.ndarray, k: np.ndarray, n: np.ndarray, theta: np.ndarray, lapse_max: float
) -> np.ndarray:
    """BCa's acceleration of each parameter (3,), from the jackknife: the fit without
    one trial. Trials at one level with one answer are alike, so there are at most 2L
    distinct leave-one-out fits, each weighted by how many trials it stands for."""
    rows_k, rows_n, weights = [], [], []
    for lvl in range(len(z)):
        for yes, count in ((1.0, k[lvl]), (0.0, n[lvl] - k[lvl])):
            if count <= 0:
                continue
            kk, nn = k.astype(float).copy(), n.astype(float).copy()
            kk[lvl] -= yes * min(1.0, count)
            nn[lvl] -= min(1.0, count)
            rows_k.append(kk)
            rows_n.append(nn)
            weights.append(count)
    fits = _refit(z, np.array(rows_k), np.array(rows_n), theta, lapse_max)
    w = np.array(weights)[:, None]
    u = np.sum(w * fits, axis=0) / w.sum() - fits
    den = 6 * np.sum(w * u**2, axis=0) ** 1.5
    return np.divide(np.sum(w * u**3, axis=0), den, out=np.zeros(3), where=den > 0)


def _bca_interval(
    boot: np.ndarray, estimate: float, ci: float, accel: float, bounds: np.ndarray
) -> tuple[float | None, float | None]:
    """The bias-corrected and accelerated percentile interval (Efron 1987) of a
    parameter's ``estimate`` from its bootstrap replicates: the percentiles move by the
    replicates' median bias (z0) and by how the estimate's spread changes with its value
    (accel). The ML sigma of 60 trials is biased low (about 8 %) and skewed; in
    simulation the plain percentile interval covers the true JND in 82 % of experiments,
    the bias-corrected one in 89 %, this one in 93 % (tests/test_psychophysics.py).

    An end whose percentile falls among replicates stuck at the parameter's search
    ``bounds`` (lo, hi) is None, unbounded: the data do not bound it there, and the
    bound is the search's, not a finding."""
    below = np.mean(boot < estimate) + 0.5 * np.mean(boot == estimate)
    z0 = float(stats.norm.ppf(np.clip(below, 1 / (2 * len(boot)), 1 - 1 / (2 * len(boot)))))
    zq = np.array([-1.0, 1.0]) * float(stats.norm.ppf(0.5 + ci / 2))
    shifted = z0 + (z0 + zq) / (1 - accel * (z0 + zq))
    lo, hi = stats.norm.cdf(shifted) * 100
    q = np.percentile(boot, [lo, hi])
    tol = 1e-3 * (bounds[1] - bounds[0])
    at_lo = 100 * np.mean(boot <= bounds[0] + tol)
    at_hi = 100 * np.mean(boot >= bounds[1] - tol)
    return (
        None if at_lo > 0 and at_lo >= lo else float(q[0]),
        None if at_hi > 0 and at_hi >= 100 - hi else float(q[1]),
    )


def _scaled(
    end: tuple[float | None, float | None], scale: float, shift: float = 0.0
) -> tuple[float | None, float | None]:
    """An interval in normalised units in the levels' unit (None ends stay None)."""
    return tuple(None if v is None else float(v * scale + shift) for v in end)  # type: ignore[return-value]


def _separation(x: np.ndarray, k: np.ndarray, n: np.ndarray) -> str | None:
    """Why the data is separated (all "no" up to a level, all "yes" above, at most one
    mixed level between), which drives the ML slope to infinity; None if it is not."""
    none, every = k <= 0, k >= n
    mixed = ~(none | every)
    if mixed.sum() > 1:
        return None
    i = int(np.argmax(~none)) if (~none).any() else len(x)  # first level with any "yes"
    j = i + 1 if i < len(x) and mixed[i] else i  # first level that must be all "yes"
    if none[:i].all() and every[j:].all():
        lo = x[i - 1] if i > 0 else x[0]
        hi = x[j] if j < len(x) else x[-1]
        return (
            f"the answers switch from all 'no' to all 'yes' between {lo:g} and {hi:g}: "
            "the curve is steeper than the levels resolve"
        )
    return None


def check_counts(
    levels: object, n_yes: object, n_total: object
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x, k, n = (np.asarray(a, dtype=float) for a in (levels, n_yes, n_total))
    if x.ndim != 1 or k.shape != x.shape or n.shape != x.shape:
        raise ValueError(
            "levels, n_yes and n_total must be 1-D and of the same length, got shapes "
            f"{x.shape}, {k.shape}, {n.shape}"
        )
    for name, a in (("levels", x), ("n_yes", k), ("n_total", n)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite, got {a.tolist()}")
    if np.any(n < 0) or np.any(k < 0) or np.any(k > n):
        raise ValueError(
            f"need 0 <= n_yes <= n_total at every level, got n_yes {k.tolist()}, "
            f"n_total {n.tolist()}"
        )
    used = n > 0
    x, k, n = x[used], k[used], n[used]
    # The same level given twice is one level.
    ux, inv = np.unique(x, return_inverse=True)
    return ux, np.bincount(inv, k, len(ux)), np.bincount(inv, n, len(ux))


def no_fit(reason: str, n_trials: float, n_levels: int, jnd_point: float) -> PsychometricFit:
    return PsychometricFit(
        estimable=False,
        reason=reason,
        pse=None,
        jnd=None,
        sigma=None,
        lapse=None,
        jnd_ci=None,
        pse_ci=None,
        n_trials=n_trials,
        n_levels=n_levels,
        log_likelihood=None,
        jnd_point=jnd_point,
    )


def data_reason(x: np.ndarray, k: np.ndarray, n: np.ndarray, min_trials: int) -> str | None:
    """Why the counts cannot determine a curve whatever the fitter, or None."""
    if len(x) < 3:
        return f"{len(x)} level(s) with trials: a curve needs at least 3"
    if n.sum() < min_trials:
        return f"{n.sum():g} trials: a curve needs at least {min_trials}"
    if np.all(k <= 0) or np.all(k >= n):
        word = "no" if np.all(k <= 0) else "yes"
        return f"every answer was '{word}': the levels are all on one side of the curve"
    return _separation(x, k, n)


def curve_reason(pse: float, sigma: float, x: np.ndarray) -> str | None:
    """Why a fitted curve (PSE, sigma in the levels' unit) is no estimate, or None: flat
    (sigma at its search bound), steeper than the levels resolve, the PSE beyond them."""
    span = x[-1] - x[0]
    if sigma >= _SIGMA_HI * span * 0.99:
        return (
            "flat: the answers hardly change over the levels (sigma reached its bound, "
            f"{_SIGMA_HI:g} times the level range)"
        )
    if sigma <= _SIGMA_LO * span * 1.01:
        return "the curve is steeper than the levels resolve"
    if abs(pse - (x[0] + x[-1]) / 2) > 0.5 * span:
        return f"the PSE ({pse:g}) lies beyond the tested levels ({x[0]:g} to {x[-1]:g})"
    min_gap = float(np.min(np.diff(x)))
    if sigma < min_gap / 4:
        return (
            f"the curve is steeper than the levels resolve (sigma {sigma:.3g} is below a "
            f"quarter of the smallest level spacing, {min_gap:g})"
        )
    return None


def fit_psychometric(
    levels: object,
    n_yes: object,
    n_total: object,
    *,
    lapse_max: float = 0.06,
    ci: float = 0.95,
    n_boot: int = 1000,
    seed: int | np.random.Generator | None = None,
    min_trials: int = 20,
    jnd_point: float = 0.75,
) -> PsychometricFit:
    """The global maximum-likelihood fit of psi(x) = l/2 + (1 - l) Phi((x - mu)/sigma).

    ``levels`` (L,) the comparison values (any unit; the results are in it),
    ``n_yes`` (L,) how often the comparison was judged more (expected counts may be
    fractional), ``n_total`` (L,) the trials per level. ``lapse_max`` bounds the lapse
    rate (0 fixes it at 0). ``jnd_ci``/``pse_ci``: a ``ci`` BCa interval from ``n_boot``
    parametric bootstrap refits (``n_boot=0``: none; the bootstrap rounds
    ``n_total`` to whole trials), drawn with ``seed``; an end that reaches the search's
    bound is None (unbounded). ``jnd_point``: the JND is x(jnd_point) - x(0.5).
    Malformed input (shapes, NaN,
    n_yes > n_total) raises ValueError; data that cannot determine a curve gives
    ``estimable=False`` with a reason.
    """
    if not 0.0 <= lapse_max < 0.5:
        raise ValueError(f"lapse_max must be in [0, 0.5), got {lapse_max}")
    if not 0.0 < ci < 1.0:
        raise ValueError(f"ci must be in (0, 1), got {ci}")
    if n_boot < 0:
        raise ValueError(f"n_boot must be >= 0, got {n_boot}")
    zj = jnd_z(jnd_point)
    x, k, n = check_counts(levels, n_yes, n_total)
    total, n_levels = float(n.sum()), len(x)
    why = data_reason(x, k, n, min_trials)
    if why:
        return no_fit(why, total, n_levels, jnd_point)
    centre, span = (x[0] + x[-1]) / 2, x[-1] - x[0]
    z = (x - centre) / span
    theta = _fit_one(z, k, n, lapse_max)
    m, s, lapse = (float(v) for v in theta)
    why = curve_reason(m * span + centre, s * span, x)
    if why:
        return no_fit(why, total, n_levels, jnd_point)
    jnd_ci = pse_ci = None
    if n_boot > 0:
        rng = np.random.default_rng(seed)
        nb = np.rint(n).astype(int)
        kb = rng.binomial(nb, _psi(z, theta), size=(n_boot, n_levels)).astype(float)
        boot = _refit(z, kb, nb.astype(float), theta, lapse_max)
        accel = _acceleration(z, k, n, theta, lapse_max)
        bounds = _bounds(lapse_max)
        sig_ci = _bca_interval(boot[:, 1], s, ci, float(accel[1]), bounds[1])
        jnd_ci = _scaled(sig_ci, span * zj)
        pse_ci = _scaled(_bca_interval(boot[:, 0], m, ci, float(accel[0]), bounds[0]), span, centre)
    return PsychometricFit(
        estimable=True,
        reason=None,
        pse=float(m * span + centre),
        jnd=float(zj * s * span),
        sigma=float(s * span),
        lapse=lapse,
        jnd_ci=jnd_ci,
        pse_ci=pse_ci,
        n_trials=total,
        n_levels=n_levels,
        log_likelihood=float(_loglik(_psi(z, theta), k, n)),
        jnd_point=jnd_point,
    )


@dataclass(frozen=True)
class PairedT:
    """A paired-samples t-test of a - b: t, degrees of freedom (n - 1), two-sided p,
    the mean and SD of the differences, the number of pairs."""

    t: float
    df: int
    p: float
    mean_diff: float
    sd_diff: float
    n: int


def paired_t(a: object, b: object) -> PairedT:
    """Paired t-test of the means of ``a`` and ``b`` (n,), two-sided.

    ValueError when it is undefined: shapes differ, a value is not finite, fewer
    than 2 pairs, or the differences have zero variance (t would be 0/0 or +-inf).
    """
    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if x.ndim != 1 or x.shape != y.shape:
        raise ValueError(f"paired_t needs two 1-D arrays of one length, got {x.shape}, {y.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError(f"paired_t needs finite values, got {x.tolist()} and {y.tolist()}")
    n = len(x)
    if n < 2:
        raise ValueError(f"paired_t needs at least 2 pairs, got {n}")
    d = x - y
    mean, sd = float(np.mean(d)), float(np.std(d, ddof=1))
    if not sd > 1e-12 * max(1.0, float(np.max(np.abs(d)))):
        raise ValueError(
            f"paired_t is undefined: every pair differs by the same amount ({mean:g}), "
            "so the differences have zero variance"
        )
    t = mean / (sd / np.sqrt(n))
    p = float(2 * stats.t.sf(abs(t), n - 1))
    return PairedT(t=float(t), df=n - 1, p=p, mean_diff=mean, sd_diff=sd, n=n)
