"""Aggregate statistics of the field (Agarwal et al., 2021), computed with rliable.

Scores are success rates in [0, 1], one matrix ``(runs, tasks)`` per algorithm (its seeds x the benchmark's tasks),
or ``(runs, tasks, times)`` for curves. Intervals are 95% stratified-bootstrap confidence intervals over runs
(runs are resampled within each task). rliable draws its resamples from numpy's global generator, so every estimate
here runs under :func:`seeded`, which sets it from ``seed`` for each label and restores it afterwards: the same
scores and seed give the same intervals, and a label's interval depends on its own scores alone.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
from rliable import library as rly
from rliable import metrics

from sb3_mtte.experiments.results.runs import Run, success_curve

DEFAULT_REPS = 2000
DEFAULT_SEED = 0
PROFILE_TAUS = np.linspace(0.0, 1.0, 21)


@dataclass(frozen=True)
class Estimate:
    """A point estimate and its 95% confidence interval."""

    value: float
    low: float
    high: float


@contextmanager
def seeded(seed: int) -> Iterator[None]:
    """numpy's global generator set from ``seed`` (rliable's resamples come from it), restored on exit."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # arch's notice on the random_state argument
            yield
    finally:
        np.random.set_state(state)


def _per_label(scores: Mapping[str, Any], draw: Callable[[dict], tuple[dict, dict]], seed: int) -> tuple[dict, dict]:
    """``draw`` (an rliable estimator returning two dicts by label) run for each label alone, from a generator set
    from ``seed``, so that a label's interval does not change when another label's runs are added."""
    estimates: tuple[dict, dict] = ({}, {})
    for label, label_scores in scores.items():
        with seeded(seed):
            drawn = draw({label: label_scores})
        for out, by_label in zip(estimates, drawn, strict=True):
            out[label] = by_label[label]
    return estimates


def _intervals(
    scores: Mapping[str, np.ndarray | list[np.ndarray]], func: Callable[..., np.ndarray], reps: int, seed: int
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    return _per_label(scores, lambda one: rly.get_interval_estimates(one, func, reps=reps), seed)


def aggregate_estimates(
    scores: Mapping[str, np.ndarray], reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED
) -> dict[str, dict[str, Estimate]]:
    """``{label: {"mean": Estimate, "iqm": Estimate}}`` over runs x tasks of each ``(runs, tasks)`` matrix."""

    def mean_and_iqm(matrix: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_mean(matrix), metrics.aggregate_iqm(matrix)])

    points, intervals = _intervals(scores, mean_and_iqm, reps, seed)
    return {
        label: {
            name: Estimate(float(points[label][j]), float(intervals[label][0, j]), float(intervals[label][1, j]))
            for j, name in enumerate(("mean", "iqm"))
        }
        for label in scores
    }


