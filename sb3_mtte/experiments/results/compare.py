"""Two algorithms on one benchmark, compared as fixed before the runs (docs/results.md): the difference of their
mean final success with a bootstrap interval and Welch's t, on the replication seeds and on all seeds, rliable's
aggregates beside it, and the runs whose soft Bellman error ran away.

Usage::

    sb3-mtte compare SOURCE [SOURCE ...] --benchmark MT10-100k [--a Ours] [--b SAC-MT]
                     [--replication-seeds 3 4 5 6 7] [--runaway-loss 100] [--fell 0.2] [--out FILE]
                     [--include-unfinished]

A benchmark with a registered comparison (:data:`PREREGISTERED`) takes its algorithms, seeds and criterion from it;
the flags override them. Only runs with a final evaluation count; a run that did not finish is left out, named in
one line, unless ``--include-unfinished`` is given (the tables then mark it). Welch's t is undefined when every run
of both algorithms has the same success, and the tables say so.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy import stats

from sb3_mtte.experiments.cli import CommandParser, command_prog, output_file_error
from sb3_mtte.experiments.results.bellman_table import window_names
from sb3_mtte.experiments.results.figures import safe_name
from sb3_mtte.experiments.results.records import load_runs
from sb3_mtte.experiments.results.runaways import (
    Runaway,
    fisher_line,
    ran_away,
    runaway,
    runaway_rows,
    runaways,
    window_edges,
)
from sb3_mtte.experiments.results.runs import Run, group_runs
from sb3_mtte.experiments.results.statistics import (
    DEFAULT_REPS,
    DEFAULT_SEED,
    Estimate,
    aggregate_estimates,
    count_cell,
    final_task_scores,
    has_final_evaluation,
    improvement_probabilities,
    leave_out_unevaluated,
    leave_out_unfinished,
    unfinished,
)

DIFFERENCE_REPS = 10_000


@dataclass(frozen=True)
class Comparison:
    """What a comparison was fixed to answer: ``a`` against ``b``, the seeds of the replication, and when a run's
    soft Bellman error ran away (some task's window-mean critic loss above ``runaway_loss``) and a runaway task's
    success fell with it (its final success ``fell`` or more below its best in-training success up to the end of
    its first runaway window)."""

    a: str = "Ours"
    b: str = "SAC-MT"
    replication_seeds: tuple[int, ...] = ()
    runaway_loss: float = 100.0
    fell: float = 0.2


PREREGISTERED: dict[str, Comparison] = {"MT10-100k": Comparison(replication_seeds=(3, 4, 5, 6, 7))}
"""Benchmark -> the comparison committed before its runs (docs/results.md)."""


@dataclass(frozen=True)
class MeanDifference:
    """``mean(a) - mean(b)`` over runs with its percentile-bootstrap interval, and Welch's t test (``t``, ``df`` and
    ``p`` NaN when every run of each algorithm has the same success: the test is undefined without variance)."""

    value: float
    low: float
    high: float
    t: float
    df: float
    p: float

    @property
    def welch_defined(self) -> bool:
        return math.isfinite(self.t)


WELCH_UNDEFINED = "undefined: no variance"
"""Welch's t when every run of both algorithms has the same success (its denominator, their spread, is 0)."""


def mean_difference(a: np.ndarray, b: np.ndarray, reps: int = DIFFERENCE_REPS, seed: int = 0) -> MeanDifference:
    """The difference of the means of ``a`` and ``b`` (one value per run); the 95% interval resamples runs within
    each algorithm (``reps`` resamples from ``numpy.random.default_rng(seed)``: ``a``'s indices, then ``b``'s)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    rng = np.random.default_rng(seed)
    draws_a = a[rng.integers(0, len(a), size=(reps, len(a)))].mean(axis=1)
    draws_b = b[rng.integers(0, len(b), size=(reps, len(b)))].mean(axis=1)
    low, high = np.percentile(draws_a - draws_b, [2.5, 97.5])
    value = float(a.mean() - b.mean())
    if np.ptp(a) == 0 and np.ptp(b) == 0:  # Welch's t divides by the runs' spread: undefined, not computed
        return MeanDifference(value, float(low), float(high), math.nan, math.nan, math.nan)
    var_a, var_b = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    df = (var_a + var_b) ** 2 / (var_a**2 / (len(a) - 1) + var_b**2 / (len(b) - 1))
    t = value / math.sqrt(var_a + var_b)
    p = 2 * stats.t.sf(abs(t), df)
    return MeanDifference(value, float(low), float(high), float(t), float(df), float(p))


def fixed_reading(diff: MeanDifference, cmp: Comparison) -> str:
    """The answer under the reading fixed before the runs (docs/results.md): yes (``a`` is ahead) when the interval
    for the difference lies above 0, ``b`` is ahead when it lies below 0, and not shown when it holds 0."""
    if diff.low > 0:
        return f"yes, {cmp.a} is ahead"
    if diff.high < 0:
        return f"{cmp.b} is ahead"
    return "not shown (the interval holds 0)"


def _reading_sentence(a: list[Run], b: list[Run], diff: MeanDifference | None, cmp: Comparison) -> str:
    """The replication's answer under the fixed reading, said to be provisional while a seed has no finished run."""
    seeds = cmp.replication_seeds
    found = "too few runs for an interval" if diff is None else fixed_reading(diff, cmp)
    done = [len(set(seeds) & {run.seed for run in runs if not unfinished(run)}) for runs in (a, b)]
    if min(done) < len(seeds):
        found += f"; {cmp.a} has finished {done[0]} of its {len(seeds)} runs and {cmp.b} {done[1]}, so this is not "
        found += "the answer yet"
    return f"Reading fixed before the runs, on {_replication_name(cmp)}: {found}."


