"""What every figure of the results shares: the plot options, file names, figure titles, the colors of the
algorithms, and panel grids with their axis labels."""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from sb3_mtte.common.utils import short_task_name
from sb3_mtte.experiments.results.runs import Run
from sb3_mtte.experiments.results.statistics import DEFAULT_REPS, DEFAULT_SEED
from sb3_mtte.experiments.variants import variant_labels

_COLORS = tuple(
    f"tab:{name}" for name in ("blue", "orange", "green", "red", "purple", "brown", "pink", "gray", "olive", "cyan")
)
_LINESTYLES = ("-", "--", "-.", ":")


@dataclass
class PlotOptions:
    """Options of the figures.

    :param out: output folder.
    :param x_per_task: time axis in env steps per task (else over all tasks).
    :param smooth: moving-average window in points (1: none).
    :param tasks: tasks of Figs. 3 and 5 (full or short names; None: all).
    :param matrix_times: times of the transfer-matrix heatmaps (x units; None: first, middle, last).
    :param freq_window_episodes: window of the train frequency, in episodes.
    :param dpi: resolution of the PNG files.
    :param results_dir: folder of the per-benchmark results JSON (None: ``out``).
    :param reps: bootstrap resamples of the confidence intervals.
    :param seed: seed of the bootstrap resamples.
    :param include_unfinished: draw and count a run that did not finish (at its final or last evaluation), marked
        in the tables.
    """

    out: Path
    x_per_task: bool = True
    smooth: int = 1
    tasks: list[str] | None = None
    matrix_times: list[float] | None = None
    freq_window_episodes: int = 20
    dpi: int = 120
    results_dir: Path | None = None
    reps: int = DEFAULT_REPS
    seed: int = DEFAULT_SEED
    include_unfinished: bool = False

    def xscale(self, run: Run) -> float:
        return 1.0 / run.n_tasks if self.x_per_task else 1.0

    @property
    def xlabel(self) -> str:
        return "environment steps per task" if self.x_per_task else "environment steps (all tasks)"


def safe_name(name: str) -> str:
    """``name`` with only letters, digits and ``-_.`` (file names)."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def new_figure(width: float, height: float) -> Figure:
    return Figure(figsize=(width, height), layout="constrained")


def wrapped_title(fig: Figure, text: str, fontsize: float = 10) -> None:
    """A figure title wrapped to the figure's width."""
    chars = max(40, int(fig.get_figwidth() * 120 / fontsize))
    fig.suptitle(textwrap.fill(text, chars), fontsize=fontsize)


def algorithm_styles(labels: Sequence[str]) -> dict[str, tuple[str, str]]:
    """(color, linestyle) of each algorithm label: fixed by its place among the registered variants, so a registered
    method looks the same in every figure; unregistered labels take the places after them, in name order. Past ten
    labels the colors repeat with another line style, so no two of the first 40 labels share both."""
    known = variant_labels()
    place = {label: i for i, label in enumerate(known + sorted(set(labels) - set(known)))}
    return {
        label: (_COLORS[place[label] % len(_COLORS)], _LINESTYLES[place[label] // len(_COLORS) % len(_LINESTYLES)])
        for label in labels
    }


def point_marker(x: Sequence[float] | np.ndarray) -> str | None:
    """A dot for a series of one point, which a line alone would not show."""
    return "o" if len(x) == 1 else None


def selected_tasks(names: Sequence[str], wanted: Sequence[str] | None) -> list[int]:
    """Indices of the tasks named in ``wanted`` (full or short names, e.g. ``pick-place``); all when None."""
    if not wanted:
        return list(range(len(names)))
    chosen = []
    for want in wanted:
        for i, name in enumerate(names):
            if want in (name, short_task_name(name)) and i not in chosen:
                chosen.append(i)
    return chosen or list(range(len(names)))


def panel_grid(n: int, max_cols: int, width: float, height: float) -> tuple[Figure, list[Axes]]:
    """A figure with ``n`` panels in a grid of at most ``max_cols`` columns (unused cells hidden)."""
    cols = min(n, max_cols)
    rows = math.ceil(n / cols)
    fig = new_figure(width * cols, height * rows + 0.6)
    grid = fig.subplots(rows, cols, squeeze=False)
    axes = [grid[j // cols][j % cols] for j in range(rows * cols)]
    for ax in axes[n:]:
        ax.axis("off")
    return fig, axes[:n]


def label_panels(
    axes: Sequence[Axes], max_cols: int, xlabel: str, ylabel: str, twins: Sequence[Axes] = (), twin_label: str = ""
) -> None:
    """Axis labels on a :func:`panel_grid`'s panels: ``xlabel`` under each panel with none below it, ``ylabel`` left
    of the first column and, with ``twins`` (each panel's right axis), ``twin_label`` right of the last column."""
    cols = min(len(axes), max_cols)
    for i, ax in enumerate(axes):
        if i + cols >= len(axes):
            ax.set_xlabel(xlabel, fontsize=8)
        if i % cols == 0:
            ax.set_ylabel(ylabel, fontsize=8, **({"color": "tab:blue"} if twins else {}))
        if twins and (i % cols == cols - 1 or i == len(axes) - 1):
            twins[i].set_ylabel(twin_label, fontsize=8, color="tab:orange")


def seeds_text(runs: Sequence[Run]) -> str:
    """Which seeds a figure draws: ``seed 3``, or ``mean over seeds 0, 1 and 2``."""
    seeds = sorted({run.seed for run in runs if run.seed is not None})
    if not seeds:
        return "seed unknown"
    if len(seeds) == 1:
        return f"seed {seeds[0]}"
    return f"mean over seeds {', '.join(map(str, seeds[:-1]))} and {seeds[-1]}"


__all__ = [
    "PlotOptions",
    "algorithm_styles",
    "label_panels",
    "new_figure",
    "panel_grid",
    "point_marker",
    "safe_name",
    "seeds_text",
    "selected_tasks",
    "wrapped_title",
]
