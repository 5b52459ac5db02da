"""How far a staircase design's JND lands from the point it names: simulated observers
of known sigma run the design's tracks (``adaptive.Track``, the runner's own rule) and
their thresholds are compared with the rule's point, x(target share) - x(0.5) = z sigma
(docs/experiments.md, "How near its point a staircase lands").

The observer judges a comparison c of the standard s "more" with probability
lapse / 2 + (1 - lapse) Phi((c / s - 1 - pse) / sigma): sigma and the PSE shift as
fractions of the standard. A simulated subject is one track per side; its JND is what
``analyze`` reports, the mean of the sides' threshold distances. ``experiment check``
warns about a design whose simulated JND is off by more than ``TOLERANCE``;
``scripts/staircase_bias.py`` writes the table of the bundled designs.

Pure: no I/O; seeded, so a design's numbers are the same on every run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from hapticd.experiment.adaptive import Track, is_correct
from hapticd.experiment.spec import Staircase

# The observers' sigmas, fractions of the standard: Weber fractions (at 75 %) from 3.4 %
# to 20 %, haptic stiffness and weight discrimination's range and beyond.
SIGMAS = (0.05, 0.10, 0.15, 0.20, 0.30)
# The farthest a design's point may lie, as a share of its max_distance, for a sigma to
# be one the design is for: beyond, its tracks' excursions above the point are clipped
# at max_distance and no rule reaches it.
REACH = 2 / 3
# The relative error of the mean JND beyond which ``experiment check`` warns.
TOLERANCE = 0.05
# Simulated subjects (pairs of tracks) per sigma at ``experiment check``.
CHECK_SUBJECTS = 500


@dataclass(frozen=True)
class Bias:
    """A design's simulated JNDs at one sigma and PSE shift (fractions of the standard):
    ``point`` the rule's, z(target share) sigma; ``mean``, ``median``, ``sd`` of the
    subjects' JNDs; ``bias`` = mean / point - 1 and ``spread`` = sd / point;
    ``share`` the share correct at the mean, Phi(mean / sigma) (the point's: the
    target share); ``missing`` subjects with no JND (a track without
    threshold_reversals reversals)."""

    sigma: float
    pse: float
    lapse: float
    target_share: float
    point: float
    subjects: int
    missing: int
    mean: float
    median: float
    sd: float

    @property
    def bias(self) -> float:
        return self.mean / self.point - 1

    @property
    def spread(self) -> float:
        return self.sd / self.point

    @property
    def stderr(self) -> float:
        """The standard error of ``bias``."""
        return self.sd / self.point / math.sqrt(max(self.subjects - self.missing, 1))

    @property
    def share(self) -> float:
        return float(stats.norm.cdf(self.mean / self.sigma))


def sigmas_for(st: Staircase, sigmas: tuple[float, ...] = SIGMAS) -> tuple[float, ...]:
    """The ``sigmas`` ``st`` is for: those whose point, z sigma, lies within ``REACH`` of
    its max_distance."""
    z = float(stats.norm.ppf(st.target_share))
    return tuple(s for s in sigmas if z * s <= REACH * st.max_distance)


def observed_track(
    st: Staircase,
    sign: int,
    sigma: float,
    pse: float,
    lapse: float,
    rng: np.random.Generator,
) -> Track:
    """One track of ``st`` answered by the simulated observer until it ends."""
    track = Track.new(0, "sim", 1.0, sign, st)
    draws = rng.random(st.max_trials)
    root2 = math.sqrt(2.0)
    while not track.done(st):
        x = (sign * track.distance - pse) / sigma
        p_more = lapse / 2 + (1 - lapse) * 0.5 * (1 + math.erf(x / root2))
        track.answer(is_correct(track, bool(draws[track.n] < p_more)), st)
    return track


def simulate(
    st: Staircase,
    sigma: float,
    *,
    pse: float = 0.0,
    lapse: float = 0.0,
    subjects: int = 300,
    seed: int = 0,
) -> Bias:
    """``subjects`` simulated subjects of ``st`` (each its tracks, one per side, from a
    generator seeded by ``seed``, the subject and the side): their JNDs against the
    rule's point."""
    jnds: list[float] = []
    for k in range(subjects):
        thresholds = []
        for sign in st.sign_list():
            rng = np.random.default_rng([int(seed), k, 1 if sign > 0 else 0])
            thresholds.append(observed_track(st, sign, sigma, pse, lapse, rng).threshold(st))
        if all(t is not None for t in thresholds):
            jnds.append(float(np.mean(thresholds)))
    got = np.array(jnds) if jnds else np.array([np.nan])
    return Bias(
        sigma=sigma,
        pse=pse,
        lapse=lapse,
        target_share=st.target_share,
        point=float(stats.norm.ppf(st.target_share)) * sigma,
        subjects=subjects,
        missing=subjects - len(jnds),
        mean=float(np.mean(got)),
        median=float(np.median(got)),
        sd=float(np.std(got)),
    )


def check(
    st: Staircase, *, subjects: int = CHECK_SUBJECTS, seed: int = 0
) -> tuple[list[Bias], str | None]:
    """``st`` simulated at each sigma it is for, and a warning (None: none) when its JND
    is more than ``TOLERANCE`` off its point, or a tenth of its subjects get none."""
    rows = [simulate(st, s, subjects=subjects, seed=seed) for s in sigmas_for(st)]
    if not rows:
        return rows, (
            f"no sigma of {', '.join(f'{s:g}' for s in SIGMAS)} has its point within "
            f"{REACH:.0%} of max_distance {st.max_distance:g}: the design's range is too "
            "narrow to be simulated"
        )
    bad = [b for b in rows if b.missing < b.subjects and not abs(b.bias) <= TOLERANCE]
    short = [b for b in rows if b.missing > subjects / 10]
    if not bad and not short:
        return rows, None
    parts = []
    if bad:
        parts.append(
            f"the simulated JND is off its {st.target_share:.1%} point by "
            + ", ".join(f"{b.bias:+.0%} at sigma {b.sigma:g}" for b in bad)
            + f" (more than {TOLERANCE:.0%})"
        )
    if short:
        parts.append(
            ", ".join(f"{b.missing / subjects:.0%} at sigma {b.sigma:g}" for b in short)
            + f" of the simulated subjects get no JND (a track ends with fewer than "
            f"{st.threshold_reversals} reversals)"
        )
    return rows, "; ".join(parts) + ": " + _remedies(st) + " bring it nearer (docs/experiments.md)"


def _remedies(st: Staircase) -> str:
    """What of ``st`` to change to bring its JND nearer its point."""
    out = [
        "more reversals after the step's floor (stop_reversals, threshold_reversals, max_trials)"
    ]
    out.append("a start nearer the threshold")
    if st.step_rule == "halve":
        out.append("a smaller min_step")
    else:
        out.append("a smaller step, or step_rule halve")
    if not st.initial_rule and st.rule != "weighted":
        out.append("initial_rule")
    if st.step_type == "lin" and st.min_distance >= 0:
        out.append("min_distance below 0")
    return ", ".join(out[:-1]) + " or " + out[-1]


def summary(rows: list[Bias]) -> str:
    """One line: the simulated bias at each sigma."""
    if not rows:
        return "no sigma within the design's range"
    return ", ".join(
        f"{'no JND' if b.missing == b.subjects else f'{b.bias:+.1%}'} at sigma {b.sigma:g}"
        for b in rows
    )