def _finished(runs: Sequence[Run], seeds: Sequence[int] | None) -> list[Run]:
    chosen = [run for run in runs if final_task_scores(run) is not None and (seeds is None or run.seed in seeds)]
    return sorted(chosen, key=lambda run: -1 if run.seed is None else run.seed)


def _means(runs: Sequence[Run]) -> np.ndarray:
    return np.array([float(np.mean(final_task_scores(run))) for run in runs])


def _pct(value: float) -> str:
    return f"{100 * value:.1f}"


def _difference(a: list[Run], b: list[Run]) -> MeanDifference | None:
    return None if len(a) < 2 or len(b) < 2 else mean_difference(_means(a), _means(b))


def _difference_row(name: str, a: list[Run], b: list[Run], diff: MeanDifference | None) -> str:
    cells = [name, count_cell(a), count_cell(b)]
    if diff is None:
        return "| " + " | ".join(cells + ["-"] * 4) + " |"
    means_a, means_b = _means(a), _means(b)
    cells += [
        f"{_pct(means_a.mean())} / {_pct(means_b.mean())}",
        f"{_pct(diff.value)} [{_pct(diff.low)}, {_pct(diff.high)}]",
        f"{diff.t:.2f} ({diff.df:.1f})" if diff.welch_defined else WELCH_UNDEFINED,
        f"{diff.p:.3f}" if diff.welch_defined else "-",
    ]
    return "| " + " | ".join(cells) + " |"


def _estimate(estimate: Estimate, scale: float = 100.0, digits: int = 1) -> str:
    value, low, high = (f"{scale * v:.{digits}f}" for v in (estimate.value, estimate.low, estimate.high))
    return f"{value} [{low}, {high}]"


def _rliable_rows(name: str, a: list[Run], b: list[Run], cmp: Comparison, reps: int) -> list[str]:
    if not a or not b:
        return []
    scores = {label: np.stack([final_task_scores(r) for r in runs]) for label, runs in ((cmp.a, a), (cmp.b, b))}
    aggregates = aggregate_estimates(scores, reps, DEFAULT_SEED)
    improvement = improvement_probabilities(scores[cmp.a], {cmp.b: scores[cmp.b]}, reps, DEFAULT_SEED)
    rows = []
    for label, runs in ((cmp.a, a), (cmp.b, b)):
        probability = _estimate(improvement[cmp.b], 1.0, 2) if label == cmp.b else "-"
        estimates = aggregates[label]
        cells = [name, label, count_cell(runs), _estimate(estimates["mean"]), _estimate(estimates["iqm"])]
        rows.append("| " + " | ".join([*cells, probability]) + " |")
    return rows


def _replication_name(cmp: Comparison) -> str:
    return "seeds " + " ".join(map(str, cmp.replication_seeds))


def _subsets(bench: str, runs: Sequence[Run], cmp: Comparison) -> dict[str, list[list[Run]]]:
    """Subset name (the replication's seeds, then "all seeds") -> [a's finished runs, b's], sorted by seed."""
    groups = group_runs(runs).get(bench, {})
    everything = [_finished(groups.get(label, []), None) for label in (cmp.a, cmp.b)]
    subsets = {}
    if cmp.replication_seeds:
        subsets[_replication_name(cmp)] = [
            [run for run in pair if run.seed in cmp.replication_seeds] for pair in everything
        ]
    subsets["all seeds"] = everything
    return subsets


