"""The three figures of a benchmark drawn with every method, from run folders or records (``<b>`` = benchmark):

- ``success_<b>.png`` (Figs. 4 and 7): success averaged over tasks against env steps, the mean over seeds with its
  95% stratified-bootstrap confidence band (runs resampled within each task at every evaluation), Fig. 7's
  ablations in a second panel beside the method they ablate;
- ``per_task_<b>.png`` (Figs. 8-9): success of every task, the mean over seeds with its 95% bootstrap band (every
  method but the ablations);
- ``profile_<b>.png``: performance profile of the final success (score distribution over runs x tasks: the share
  with success above tau) with its 95% confidence band.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes

from sb3_mtte.common.utils import short_task_name
from sb3_mtte.experiments.results.figure_layout import (
    PlotOptions,
    algorithm_styles,
    label_panels,
    new_figure,
    panel_grid,
    point_marker,
    safe_name,
    wrapped_title,
)
from sb3_mtte.experiments.results.figures import save_figure
from sb3_mtte.experiments.results.runs import Run, common_grid, label_order, smooth, success_curve
from sb3_mtte.experiments.results.statistics import PROFILE_TAUS, curve_estimates, performance_profiles
from sb3_mtte.experiments.variants import ablation_labels

BAND_NOTE = "mean over seeds, band: 95% stratified-bootstrap CI"
PER_TASK_COLUMNS = 5


@dataclass
class CurveBand:
    """An algorithm's success curves on one benchmark: x (in the figures' units), the estimates of
    :func:`~sb3_mtte.experiments.results.statistics.curve_estimates` and the number of runs behind them."""

    x: np.ndarray
    estimates: dict[str, np.ndarray]
    n_runs: int


def task_curves(runs: Sequence[Run], opts: PlotOptions) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-task success of every run that has all its task curves, on a shared x grid: ``x (T,)`` and
    ``curves (runs, tasks, T)``; None when no run has them."""
    per_run = []
    for run in runs:
        curves = [success_curve(run, task) for task in range(run.n_tasks)]
        if curves and all(curve is not None and len(curve[0]) for curve in curves):
            per_run.append([(x * opts.xscale(run), smooth(y, opts.smooth)) for x, y in curves])
    if not per_run:
        return None
    grid = common_grid([curve for curves in per_run for curve in curves])
    stacked = np.array([[np.interp(grid, x, y) for x, y in curves] for curves in per_run])
    return grid, stacked


def curve_bands(groups: Mapping[str, Sequence[Run]], opts: PlotOptions) -> dict[str, CurveBand]:
    """The success curves of every algorithm label that has some, in label order."""
    bands = {}
    for label in label_order(list(groups)):
        curves = task_curves(groups[label], opts)
        if curves is not None:
            x, stacked = curves
            bands[label] = CurveBand(x, curve_estimates(stacked, opts.reps, opts.seed), len(stacked))
    return bands


def _band(
    ax: Axes, x: np.ndarray, mean: np.ndarray, low: np.ndarray, high: np.ndarray, label: str, style: tuple[str, str]
) -> None:
    color, linestyle = style
    ax.plot(x, 100 * mean, label=label, color=color, linestyle=linestyle, marker=point_marker(x))
    if np.any(high > low):
        ax.fill_between(x, 100 * low, 100 * high, alpha=0.2, color=color)


def success_panels(labels: Sequence[str]) -> list[tuple[str, list[str]]]:
    """The panels of the success figure: (title, labels). Table 1's rows and the peers in one; when an ablation
    (Fig. 7) has runs, the ablated method and its ablations in a second, so neither panel is crowded."""
    fig7 = ablation_labels()
    ablations = [label for label in labels if label in fig7[1:]]
    if not ablations:
        return [("", list(labels))]
    others = [label for label in labels if label not in ablations]
    ablated = [label for label in labels if label in fig7 and label not in ablations]
    return [("Table 1 and peers", others), ("ablations (Fig. 7)", ablated + ablations)]


