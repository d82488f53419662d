"""The soft Bellman error run by run, as numbers: which task's critic loss was largest between evaluations, and how
much of the batch the clip of Eq. 16 dropped (Fig. 3's story, readable across seeds)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sb3_mtte.common.utils import short_task_name
from sb3_mtte.experiments.results.runs import Run, table_order, task_scalar
from sb3_mtte.experiments.results.statistics import seed_cell
from sb3_mtte.mtsac.task_logs import CLIP_FRACTION_KEY, CRITIC_LOSS_KEY

BELLMAN_NOTE = (
    "{bench}: the soft Bellman error (critic loss J^Q) run by run. Each window runs from one periodic evaluation to "
    "the next (the first from the start; env steps per task, on the evaluations of the run evaluated furthest); its "
    "cell names the task whose critic loss, averaged over the window's logged points, is the largest, and that "
    "average. Peak: the largest logged value over the whole run and its task. Clip dropped: the share of samples the "
    "clip of Eq. 16 dropped per logging window, mean and largest over the run (- without the clip). A record keeps up "
    "to 200 of its run's logged points; a point where some task's loss is missing or not finite is left out."
)


def critic_losses(run: Run) -> tuple[np.ndarray, np.ndarray] | None:
    """The run's env steps where every task logged a finite critic loss, and those losses ``(points, tasks)``; None
    without such a step."""
    series = [task_scalar(run, CRITIC_LOSS_KEY, i) for i in range(run.n_tasks)]
    if not series or any(s is None for s in series):
        return None
    by_step = [
        dict(zip(np.asarray(steps, dtype=float), np.asarray(values, dtype=float), strict=True))
        for steps, values in series
    ]
    common = sorted(set.intersection(*({t for t, v in task.items() if np.isfinite(v)} for task in by_step)))
    if not common:
        return None
    return np.asarray(common), np.array([[task[t] for task in by_step] for t in common])


def evaluation_steps(run: Run) -> np.ndarray | None:
    """Env steps per task of the run's periodic evaluations (``evaluations.npz``, else the ``eval/`` scalars)."""
    if run.evaluations is not None and len(run.evaluations.get("timesteps", [])):
        steps = np.asarray(run.evaluations["timesteps"], dtype=float)
    elif run.scalar("eval/success_rate") is not None:
        steps = np.asarray(run.scalar("eval/success_rate")[0], dtype=float)
    else:
        return None
    steps = steps[steps > 0] / run.n_tasks
    return steps if len(steps) else None


def window_peaks(steps: np.ndarray, losses: np.ndarray, edges: Sequence[float]) -> list[tuple[float, int] | None]:
    """Per window ``(previous edge, edge]`` (the first from 0): the largest per-task mean of ``losses`` over the
    window's points and that task's index; None for a window without points."""
    peaks: list[tuple[float, int] | None] = []
    for low, high in zip([0.0, *edges[:-1]], edges, strict=True):
        inside = (steps > low) & (steps <= high)
        means = losses[inside].mean(axis=0) if inside.any() else None
        peaks.append(None if means is None else (float(means.max()), int(means.argmax())))
    return peaks


def loss_text(value: float) -> str:
    """A critic loss in every table (the Bellman table, the comparison's runaways): from 100 up with one decimal and
    thousands separated (``1,692.2``), below 100 to three significant digits (``0.0776``)."""
    return f"{value:,.1f}" if abs(value) >= 100 else f"{value:.3g}"


def _thousands(env_steps: float) -> str:
    return f"{env_steps / 1000:g}k" if env_steps else "0"


def window_names(edges: Sequence[float]) -> list[str]:
    """``0-20k``, ``20k-40k``, ...: the windows that end at ``edges`` (env steps per task), the first from 0."""
    return [f"{_thousands(low)}-{_thousands(high)}" for low, high in zip([0.0, *edges[:-1]], edges, strict=True)]


def _clip(run: Run) -> str:
    clip = run.scalar(CLIP_FRACTION_KEY)
    if clip is None or not len(clip[1]):
        return "-"
    return f"{100 * np.mean(clip[1]):.2f} / {100 * np.max(clip[1]):.2f}"


def _row(run: Run, steps: np.ndarray, losses: np.ndarray, edges: np.ndarray) -> list[str]:
    names = [short_task_name(name) for name in run.task_names]
    cells = [run.label, seed_cell(run)]
    for peak in window_peaks(steps, losses, list(edges)):
        cells.append("-" if peak is None else f"{loss_text(peak[0])} {names[peak[1]]}")
    point, task = np.unravel_index(int(np.argmax(losses)), losses.shape)
    return [*cells, f"{loss_text(float(losses[point, task]))} {names[task]}", _clip(run)]


def bellman_table(bench: str, groups: dict[str, list[Run]]) -> str | None:
    """Markdown table of a benchmark's runs with per-task critic losses (None without any): per window between
    evaluations the largest task mean, the peak, and the clip's share; the windows are those of the run evaluated
    furthest."""
    rows = []
    for run in table_order(groups):
        losses, evaluations = critic_losses(run), evaluation_steps(run)
        if losses is not None and evaluations is not None:
            rows.append((run, *losses, evaluations))
    if not rows:
        return None
    edges = max((row[3] for row in rows), key=lambda grid: (grid[-1], len(grid)))
    headers = ["Algorithm", "Seed", *window_names(list(edges)), "Peak", "Clip dropped (mean / max, %)"]
    lines = ["| " + " | ".join(headers) + " |", "|:--|--:|" + "--:|" * (len(headers) - 2)]
    for run, steps, losses, _ in rows:
        lines.append("| " + " | ".join(_row(run, steps / run.n_tasks, losses, edges)) + " |")
    return BELLMAN_NOTE.format(bench=bench) + "\n\n" + "\n".join(lines) + "\n"