def comparison_summary(bench: str, runs: Sequence[Run], cmp: Comparison) -> str:
    """One paragraph for under Table 1: on each subset of :func:`comparison_report`, the difference of the means
    with its interval and Welch's t, and how many runs of each algorithm ran away."""
    subsets = _subsets(bench, runs, cmp)
    everything = subsets["all seeds"][0] + subsets["all seeds"][1]
    edges = window_edges(everything)
    by_run = None if edges is None else runaways(everything, edges, cmp.runaway_loss)
    sentences = []
    for name, (a, b) in subsets.items():
        found = f"{name.capitalize()} (n = {len(a)} and {len(b)}): "
        diff = _difference(a, b)
        if diff is None:
            found += "too few runs for the difference"
        else:
            found += f"{100 * diff.value:+.1f} points [{_pct(diff.low)}, {_pct(diff.high)}]"
            found += f", Welch t {diff.t:.2f}, p {diff.p:.3f}" if diff.welch_defined else f", Welch t {WELCH_UNDEFINED}"
        if by_run is not None:
            counts = [sum(ran_away(by_run[id(run)]) for run in group) for group in (a, b)]
            found += f"; ran away: {counts[0]} of {len(a)} and {counts[1]} of {len(b)}"
        sentences.append(found + ".")
        if cmp.replication_seeds and name == _replication_name(cmp):
            sentences.append(_reading_sentence(a, b, diff, cmp))
    stem = safe_name(bench)
    return (
        f"{cmp.a} minus {cmp.b} as fixed before the runs (docs/results.md): the difference of the mean final success "
        f"over runs with its 95% bootstrap interval ({DIFFERENCE_REPS:,} resamples) and Welch's t; the runs whose "
        f"soft Bellman error ran away (a task's window-mean critic loss above {cmp.runaway_loss:g}), {cmp.a} then "
        f"{cmp.b}. " + " ".join(sentences) + f" In full: compare_{stem}.md, written beside "
        f"table1_{stem}.md (`sb3-mtte plot`, or `sb3-mtte compare` alone)."
    )


def comparison_report(bench: str, runs: Sequence[Run], cmp: Comparison, reps: int = DEFAULT_REPS) -> str:
    """The markdown report of ``cmp`` on the runs of benchmark ``bench`` that have a final evaluation (rliable's
    intervals from ``reps`` resamples)."""
    chosen = _subsets(bench, runs, cmp)
    diffs = {name: _difference(*pair) for name, pair in chosen.items()}
    replication = _replication_name(cmp)
    reading = [_reading_sentence(*chosen[replication], diffs[replication], cmp)] if replication in chosen else []
    interim = sorted({f"{run.label} seed {run.seed}" for pair in chosen.values() for runs in pair for run in runs
                      if not has_final_evaluation(run)})  # fmt: skip
    interim_line = f"Counted at their last periodic evaluation, having no final one: {', '.join(interim)}."
    lines = [
        f"{bench}: {cmp.a} against {cmp.b}, the final success (mean over tasks of each run's final evaluation). "
        f"Difference: the mean over runs of {cmp.a} minus that of {cmp.b}, 95% percentile bootstrap over runs "
        f"within each algorithm ({DIFFERENCE_REPS:,} resamples, seed 0); Welch's t with its degrees of freedom and "
        "two-sided p.",
        *(["", interim_line] if interim else []),
        "",
        f"| Seeds | n {cmp.a} | n {cmp.b} | Means (%) | Difference (points) | Welch t (df) | p |",
        "|:--|--:|--:|--:|--:|--:|--:|",
        *(_difference_row(name, *pair, diffs[name]) for name, pair in chosen.items()),
        *(["", *reading] if reading else []),
        "",
        f"rliable over runs x tasks (95% stratified bootstrap, {reps} resamples, seed {DEFAULT_SEED}); "
        f"P({cmp.a} > {cmp.b}) averages over tasks the chance that a run of {cmp.a} beats one of {cmp.b}, ties "
        "counted one half, so a task at 0 in every run of both contributes exactly 0.5.",
        "",
        f"| Seeds | Algorithm | n | Mean (%) | IQM (%) | P({cmp.a} > {cmp.b}) |",
        "|:--|:--|--:|--:|--:|--:|",
        *(row for name, pair in chosen.items() for row in _rliable_rows(name, *pair, cmp, reps)),
    ]
    everything = chosen["all seeds"][0] + chosen["all seeds"][1]
    edges = window_edges(everything)
    if edges is not None:
        found_by_run = runaways(everything, edges, cmp.runaway_loss)
        windows = ", ".join(window_names(edges))
        lines += [
            "",
            f"Soft Bellman error: a run ran away when some task's critic loss, averaged over an evaluation window "
            f"({windows} env steps per task), is above {cmp.runaway_loss:g}; its task fell with it when the task's "
            f"final success is {_pct(cmp.fell)} points or more below its best in-training success up to the end of "
            "the first window above the criterion (best -> final, %).",
            "",
            "| Algorithm | Seed | Largest window mean | Ran away | Fell with it | Final (%) |",
            "|:--|--:|--:|:--|:--|--:|",
            *runaway_rows(everything, found_by_run, cmp.fell),
            "",
            *(fisher_line(name, tuple(pair), (cmp.a, cmp.b), found_by_run) for name, pair in chosen.items()),
        ]
    return "\n".join(lines) + "\n"


