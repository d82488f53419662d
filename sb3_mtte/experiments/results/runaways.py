"""Runs whose soft Bellman error ran away: some task's critic loss, averaged over an evaluation window, above a
criterion, and whether that task's success fell with it (the comparison's second question,
:mod:`sb3_mtte.experiments.results.compare`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from sb3_mtte.common.utils import short_task_name
from sb3_mtte.experiments.results.bellman_table import critic_losses, evaluation_steps, loss_text, window_peaks
from sb3_mtte.experiments.results.runs import Run, success_curve
from sb3_mtte.experiments.results.statistics import final_task_scores, seed_cell


@dataclass(frozen=True)
class Runaway:
    """A run's largest window-mean critic loss (and its task), its first window above the criterion (None when it
    stayed below), and the runaway task's best in-training success up to that window's end and final success."""

    peak: float
    task: int
    window: int | None
    best_before: float | None = None
    final: float | None = None

    def fell(self, points: float) -> bool:
        return self.window is not None and self.final is not None and self.final <= (self.best_before or 0) - points


def runaway(run: Run, edges: Sequence[float], loss: float) -> Runaway | None:
    """The run's soft Bellman error over the windows ``(0, edges[0]], (edges[0], edges[1]], ...`` (env steps per
    task); None without per-task critic losses."""
    losses = critic_losses(run)
    if losses is None:
        return None
    peaks = window_peaks(losses[0] / run.n_tasks, losses[1], list(edges))
    largest = max((p for p in peaks if p is not None), default=None)
    if largest is None:
        return None
    first = next((k for k, p in enumerate(peaks) if p is not None and p[0] > loss), None)
    if first is None:
        return Runaway(largest[0], largest[1], None)
    task = peaks[first][1]
    steps, values = success_curve(run, task)
    seen = values[np.asarray(steps, dtype=float) / run.n_tasks <= edges[first]]
    final = final_task_scores(run)
    return Runaway(
        largest[0], task, first, float(seen.max()) if len(seen) else None, None if final is None else float(final[task])
    )


def window_edges(runs: Sequence[Run]) -> list[float] | None:
    """The ends of the evaluation windows (env steps per task): those of the run evaluated furthest."""
    grids = [grid for grid in (evaluation_steps(run) for run in runs) if grid is not None]
    return list(max(grids, key=lambda grid: (grid[-1], len(grid)))) if grids else None


def runaways(runs: Sequence[Run], edges: Sequence[float], loss: float) -> dict[int, Runaway | None]:
    """:func:`runaway` of every run, by ``id(run)``."""
    return {id(run): runaway(run, edges, loss) for run in runs}


def ran_away(found: Runaway | None) -> bool:
    return found is not None and found.window is not None


def _pct(value: float) -> str:
    return f"{100 * value:.1f}"


def _final_mean(run: Run) -> str:
    return _pct(float(np.mean(final_task_scores(run))))


def runaway_rows(runs: Sequence[Run], found_by_run: dict[int, Runaway | None], fell: float) -> list[str]:
    """One markdown row per run: its largest window mean and task, whether and from which window it ran away,
    whether its task fell with it by ``fell`` or more (best -> final), and its final success."""
    rows = []
    for run in runs:
        found = found_by_run[id(run)]
        if found is None:
            rows.append(f"| {run.label} | {seed_cell(run)} | - | - | - | {_final_mean(run)} |")
            continue
        name = short_task_name(run.task_names[found.task]) if run.task_names else str(found.task)
        ran, fell_cell = "no", "-"
        if found.window is not None:
            ran = f"yes, from window {found.window + 1}"
            change = f"{_pct(found.best_before or 0)} -> {_pct(found.final or 0)}"
            fell_cell = f"{'yes' if found.fell(fell) else 'no'} ({change})"
        cells = [run.label, seed_cell(run), f"{loss_text(found.peak)} {name}", ran, fell_cell, _final_mean(run)]
        rows.append("| " + " | ".join(cells) + " |")
    return rows


def fisher_line(
    name: str, runs: tuple[list[Run], list[Run]], labels: tuple[str, str], found_by_run: dict[int, Runaway | None]
) -> str:
    """How many runs of each algorithm ran away on a subset, with Fisher's exact test of the two counts."""
    a, b = runs
    count_a, count_b = (sum(ran_away(found_by_run[id(run)]) for run in group) for group in runs)
    line = f"- {name}: {labels[0]} {count_a} of {len(a)}, {labels[1]} {count_b} of {len(b)} runs ran away"
    if a and b:
        _, p = stats.fisher_exact([[count_a, len(a) - count_a], [count_b, len(b) - count_b]])
        line += f"; Fisher's exact test (two-sided) p = {float(p):.3f}"
    return line + "."


__all__ = ["Runaway", "fisher_line", "ran_away", "runaway", "runaway_rows", "runaways", "window_edges"]
