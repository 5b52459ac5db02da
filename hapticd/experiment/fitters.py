"""The psychometric fitters ``hapticd experiment analyze --fitter`` chooses from: ``ml``,
hapticd's maximum-likelihood fit (hapticd.psychophysics, pure), and ``psignifit``,
psignifit 4's Bayesian fit of the same curve (an optional dependency that brings
matplotlib: kept out of the pure module)."""

from __future__ import annotations

import numpy as np
from scipy import stats

from hapticd import psychophysics as pp
from hapticd.psychophysics import fit_psychometric


def fit_psignifit(
    levels: object,
    n_yes: object,
    n_total: object,
    *,
    lapse_max: float = 0.06,
    ci: float = 0.95,
    min_trials: int = 20,
    jnd_point: float = 0.75,
    **_: object,
) -> pp.PsychometricFit:
    """The same curve fitted by psignifit 4 (Schuett et al. 2016; ``pip install
    'hapticd[psignifit]'``), for a second opinion: a cumulative normal with equal lower
    and upper asymptotes (l/2 each, l <= ``lapse_max``), no overdispersion (eta 0), its
    default priors, the MAP estimate; ``jnd_ci``/``pse_ci`` its ``ci`` credible
    intervals as psignifit gives them. Data that ``fit_psychometric`` calls not estimable
    (too few levels or trials, one answer, separated, flat, too steep, PSE beyond the
    levels) is not estimable here either, with the same reason. ImportError without
    psignifit."""
    import psignifit  # an optional dependency: imported when chosen

    zj = pp.jnd_z(jnd_point)
    x, k, n = pp.check_counts(levels, n_yes, n_total)
    total, n_levels = float(n.sum()), len(x)
    why = pp.data_reason(x, k, n, min_trials)
    if why:
        return pp.no_fit(why, total, n_levels, jnd_point)
    conf = (0.95, 0.9, 0.68) if ci in (0.95, 0.9, 0.68) else (ci,)
    r = psignifit.psignifit(
        np.c_[x, k, n],
        sigmoid="norm",
        # No lapse allowed: both asymptotes fixed at 0 (psignifit's equal-asymptote
        # type cannot fix its shared one).
        experiment_type="equal asymptote" if lapse_max > 0 else "yes/no",
        fixed_parameters=(
            {"eta": 0.0} if lapse_max > 0 else {"eta": 0.0, "lambda": 0.0, "gamma": 0.0}
        ),
        bounds={"lambda": (0.0, lapse_max / 2)} if lapse_max > 0 else None,
        confP=conf,
        verbose=False,
    )
    est = r.parameter_estimate_MAP
    # psignifit's width is x(0.95) - x(0.05) of the sigmoid without lapse.
    per_sigma = float(stats.norm.ppf(0.95) - stats.norm.ppf(0.05))
    pse, sigma = float(est["threshold"]), float(est["width"]) / per_sigma
    why = pp.curve_reason(pse, sigma, x)
    if why:
        return pp.no_fit(why, total, n_levels, jnd_point)
    width_ci = r.confidence_intervals["width"][str(ci)]
    pse_ci = r.confidence_intervals["threshold"][str(ci)]
    return pp.PsychometricFit(
        estimable=True,
        reason=None,
        pse=pse,
        jnd=zj * sigma,
        sigma=sigma,
        lapse=2 * float(est["lambda"]),
        jnd_ci=(zj * width_ci[0] / per_sigma, zj * width_ci[1] / per_sigma),
        pse_ci=(float(pse_ci[0]), float(pse_ci[1])),
        n_trials=total,
        n_levels=n_levels,
        log_likelihood=None,
        jnd_point=jnd_point,
    )


# ``--fitter`` names: the maximum-likelihood fit (hapticd.psychophysics), psignifit's.
FITTERS = {"ml": fit_psychometric, "psignifit": fit_psignifit}
