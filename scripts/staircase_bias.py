#!/usr/bin/env python3
"""How near its point each staircase design's JND lands (a simulation study, not a
timing benchmark): hapticd.experiment.bias on every design given (the bundled
staircase files by default).

Per design, per simulated observer's sigma (those the design is for: its point
z sigma within 2/3 of max_distance), ``--subjects`` simulated subjects, each one track
per side answered by P(judged more) = Phi((c / s - 1 - pse) / sigma) with the runner's
own rule (adaptive.Track), the JND what ``analyze`` reports (the sides' mean threshold
distance). Printed per row: the point z(target) sigma, the mean JND's bias against it
(with its standard error), the median's, the spread (SD / point), the share correct at
the mean JND (the point's: the target share), the subjects with no JND.

Alternatives in the same run, on the same simulated answers: each design with its
tracks kept on their side of the standard (``min_distance: 0``) and, where it uses
it, without ``initial_rule``. Then the PSE shift: each design at its middle sigma with
the observer's PSE moved by ``--pse`` (fractions of the standard), crossing the
standard and not.

Usage: python scripts/staircase_bias.py [--subjects 4000] [--seed 0] [--workers N]
[--pse 0,0.05,0.1,0.15] [--plot PATH] [EXPERIMENT.yaml ...] (the plot goes to the temp
directory unless --plot says where).
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import os
import tempfile
import time
from pathlib import Path

from hapticd.experiment import bias
from hapticd.experiment.spec import load_experiment

ROOT = Path(__file__).resolve().parent.parent
BUNDLED = [
    ROOT / "configs" / "experiments" / "stiffness-staircase.yaml",
    ROOT / "configs" / "experiments" / "weight-staircase.yaml",
]


def variants(st):
    """The design and its alternatives: (name, staircase)."""
    out = [("as set", st)]
    if st.min_distance < 0:
        out.append(("min_distance 0", st.model_copy(update={"min_distance": 0.0})))
    if st.initial_rule:
        out.append(("initial_rule false", st.model_copy(update={"initial_rule": False})))
    return out


def cell(args):
    design, variant, st, sigma, pse, subjects, seed = args
    return design, variant, bias.simulate(st, sigma, pse=pse, subjects=subjects, seed=seed)


def row(design: str, variant: str, b: bias.Bias) -> str:
    return (
        f"| {design} | {variant} | {b.sigma:.2f} | {b.pse:+.2f} | {b.point:.4f} "
        f"({b.target_share:.1%}) | {b.bias:+.1%} ± {b.stderr:.1%} | "
        f"{b.median / b.point - 1:+.1%} | {b.spread:.0%} | {b.share:.1%} | "
        f"{b.missing / b.subjects:.1%} |"
    )


HEADER = (
    "| design | variant | sigma | PSE shift | point z sigma (share) | mean JND bias ± SE | "
    "median bias | spread (SD / point) | share correct at the mean | no JND |\n"
    "|---|---|---|---|---|---|---|---|---|---|"
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("experiments", nargs="*", type=Path, default=BUNDLED)
    ap.add_argument("--subjects", type=int, default=4000, help="simulated subjects a row")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--pse", default="0,0.05,0.1,0.15", help="PSE shifts, comma-separated")
    ap.add_argument("--plot", type=Path, default=None)
    args = ap.parse_args()
    shifts = [float(x) for x in args.pse.split(",") if x.strip()]

    designs = []
    for path in args.experiments:
        exp = load_experiment(path)
        if exp.staircase is None:
            raise SystemExit(f"{path}: not a staircase design")
        designs.append((exp.name, exp.staircase))
    jobs, pse_jobs = [], []
    for name, st in designs:
        sigmas = bias.sigmas_for(st)
        for variant, v in variants(st):
            jobs += [(name, variant, v, s, 0.0, args.subjects, args.seed) for s in sigmas]
        mid = sigmas[len(sigmas) // 2]
        for variant, v in variants(st)[:2]:
            pse_jobs += [(name, variant, v, mid, d, args.subjects, args.seed) for d in shifts]
    t0 = time.perf_counter()
    with cf.ProcessPoolExecutor(max_workers=args.workers) as pool:
        results = list(pool.map(cell, jobs + pse_jobs, chunksize=1))
    took = time.perf_counter() - t0
    main_rows, pse_rows = results[: len(jobs)], results[len(jobs) :]

    print(f"Simulated JNDs against their point: {args.subjects} subjects a row, seed "
          f"{args.seed}, {took:.0f} s on {args.workers} workers\n")  # fmt: skip
    print(HEADER)
    for r in main_rows:
        print(row(*r))
    print("\nThe PSE shift (each design at its middle sigma):\n")
    print(HEADER)
    for r in pse_rows:
        print(row(*r))

    out = args.plot or Path(tempfile.gettempdir()) / "staircase_bias.png"
    plot(main_rows, pse_rows, out)
    print(f"\nplot: {out}")


def plot(main_rows, pse_rows, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for ax, rows, x_of, xlabel in (
        (a, main_rows, lambda r: r.sigma, "observer's sigma (fraction of the standard)"),
        (b, pse_rows, lambda r: r.pse, "observer's PSE shift (fraction of the standard)"),
    ):
        lines = sorted({(d, v) for d, v, _ in rows})
        for d, v in lines:
            pts = [r for dd, vv, r in rows if (dd, vv) == (d, v)]
            ax.errorbar(
                [x_of(r) for r in pts],
                [100 * r.bias for r in pts],
                yerr=[200 * r.stderr for r in pts],
                marker="o",
                capsize=3,
                label=f"{d}, {v}",
            )
        ax.axhspan(-100 * bias.TOLERANCE, 100 * bias.TOLERANCE, color="0.9")
        ax.axhline(0, color="0.5", lw=0.8)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("mean JND / its point - 1 (%), +- 2 SE")
        ax.legend(fontsize=7)
    fig.suptitle("staircases: simulated JND against the point the rule names")
    fig.tight_layout()
    fig.savefig(out, dpi=110)


if __name__ == "__main__":
    main()