def plot_success(bench: str, bands: Mapping[str, CurveBand], opts: PlotOptions, written: list[Path]) -> None:
    """Mean success over tasks of every algorithm, with its confidence band over seeds; the y axis spans the
    highest band (at least 0-25%) so that low curves stay apart."""
    panels = success_panels(list(bands))
    fig = new_figure(7 if len(panels) == 1 else 11, 4.5)
    axes = fig.subplots(1, len(panels), sharey=True, squeeze=False)[0]
    styles = algorithm_styles(list(bands))
    top = max([25.0] + [100 * float(np.max(band.estimates["high"])) for band in bands.values()])
    for ax, (title, labels) in zip(axes, panels, strict=True):
        for label in labels:
            est = bands[label].estimates
            _band(
                ax,
                bands[label].x,
                est["mean"],
                est["low"],
                est["high"],
                f"{label} (n={bands[label].n_runs})",
                styles[label],
            )
        ax.set_xlabel(opts.xlabel)
        ax.set_ylim(-1, min(102.0, 1.1 * top))
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=8, loc="upper left")
    axes[0].set_ylabel("success rate (%)")
    wrapped_title(fig, f"{bench}: success averaged over tasks ({BAND_NOTE})")
    save_figure(fig, opts.out / f"success_{safe_name(bench)}.png", opts, written)


def plot_per_task(
    bench: str, bands: Mapping[str, CurveBand], task_names: Sequence[str], opts: PlotOptions, written: list[Path]
) -> None:
    """Success of every task, one panel per task, every algorithm but Fig. 7's ablations (those are in the success
    figure's second panel) with its confidence band over seeds."""
    fig, axes = panel_grid(len(task_names), PER_TASK_COLUMNS, 3.2, 2.6)
    styles = algorithm_styles(list(bands))
    shown = success_panels(list(bands))[0][1]
    for i, (ax, name) in enumerate(zip(axes, task_names, strict=True)):
        for label in shown:
            est = bands[label].estimates
            _band(
                ax, bands[label].x, est["task_mean"][i], est["task_low"][i], est["task_high"][i], label, styles[label]
            )
        ax.set_title(short_task_name(name), fontsize=9)
        ax.set_ylim(-2, 102)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    label_panels(axes, PER_TASK_COLUMNS, opts.xlabel, "success rate (%)")
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncol=min(len(labels), 6), fontsize=8)
    left_out = "; Fig. 7's ablations: success figure" if len(shown) < len(bands) else ""
    wrapped_title(fig, f"{bench}: success rate (%) per task vs {opts.xlabel} ({BAND_NOTE}{left_out})")
    save_figure(fig, opts.out / f"per_task_{safe_name(bench)}.png", opts, written)


def plot_profile(bench: str, scores: Mapping[str, np.ndarray], opts: PlotOptions, written: list[Path]) -> None:
    """Performance profile of the final success: share of runs x tasks above each tau, with its confidence band; the
    share holds from one tau to the next, so a drop is drawn as a step."""
    profiles, intervals = performance_profiles(scores, PROFILE_TAUS, opts.reps, opts.seed)
    fig = new_figure(6, 4.2)
    ax = fig.subplots()
    styles = algorithm_styles(list(scores))
    for label, profile in profiles.items():
        color, linestyle = styles[label]
        ax.plot(
            100 * PROFILE_TAUS,
            profile,
            color=color,
            linestyle=linestyle,
            drawstyle="steps-post",
            label=f"{label} (n={len(scores[label])})",
        )
        low, high = intervals[label]
        ax.fill_between(100 * PROFILE_TAUS, low, high, step="post", color=color, alpha=0.2)
    ax.set_xlabel("final success rate tau (%)")
    ax.set_ylabel("fraction of runs x tasks with success > tau")
    ax.set_xlim(0, 100)
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"{bench}: performance profile (band: 95% stratified-bootstrap CI)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, opts.out / f"profile_{safe_name(bench)}.png", opts, written)


__all__ = ["CurveBand", "curve_bands", "plot_per_task", "plot_profile", "plot_success", "task_curves"]