def _parser() -> argparse.ArgumentParser:
    parser = CommandParser(
        prog=command_prog("compare"),
        description="Two algorithms of one benchmark compared as fixed before the runs: the difference of mean final "
        "success with a bootstrap interval and Welch's t, rliable's aggregates, and the runs whose soft Bellman "
        "error ran away (Fisher's exact test).",
    )
    parser.add_argument("sources", nargs="+", help="folders of run folders and records (e.g. docs/records)")
    parser.add_argument("--benchmark", required=True, help="env id of the runs (e.g. MT10-100k)")
    parser.add_argument("--a", help="the first algorithm's label (default: the registered one, else Ours)")
    parser.add_argument("--b", help="the second algorithm's label (default: the registered one, else SAC-MT)")
    parser.add_argument("--replication-seeds", type=int, nargs="+", help="seeds of the replication")
    parser.add_argument("--runaway-loss", type=float, help="window-mean critic loss above which a run ran away")
    parser.add_argument("--fell", type=float, help="drop in success (0-1) that counts as falling with it")
    parser.add_argument("--reps", type=int, default=DEFAULT_REPS, help="rliable's bootstrap resamples")
    parser.add_argument("--out", help="also write the report to this markdown file")
    parser.add_argument(
        "--include-unfinished",
        action="store_true",
        help="count runs that did not finish, marked in the tables (default: left out, each named)",
    )
    return parser


def _comparison(args: argparse.Namespace) -> Comparison:
    cmp = PREREGISTERED.get(args.benchmark, Comparison())
    given = {
        "a": args.a,
        "b": args.b,
        "replication_seeds": None if args.replication_seeds is None else tuple(args.replication_seeds),
        "runaway_loss": args.runaway_loss,
        "fell": args.fell,
    }
    return replace(cmp, **{key: value for key, value in given.items() if value is not None})


def main(argv: Sequence[str] | None = None) -> str:
    parser = _parser()
    args = parser.parse_args(argv)
    missing = [source for source in args.sources if not Path(source).is_dir()]
    if missing:
        parser.error(f"{missing[0]} is not a folder: give folders of run folders or records (e.g. docs/records).")
    if args.reps < 1:
        parser.error(f"--reps {args.reps}: give a number of resamples of at least 1 (default {DEFAULT_REPS}).")
    if args.out and (problem := output_file_error("--out", args.out)):
        parser.error(problem)
    cmp = _comparison(args)
    runs = load_runs(args.sources)
    bench_runs = [run for members in group_runs(runs).get(args.benchmark, {}).values() for run in members]
    runs = leave_out_unfinished(bench_runs, args.include_unfinished, scope="the comparison")
    runs = leave_out_unevaluated(runs, scope="the comparison")
    labels = group_runs(runs).get(args.benchmark, {})
    absent = [label for label in (cmp.a, cmp.b) if label not in labels]
    if absent:
        known = ", ".join(sorted(labels)) or "none"
        where = " ".join(args.sources)
        parser.error(f"no runs of {absent[0]} on {args.benchmark} in {where} (algorithms there: {known}).")
    report = comparison_report(args.benchmark, runs, cmp, args.reps)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(report)
    sys.stdout.write(report)
    return report


__all__ = [
    "DIFFERENCE_REPS",
    "PREREGISTERED",
    "WELCH_UNDEFINED",
    "Comparison",
    "MeanDifference",
    "Runaway",
    "comparison_report",
    "comparison_summary",
    "fixed_reading",
    "main",
    "mean_difference",
    "runaway",
]
