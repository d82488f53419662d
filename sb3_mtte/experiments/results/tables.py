"""Final results of a benchmark's runs: Table 1 (markdown, with rliable's aggregates) and the results JSON."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sb3_mtte.common.utils import short_task_name
from sb3_mtte.experiments.results.runs import Run, label_order, success_curve, table_order
from sb3_mtte.experiments.results.statistics import (
    DEFAULT_REPS,
    DEFAULT_SEED,
    Estimate,
    aggregate_estimates,
    final_task_scores,
    improvement_probabilities,
    score_matrix,
    seed_cell,
    unfinished,
)
from sb3_mtte.experiments.variants import paper_sources, paper_table1


def results_records(runs: Sequence[Run]) -> list[dict[str, Any]]:
    """One record per run with a final evaluation (``success.json``): algo, label, benchmark, seed, env_steps and
    success ``{"mean": m, "per_task": {task: rate}}``, sorted by algorithm order and seed."""
    records = []
    for run in runs:
        if run.final is None or "per_task" not in run.final:
            continue
        records.append(
            {
                **({"unfinished": True} if unfinished(run) else {}),
                "algo": run.info.get("algo"),
                "label": run.label,
                "benchmark": run.benchmark,
                "seed": run.seed,
                "env_steps": run.final.get("timesteps"),
                "episodes_per_task": run.final.get("episodes_per_task"),
                "success": {"mean": run.final["mean"], "per_task": run.final["per_task"]},
            }
        )
    order = {label: i for i, label in enumerate(label_order([r["label"] for r in records]))}
    return sorted(records, key=lambda r: (order[r["label"]], r["seed"] if r["seed"] is not None else -1))


OURS_ALGO = "mtsacte"
"""Zoo key of the method whose probability of improvement over every other method the table shows."""


@dataclass
class BenchmarkStatistics:
    """Final success of one benchmark's algorithms: ``scores`` label -> ``(runs, tasks)``, the mean and IQM of each
    with its interval, P(Ours > label) for every other label (empty without Ours), and the Meta-World reward
    functions of the runs (empty off Meta-World), ``scored`` label -> the runs behind ``scores``, and the labels of
    the training envs that are not Meta-World's benchmark protocol (``protocols``; empty on Meta-World's own)."""

    scores: dict[str, np.ndarray]
    aggregates: dict[str, dict[str, Estimate]]
    ours: str | None
    improvement: dict[str, Estimate]
    reward_function_versions: tuple[str, ...] = ()
    scored: dict[str, list[Run]] = field(default_factory=dict)
    protocols: tuple[str, ...] = ()


def ours_label(groups: dict[str, list[Run]]) -> str | None:
    """The label of the runs of :data:`OURS_ALGO`, if any."""
    return next((label for label, runs in groups.items() if any(r.info.get("algo") == OURS_ALGO for r in runs)), None)


def benchmark_statistics(
    groups: dict[str, list[Run]], reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED
) -> BenchmarkStatistics:
    """Score matrices and their aggregates (rliable) for the algorithms of one benchmark, in label order."""
    scores, scored = {}, {}
    for label in label_order(list(groups)):
        matrix = score_matrix(groups[label])
        if matrix is not None:
            scores[label] = matrix
            scored[label] = [run for run in groups[label] if final_task_scores(run) is not None]
    ours = ours_label({label: groups[label] for label in scores})
    baselines = {label: matrix for label, matrix in scores.items() if label != ours}
    improvement = improvement_probabilities(scores[ours], baselines, reps, seed) if ours and baselines else {}
    versions = {run.reward_function_version for label in scores for run in groups[label]} - {None}
    aggregates = aggregate_estimates(scores, reps, seed) if scores else {}
    protocols = tuple(sorted(_protocol_labels(run for runs in scored.values() for run in runs)))
    return BenchmarkStatistics(scores, aggregates, ours, improvement, tuple(sorted(versions)), scored, protocols)


def _protocol_labels(runs: Iterable[Run]) -> set[str]:
    """The labels of the training envs of ``runs`` that are not Meta-World's benchmark protocol."""
    protocols = (run.env_protocol for run in runs)
    return {str(p.get("label")) for p in protocols if p and p.get("benchmark_protocol") is False}


def _cell(estimate: Estimate | None, scale: float = 100.0, digits: int = 1) -> str:
    if estimate is None:
        return "-"
    value, low, high = (f"{scale * v:.{digits}f}" for v in (estimate.value, estimate.low, estimate.high))
    return f"{value} [{low}, {high}]"


SAME_BUDGET_ANCHORS: dict[str, tuple[str, dict[str, str]]] = {
    "MT10-100k": (
        "McLean et al. 2025 (Multi-Task RL Enables Parameter Scaling), Meta-World MT10, multi-head multi-task SAC with "
        "3 hidden layers 256 and 512 wide (ours: 2 x 400, one-hot input), 28.3% and 33.1% after 1.0M env steps "
        "(100k per task), the IQM over their seeds of each run's mean success, read off their Fig. 3 "
        "(scripts/studies/read_vega_lines.py on figures/fig3_mt10.svg of rainx0r/mtrl); their protocol, not ours",
        {"SAC-MT": "28-33"},
    ),
}
"""Benchmark (env id) -> (source, label -> published success (%) at the benchmark's own budget)."""


