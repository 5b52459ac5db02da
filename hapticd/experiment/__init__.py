"""JND experiments (method of constant stimuli) on hapticd: the experiment file, the
trial plan, the trial store and the analysis. See docs/experiments.md."""

from hapticd.experiment.plan import PlannedTrial, make_plan
from hapticd.experiment.spec import (
    Experiment,
    ExperimentError,
    check_against_profile,
    check_experiment,
    load_experiment,
    parse_experiment,
)

__all__ = [
    "Experiment",
    "ExperimentError",
    "PlannedTrial",
    "check_against_profile",
    "check_experiment",
    "load_experiment",
    "make_plan",
    "parse_experiment",
]