def improvement_probabilities(
    ours: np.ndarray, baselines: Mapping[str, np.ndarray], reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED
) -> dict[str, Estimate]:
    """P(ours > baseline) per baseline: the chance that a run of ``ours`` beats one of the baseline on a task,
    averaged over tasks, with runs of each algorithm resampled independently within each task."""

    def probability(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.array([metrics.probability_of_improvement(x, y)])

    pairs = {label: [ours, scores] for label, scores in baselines.items()}
    points, intervals = _intervals(pairs, probability, reps, seed)
    return {
        label: Estimate(float(points[label][0]), float(intervals[label][0, 0]), float(intervals[label][1, 0]))
        for label in baselines
    }


def performance_profiles(
    scores: Mapping[str, np.ndarray],
    taus: np.ndarray = PROFILE_TAUS,
    reps: int = DEFAULT_REPS,
    seed: int = DEFAULT_SEED,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Score distributions: per label, the share of runs x tasks with success above each tau, and its interval
    ``(2, len(taus))``."""
    return _per_label(scores, lambda one: rly.create_performance_profile(one, taus, reps=reps), seed)


def curve_estimates(curves: np.ndarray, reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED) -> dict[str, np.ndarray]:
    """Mean curves and their pointwise intervals from ``curves (runs, tasks, times)``: ``mean`` and ``low``/``high``
    of the mean over tasks ``(times,)``, and ``task_mean``/``task_low``/``task_high`` of each task ``(tasks, times)``
    (the mean over runs)."""
    n_tasks, n_times = curves.shape[1:]

    def means(sample: np.ndarray) -> np.ndarray:
        return np.concatenate([sample.mean(axis=(0, 1)), sample.mean(axis=0).ravel()])

    points, intervals = _intervals({"curves": curves}, means, reps, seed)
    point, (low, high) = points["curves"], intervals["curves"]
    per_task = (n_tasks, n_times)
    return {
        "mean": point[:n_times],
        "low": low[:n_times],
        "high": high[:n_times],
        "task_mean": point[n_times:].reshape(per_task),
        "task_low": low[n_times:].reshape(per_task),
        "task_high": high[n_times:].reshape(per_task),
    }


def has_final_evaluation(run: Run) -> bool:
    """Whether a run has a final evaluation (``success.json``, a record's ``final``) of every task."""
    per_task = (run.final or {}).get("per_task")
    return bool(per_task) and all(name in per_task for name in run.task_names)


def run_budget(run: Run) -> tuple[int | None, int | None]:
    """``(reached, planned)`` env steps of a run (all tasks): reached from its ``run_info`` (written when training
    ends), else its success curve's last point; planned: its ``n_timesteps``; None where unknown."""
    curve = success_curve(run)
    reached = run.info.get("timesteps") or (int(curve[0][-1]) if curve is not None and len(curve[0]) else None)
    planned = run.info.get("n_timesteps") or (run.info.get("hyperparams") or {}).get("n_timesteps")
    return reached, None if planned is None else int(planned)


def unfinished(run: Run) -> bool:
    """Whether a run did not finish: its ``run_info`` (a record's ``budget``) says ``finished: false``, as for a run
    that crashed, was stopped or killed, or is still training, even when it was evaluated since. A run that predates
    the field did not finish when it has no final evaluation and reached fewer env steps than its ``n_timesteps``:
    a run that trained its whole budget is finished, and its last evaluation is its final success."""
    finished = run.info.get("finished")
    if finished is not None:
        return not finished
    if has_final_evaluation(run):
        return False
    reached, planned = run_budget(run)
    return planned is not None and (reached is None or reached < planned)


def stopped_at(run: Run) -> str:
    """Where a run stopped, for a line: ``at 6,948 of 16,000 env steps``, else ``before its budget``."""
    reached, planned = run_budget(run)
    return "before its budget" if planned is None else f"at {reached or 0:,} of {planned:,} env steps"


def seed_cell(run: Run) -> str:
    """A run's seed in a table, marked when the run did not finish (``2 (unfinished)``); ``-`` when unknown."""
    seed = "-" if run.seed is None else str(run.seed)
    return f"{seed} (unfinished)" if unfinished(run) else seed


def count_cell(runs: Sequence[Run]) -> str:
    """How many runs a table row counts, with how many of them did not finish (``3 (1 unfinished)``)."""
    stopped = sum(unfinished(run) for run in runs)
    return f"{len(runs)} ({stopped} unfinished)" if stopped else str(len(runs))


def leave_out_unfinished(
    runs: Sequence[Run], include: bool, scope: str = "every figure and table", action: str = "counts"
) -> list[Run]:
    """``runs`` but those that did not finish (:func:`unfinished`), each named in one line on stderr saying where
    it stopped and what ``--include-unfinished`` does (``action``: counts, records); all of them with ``include``
    (the tables mark them)."""
    kept = []
    for run in runs:
        if include or not unfinished(run):
            kept.append(run)
            continue
        who = f"{run.path} ({run.benchmark}, {run.label}, seed {run.seed})"
        if has_final_evaluation(run):
            why, counted = f"did not finish: it stopped {stopped_at(run)}", "its final evaluation, marked unfinished"
        else:
            why, counted = f"has no final evaluation and stopped {stopped_at(run)}", "its last evaluation"
        print(f"Left out of {scope}: {who} {why}; --include-unfinished {action} {counted}", file=sys.stderr)
    return kept


def final_task_scores(run: Run) -> np.ndarray | None:
    """A run's final success per task: its final evaluation (``success.json``), else the last point of each task's
    periodic evaluations; None when a task has neither (the training episodes' success never stands in)."""
    if has_final_evaluation(run):
        per_task = (run.final or {})["per_task"]
        return np.array([float(per_task[name]) for name in run.task_names])
    scores = []
    for task in range(run.n_tasks):
        curve = success_curve(run, task, training_episodes=False)
        if curve is None or not len(curve[1]):
            return None
        scores.append(float(curve[1][-1]))
    return np.array(scores)


def leave_out_unevaluated(runs: Sequence[Run], scope: str) -> list[Run]:
    """``runs`` but those without an evaluation to score (:func:`final_task_scores`), each named in one line on
    stderr with the command that evaluates it. Table 1 and the comparison count runs by this rule."""
    kept = []
    for run in runs:
        if final_task_scores(run) is not None:
            kept.append(run)
            continue
        model = run.path / f"{run.benchmark}.zip"
        fix = f"sb3-mtte evaluate {model}" if model.is_file() else "evaluate its model with sb3-mtte evaluate"
        who = f"{run.path} ({run.benchmark}, {run.label}, seed {run.seed})"
        print(f"Left out of {scope}: {who} has no evaluation to score; {fix}", file=sys.stderr)
    return kept


def score_matrix(runs: Sequence[Run]) -> np.ndarray | None:
    """``(runs, tasks)`` final success of the runs that have one; None when none has."""
    rows = [scores for scores in (final_task_scores(run) for run in runs) if scores is not None]
    return np.stack(rows) if rows else None


__all__ = [
    "DEFAULT_REPS",
    "DEFAULT_SEED",
    "Estimate",
    "aggregate_estimates",
    "count_cell",
    "curve_estimates",
    "final_task_scores",
    "has_final_evaluation",
    "improvement_probabilities",
    "leave_out_unevaluated",
    "leave_out_unfinished",
    "performance_profiles",
    "run_budget",
    "score_matrix",
    "seed_cell",
    "seeded",
    "stopped_at",
    "unfinished",
]
