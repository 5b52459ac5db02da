"""Barbagli & Salisbury's sensor/actuator asymmetry analysis on the live rendering pipeline.

The math is in ``hapticd.analysis.pipeline`` (pure: numpy in, numpy out, the
loop's own stages); this package adds ``Pipeline.from_profile``, which reads a
profile (and the files it names) through ``hapticd.daemon.build``. See docs/analysis.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from hapticd.analysis import pipeline as _pipeline
from hapticd.analysis.pipeline import (
    CLOSURE_TOL_M,
    COINCIDENT_M,
    COORD_STEPS,
    FD_STEP_M,
    Forces,
    Linearization,
    Sample,
    State,
    Work,
    asymmetry,
    loop_work_rate,
    null_directions,
)
from hapticd.daemon.build import build_renderer
from hapticd.profile import Profile, load_profile


class Pipeline(_pipeline.Pipeline):
    """``hapticd.analysis.pipeline.Pipeline``, also made from a profile."""

    @classmethod
    def from_profile(
        cls, profile: Profile | str | Path, *, allocators: Sequence[str] | None = None
    ) -> Pipeline:
        """The pipeline of a profile (a parsed ``Profile`` or the path of one; ProfileError
        for a bad one): its scene, fingertips, actuation, robustness and adaptive ratios."""
        prof = profile if isinstance(profile, Profile) else load_profile(profile)
        return cls.from_renderer(
            build_renderer(prof), allocators=allocators, finger_names=prof.finger_names
        )


__all__ = [
    "CLOSURE_TOL_M",
    "COINCIDENT_M",
    "COORD_STEPS",
    "FD_STEP_M",
    "Forces",
    "Linearization",
    "Pipeline",
    "Sample",
    "State",
    "Work",
    "asymmetry",
    "loop_work_rate",
    "null_directions",
]