def _table_note(bench: str, stats: BenchmarkStatistics, published: dict[str, float], reps: int, seed: int) -> str:
    note = (
        f"{bench}: final success over runs x tasks. n: seeds; [low, high]: 95% stratified-bootstrap confidence "
        f"interval ({reps} resamples, seed {seed}; rliable, Agarwal et al. 2021); IQM: interquartile mean"
    )
    if stats.improvement:
        note += f"; P({stats.ours} > X): probability that a run of {stats.ours} beats a run of X on a task"
    note += ". A run's final success is its final evaluation (success.json) when present, else its last evaluation."
    if any(unfinished(run) for runs in stats.scored.values() for run in runs):
        note += f" Unfinished: {UNFINISHED_NOTE}"
    if stats.reward_function_versions:
        note += f" Meta-World reward function {' and '.join(stats.reward_function_versions)}."
    if stats.protocols:
        note += (
            f" Trained on {' and '.join(stats.protocols)}, not Meta-World's benchmark protocol; evaluated on "
            "Meta-World's own envs."
        )
    if published:
        by_source: dict[str, list[str]] = {}
        for label, source in paper_sources().items():
            if label in published:
                by_source.setdefault(source, []).append(label)
        sources = "".join(f" {' and '.join(labels)}: {source}." for source, labels in by_source.items())
        note += " Published: the paper's Table 1 (Meta-World v2, 5 seeds)" + (f", except{sources}" if sources else ".")
    if bench in SAME_BUDGET_ANCHORS:
        note += f" At this budget: {SAME_BUDGET_ANCHORS[bench][0]}."
    return note


def _unfinished_seeds(runs: Sequence[Run]) -> str:
    """The seeds of ``runs`` that did not finish, for Table 1's column (``seeds 2, 4``), or ``-``."""
    seeds = [seed_cell(run).split(" ")[0] for run in runs if unfinished(run)]
    return "-" if not seeds else f"seed{'s' if len(seeds) > 1 else ''} {', '.join(seeds)}"


def table1(bench: str, stats: BenchmarkStatistics, reps: int = DEFAULT_REPS, seed: int = DEFAULT_SEED) -> str:
    """Markdown Table 1 of one benchmark: per algorithm, n (seeds), mean and IQM of the final success over runs x
    tasks and P(Ours > algorithm), each with its 95% interval, and the published success where there is one."""
    family = bench.split("-")[0]
    published = {
        label: paper[family] for label, paper in paper_table1().items() if label in stats.scores and family in paper
    }
    headers = ["Algorithm", "n", "Mean success (%)", "IQM (%)"]
    headers += [f"P({stats.ours} > X)"] if stats.improvement else []
    headers += ["Published (%)"] if published else []
    anchors = SAME_BUDGET_ANCHORS.get(bench, ("", {}))[1]
    headers += ["At this budget (%)"] if anchors else []
    marked = any(unfinished(run) for runs in stats.scored.values() for run in runs)
    headers += ["Unfinished"] if marked else []
    lines = ["| " + " | ".join(headers) + " |", "|:--|" + "--:|" * (len(headers) - 1)]
    for label, matrix in stats.scores.items():
        cells = [label, str(len(matrix)), _cell(stats.aggregates[label]["mean"]), _cell(stats.aggregates[label]["iqm"])]
        if stats.improvement:
            cells.append(_cell(stats.improvement.get(label), scale=1.0, digits=2))
        if published:
            cells.append(f"{published[label]:.1f}" if label in published else "-")
        if anchors:
            cells.append(anchors.get(label, "-"))
        if marked:
            cells.append(_unfinished_seeds(stats.scored.get(label, [])))
        lines.append("| " + " | ".join(cells) + " |")
    return _table_note(bench, stats, published, reps, seed) + "\n\n" + "\n".join(lines) + "\n"


UNFINISHED_NOTE = (
    "a run that did not finish (drawn with --include-unfinished), counted at its final evaluation, else its last."
)

RUNS_NOTE = (
    "{bench}: every run, seed by seed. Final: the final success that Table 1 counts (its final evaluation when "
    "present, else its last evaluation); last in training: the mean success of the run's last periodic evaluation "
    "(of its last training episodes where it logged none); tasks above 0: the final success of each task that is "
    "not 0, highest first; commit: the package commit at the run's start."
)


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def _commit(run: Run) -> str:
    git = run.info.get("git") or {}
    commit = str(git.get("commit") or "")[:7]
    if not commit:
        return "-"
    return commit + " (dirty)" if git.get("dirty") else commit


def run_row(run: Run) -> list[str]:
    """Cells of one run in :func:`runs_table`."""
    final = final_task_scores(run)
    curve = success_curve(run)
    last = float(curve[1][-1]) if curve is not None and len(curve[1]) else None
    above = (
        [] if final is None else sorted(zip(final, run.task_names, strict=True), key=lambda pair: (-pair[0], pair[1]))
    )
    tasks = ", ".join(f"{short_task_name(name)} {100 * rate:.0f}" for rate, name in above if rate > 0)
    mean = None if final is None else float(final.mean())
    tasks = "-" if final is None else tasks or "none"
    return [run.label, seed_cell(run), _percent(mean), _percent(last), tasks, _commit(run)]


def runs_table(bench: str, groups: dict[str, list[Run]]) -> str:
    """Markdown table of a benchmark's runs, one row per seed in label order: final and last in-training success,
    the tasks above 0 at the end, and the package commit."""
    headers = ["Algorithm", "Seed", "Final (%)", "Last in training (%)", "Tasks above 0 at the end (%)", "Commit"]
    lines = ["| " + " | ".join(headers) + " |", "|:--|--:|--:|--:|:--|:--|"]
    runs = table_order(groups)
    for run in runs:
        lines.append("| " + " | ".join(run_row(run)) + " |")
    note = RUNS_NOTE.format(bench=bench)
    if any(unfinished(run) for run in runs):
        note += f" Unfinished: {UNFINISHED_NOTE}"
    return note + "\n\n" + "\n".join(lines) + "\n"
