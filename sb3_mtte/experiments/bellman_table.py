"""The soft Bellman error run by run, as numbers: which task's critic loss was largest between evaluations, and how
much of the batch the clip of Eq. 16 dropped (Fig. 3's story, readable across seeds)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sb3_mtte.common.utils import short_task_name
from sb3_mtte.experiments.runs import Run, label_order, success_curve, task_scalar
from sb3_mtte.mtsac.task_logs import CLIP_FRACTION_KEY, CRITIC_LOSS_KEY

BELLMAN_NOTE = (
    "{bench}: the soft Bellman error (critic loss J^Q) run by run. Each window runs from one periodic evaluation to "
    "the next (env steps per task); its cell names the task whose critic loss, averaged over the window's logged "
    "points, is the largest, and that average. Peak: the largest logged value and its task. Clip dropped: the share "
    "of samples the clip of Eq. 16 dropped per logging window, mean and largest over the run (- without the clip). "
    "A record keeps up to 200 of its run's logged points."
)


def critic_losses(run: Run) -> tuple[np.ndarray, np.ndarray] | None:
    """The run's logged env steps and its per-task critic loss ``(points, tasks)``; None unless every task has one
    on the same steps."""
    series = [task_scalar(run, CRITIC_LOSS_KEY, i) for i in range(run.n_tasks)]
    if not series or any(s is None or not np.array_equal(s[0], series[0][0]) for s in series):
        return None
    return np.asarray(series[0][0], dtype=float), np.stack([values for _, values in series], axis=1)


def window_peaks(steps: np.ndarray, losses: np.ndarray, edges: Sequence[float]) -> list[tuple[float, int] | None]:
    """Per window ``(previous edge, edge]`` (the first from 0): the largest per-task mean of ``losses`` over the
    window's points and that task's index; None for a window without points."""
    peaks: list[tuple[float, int] | None] = []
    for low, high in zip([0.0, *edges[:-1]], edges, strict=True):
        inside = (steps > low) & (steps <= high)
        means = losses[inside].mean(axis=0) if inside.any() else None
        peaks.append(None if means is None else (float(means.max()), int(means.argmax())))
    return peaks


def _loss(value: float) -> str:
    return f"{value:,.0f}" if value >= 100 else f"{value:.3g}"


def _thousands(env_steps: float) -> str:
    return f"{env_steps / 1000:g}k" if env_steps else "0"


def _clip(run: Run) -> str:
    clip = run.scalar(CLIP_FRACTION_KEY)
    if clip is None or not len(clip[1]):
        return "-"
    return f"{100 * np.mean(clip[1]):.2f} / {100 * np.max(clip[1]):.2f}"


def _row(run: Run, steps: np.ndarray, losses: np.ndarray, edges: np.ndarray) -> list[str]:
    names = [short_task_name(name) for name in run.task_names]
    cells = [run.label, "-" if run.seed is None else str(run.seed)]
    for peak in window_peaks(steps, losses, list(edges)):
        cells.append("-" if peak is None else f"{_loss(peak[0])} {names[peak[1]]}")
    point, task = np.unravel_index(int(np.argmax(losses)), losses.shape)
    return [*cells, f"{_loss(float(losses[point, task]))} {names[task]}", _clip(run)]


def bellman_table(bench: str, groups: dict[str, list[Run]]) -> str | None:
    """Markdown table of a benchmark's runs with per-task critic losses (None without any): per window between
    evaluations the largest task mean, the peak, and the clip's share; windows on the longest evaluation grid."""
    rows = []
    for label in label_order(list(groups)):
        for run in sorted(groups[label], key=lambda r: -1 if r.seed is None else r.seed):
            losses = critic_losses(run)
            curve = None if losses is None else success_curve(run)
            if losses is not None and curve is not None:
                edges = np.asarray(curve[0], dtype=float) / run.n_tasks
                rows.append((run, *losses, edges[edges > 0]))
    if not rows:
        return None
    edges = max((row[3] for row in rows), key=len)
    windows = [f"{_thousands(low)}-{_thousands(high)}" for low, high in zip([0.0, *edges[:-1]], edges, strict=True)]
    headers = ["Algorithm", "Seed", *windows, "Peak", "Clip dropped (mean / max, %)"]
    lines = ["| " + " | ".join(headers) + " |", "|:--|--:|" + "--:|" * (len(headers) - 2)]
    for run, steps, losses, _ in rows:
        lines.append("| " + " | ".join(_row(run, steps / run.n_tasks, losses, edges)) + " |")
    return BELLMAN_NOTE.format(bench=bench) + "\n\n" + "\n".join(lines) + "\n"
