"""A scripted-answer trial writer (the live runner's stand-in for the store tests):
python trial_writer.py EXP DB SUBJECT [MU_RATIO SIGMA_RATIO [LIMIT]].

Answers come from a simulated observer, psi(ratio) = Phi((ratio - MU_RATIO) /
SIGMA_RATIO), drawn with a generator seeded by the subject and the trial. After each
committed trial it prints "committed INDEX" and flushes, so a test knows what must
survive a kill. It stops after LIMIT trials (default: the whole plan)."""

from __future__ import annotations

import sys
import zlib

import numpy as np
from scipy import stats

from hapticd.experiment import load_experiment, make_plan
from hapticd.experiment.store import TrialStore


def main() -> None:
    exp_path, db, subject = sys.argv[1:4]
    mu = float(sys.argv[4]) if len(sys.argv) > 4 else 1.0
    sigma = float(sys.argv[5]) if len(sys.argv) > 5 else 0.15
    limit = int(sys.argv[6]) if len(sys.argv) > 6 else None
    exp = load_experiment(exp_path)
    seed = exp.subject_seed(subject)
    with TrialStore.for_experiment(db, exp) as store:
        store.ensure_plan(subject, make_plan(exp, seed), seed)
        for done, trial in enumerate(store.remaining(subject)):
            if limit is not None and done >= limit:
                break
            rng = np.random.default_rng([zlib.crc32(subject.encode()), trial.index])
            more = rng.random() < stats.norm.cdf((trial.ratio - mu) / sigma)
            # "Was the second more?": yes when the comparison, judged more, was second.
            answer = bool(more) != trial.comparison_first
            store.record(
                subject,
                trial,
                answer_second_more=answer,
                response_time_s=0.8,
                profile_hash="p" * 64,
                seed=seed,
            )
            print(f"committed {trial.index}", flush=True)


if __name__ == "__main__":
    main()
