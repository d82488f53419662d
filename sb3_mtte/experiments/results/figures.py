"""Figures of the paper that need a run folder's logs (``<b>`` = benchmark, ``<a>`` = algorithm label), and where
every figure is saved. The success figures, drawn from records as well, are in
:mod:`sb3_mtte.experiments.results.summary_figures`; what the figures share (options, styles, panels) is in
:mod:`sb3_mtte.experiments.results.figure_layout`.

- ``bellman_<b>_<a>.png`` (Fig. 3): per task, soft Bellman error (critic loss) and success;
- ``bellman_avg_<b>.png`` (Fig. 6): Bellman error and success averaged over tasks, one row per algorithm, with the
  share of samples the clip of Eq. 16 dropped where it was on;
- ``train_frequency_<b>_<a>.png`` (Fig. 5): per task, the fraction of recomputations in which it was in C_s
  over a sliding window, and its success;
- ``nt_<b>_<a>.png``: mu, the task weights w and the task information in z (linear-probe accuracy) over time;
- ``nt_matrix_<b>_<a>.png``: the N x N matrix [k, i] = J_i(theta^k) - J_i(theta) at chosen times.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import TwoSlopeNorm
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, MaxNLocator

from sb3_mtte.common.utils import short_task_name
from sb3_mtte.experiments.results.figure_layout import (
    PlotOptions,
    algorithm_styles,
    label_panels,
    new_figure,
    panel_grid,
    point_marker,
    safe_name,
    seeds_text,
    selected_tasks,
    wrapped_title,
)
from sb3_mtte.experiments.results.runs import (
    Run,
    Series,
    episode_length,
    label_order,
    mean_std,
    nt_arrays,
    nt_series,
    smooth,
    success_curve,
    task_scalar,
    train_frequency,
)
from sb3_mtte.mtsac.task_logs import CLIP_FRACTION_KEY, CRITIC_LOSS_KEY

Groups = dict[str, list[Run]]
"""Algorithm label -> runs (its seeds), for one benchmark."""


def _steps_label(x: float, _position: int | None = None) -> str:
    """Tick label of an env-step count: ``20k``, ``1.5M``."""
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(x) >= scale:
            return f"{x / scale:g}{suffix}"
    return f"{x:g}"


def save_figure(fig: Figure, path: Path, opts: PlotOptions, written: list[Path]) -> None:
    for ax in fig.axes:
        if not ax.images and getattr(ax, "_colorbar", None) is None:  # time axes, not the heatmaps or colorbars
            ax.xaxis.set_major_locator(MaxNLocator(5))
            ax.xaxis.set_major_formatter(FuncFormatter(_steps_label))
    fig.savefig(path, dpi=opts.dpi)
    written.append(path)


def _mean_series(
    runs: Sequence[Run], get: Callable[[Run], Series | None], opts: PlotOptions, smoothed: bool = True
) -> Series | None:
    """Mean over runs (seeds) of a series of each run, in x units (and smoothed over ``opts.smooth`` points)."""
    curves = []
    for run in runs:
        series = get(run)
        if series is not None and len(series[0]):
            values = smooth(series[1], opts.smooth) if smoothed else series[1]
            curves.append((series[0] * opts.xscale(run), values))
    if not curves:
        return None
    x, mean, _ = mean_std(curves)
    return x, mean


def _twin_panel(ax: Axes, success: Series | None, other: Series | None, other_label: str) -> Axes:
    """Success (left axis, blue) and another quantity (right axis, orange) on one panel."""
    if success is not None and len(success[0]):
        ax.plot(success[0], 100 * success[1], color="tab:blue", marker=point_marker(success[0]), label="success")
    ax.set_ylim(-2, 102)
    ax.tick_params(axis="y", labelcolor="tab:blue", labelsize=7)
    ax.tick_params(axis="x", labelsize=7)
    twin = ax.twinx()
    if other is not None and len(other[0]):
        twin.plot(other[0], other[1], color="tab:orange", marker=point_marker(other[0]), label=other_label)
    twin.tick_params(axis="y", labelcolor="tab:orange", labelsize=7)
    return twin


def _mean_critic_loss(run: Run) -> Series | None:
    series = [task_scalar(run, CRITIC_LOSS_KEY, i) for i in range(run.n_tasks)]
    series = [s for s in series if s is not None]
    return mean_std(series)[:2] if series else None


def _clip_note(runs: Sequence[Run]) -> str:
    """The share of samples the clip of Eq. 16 dropped, over every logging window of ``runs`` ('' without it)."""
    series = [run.scalar(CLIP_FRACTION_KEY) for run in runs]
    values = np.concatenate([values for _, values in filter(None, series)] or [np.empty(0)])
    if values.size == 0:
        return ""
    return f"; samples the clip dropped per logging window: mean {values.mean():.2%}, max {values.max():.2%}"


def plot_bellman(bench: str, groups: Groups, opts: PlotOptions, written: list[Path]) -> None:
    """Fig. 3 (per task, per algorithm) and Fig. 6 (task average, one row per algorithm)."""
    with_loss = {
        label: runs
        for label, runs in groups.items()
        if any(task_scalar(r, CRITIC_LOSS_KEY, 0) is not None for r in runs)
    }
    for label in label_order(list(with_loss)):
        runs = with_loss[label]
        names = runs[0].task_names
        fig, axes = panel_grid(len(selected_tasks(names, opts.tasks)), 4, 3.6, 2.8)
        twins = []
        for ax, i in zip(axes, selected_tasks(names, opts.tasks), strict=True):
            success = _mean_series(runs, lambda r, i=i: success_curve(r, i), opts)
            loss = _mean_series(runs, lambda r, i=i: task_scalar(r, CRITIC_LOSS_KEY, i), opts)
            twins.append(_twin_panel(ax, success, loss, "soft Bellman error"))
            ax.set_title(short_task_name(names[i]), fontsize=9)
        label_panels(axes, 4, opts.xlabel, "success rate (%)", twins, "soft Bellman error J^Q")
        wrapped_title(
            fig, f"{bench}, {label}: success rate % (blue) and soft Bellman error J^Q (orange) vs {opts.xlabel}"
        )
        save_figure(fig, opts.out / f"bellman_{safe_name(bench)}_{safe_name(label)}.png", opts, written)
    if not with_loss:
        return
    labels = label_order(list(with_loss))
    fig = new_figure(7, 2.8 * len(labels) + 0.6)
    axes = fig.subplots(len(labels), 1, squeeze=False)[:, 0]
    for ax, label in zip(axes, labels, strict=True):
        success = _mean_series(with_loss[label], success_curve, opts)
        twin = _twin_panel(ax, success, _mean_series(with_loss[label], _mean_critic_loss, opts), "soft Bellman error")
        ax.set_ylabel("success rate (%)", color="tab:blue", fontsize=8)
        twin.set_ylabel("soft Bellman error", color="tab:orange", fontsize=8)
        ax.set_title(f"{label}: average over tasks{_clip_note(with_loss[label])}", fontsize=9)
    axes[-1].set_xlabel(opts.xlabel)
    wrapped_title(fig, f"{bench}: success rate % (blue) and average soft Bellman error (orange)")
    save_figure(fig, opts.out / f"bellman_avg_{safe_name(bench)}.png", opts, written)


def plot_negative_transfer(bench: str, groups: Groups, opts: PlotOptions, written: list[Path]) -> None:
    """Fig. 5 (train frequency vs success), mu and weights over time, and the transfer-matrix heatmaps."""
    for label in label_order(list(groups)):
        runs = [r for r in groups[label] if r.nt_records]
        if not runs:
            continue
        name = f"{safe_name(bench)}_{safe_name(label)}.png"
        title = f"{bench}, {label}"
        save_figure(_train_frequency_figure(title, runs, opts), opts.out / f"train_frequency_{name}", opts, written)
        save_figure(_nt_over_time_figure(title, runs, opts), opts.out / f"nt_{name}", opts, written)
        heatmaps = _drawn_matrices(runs, opts, f"nt_matrix_{name}")
        if heatmaps:
            save_figure(
                _transfer_matrix_figure(title, runs, heatmaps, opts), opts.out / f"nt_matrix_{name}", opts, written
            )


def _train_frequency_figure(title: str, runs: Sequence[Run], opts: PlotOptions) -> Figure:
    """Fig. 5: per task, success and the share of recomputations in which the task was in C_s."""
    names = runs[0].task_names
    tasks = selected_tasks(names, opts.tasks)
    fig, axes = panel_grid(len(tasks), 4, 3.6, 2.8)
    twins = []
    for ax, i in zip(axes, tasks, strict=True):

        def frequency(run: Run, i: int = i) -> Series:
            window = opts.freq_window_episodes * episode_length(run) * run.n_tasks
            steps, freq = train_frequency(run, window)
            return steps, freq[:, i]

        success = _mean_series(runs, lambda r, i=i: success_curve(r, i), opts)
        twins.append(_twin_panel(ax, success, _mean_series(runs, frequency, opts, smoothed=False), "train frequency"))
        twins[-1].set_ylim(-0.02, 1.02)
        ax.set_title(short_task_name(names[i]), fontsize=9)
    label_panels(axes, 4, opts.xlabel, "success rate (%)", twins, "train frequency")
    wrapped_title(
        fig,
        f"{title}: success rate % (blue) and train frequency (orange, share of recomputations in C_s over "
        f"{opts.freq_window_episodes} episodes) vs {opts.xlabel}",
    )
    return fig


def _nt_over_time_figure(title: str, runs: Sequence[Run], opts: PlotOptions) -> Figure:
    """mu and w per task, and the task information in z (linear probe), over time."""
    names, n = runs[0].task_names, runs[0].n_tasks
    fig = new_figure(9, 8)
    axes = fig.subplots(3, 1, sharex=True)
    for key, ax, ylabel in (("mu", axes[0], "mu (negative-transfer count, Eq. 6)"), ("weights", axes[1], "w (Eq. 8)")):
        for i in range(n):
            series = _mean_series(runs, lambda r, i=i, key=key: nt_series(r, key, i), opts)
            if series is not None:
                ax.plot(series[0], series[1], label=short_task_name(names[i]), lw=1)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    for key, style, name in (
        ("task_probe_accuracy", "-", "z ~ E_phi (what the policy sees)"),
        ("task_probe_accuracy_of_mean", ":", "mean of E_phi"),
    ):
        with_key = [r for r in runs if all(key in record for record in r.nt_records)]
        probe = _mean_series(with_key, lambda r, key=key: nt_arrays(r, key), opts)
        if probe is not None:
            axes[2].plot(probe[0], probe[1], color="k", ls=style, lw=1, label=name)
    axes[2].axhline(1.0 / n, color="gray", ls="--", lw=0.8, label="chance (1/N)")
    axes[2].set_ylim(-0.02, 1.02)
    axes[2].set_ylabel("linear probe of the task")
    axes[2].legend(fontsize=7, loc="center right")
    axes[2].grid(alpha=0.3)
    axes[2].set_xlabel(opts.xlabel)
    axes[0].legend(fontsize=7, ncol=max(1, math.ceil(n / 10)), loc="upper left", bbox_to_anchor=(1.0, 1.0))
    wrapped_title(fig, f"{title}: negative-transfer measure, task weights and task information in z (mean over seeds)")
    return fig


def _recomputation_times(run: Run, opts: PlotOptions) -> np.ndarray:
    return np.array([r["timesteps"] for r in run.nt_records], float) * opts.xscale(run)


def _drawn_matrices(runs: Sequence[Run], opts: PlotOptions, name: str) -> dict[str, list[int]]:
    """Title (the time drawn) -> the recomputation of each run that the heatmap averages: the one nearest to each
    matrix time. A time more than one recomputation interval past a run's last recomputation is skipped with a line
    naming the time and that run; times that draw the same recomputations give one heatmap."""
    times = [_recomputation_times(run, opts) for run in runs]
    reaches = [float(steps[-1] + _interval(steps)) for steps in times]
    shortest = int(np.argmin(reaches))
    drawn: dict[str, list[int]] = {}
    for t in _matrix_times(runs, opts):
        if t > reaches[shortest]:
            print(
                f"{name}: t = {t:,.0f} is past the last recomputation of {runs[shortest].path} (seed "
                f"{runs[shortest].seed}, t = {times[shortest][-1]:,.0f}): skipped",
                file=sys.stderr,
            )
            continue
        picks = [int(np.argmin(np.abs(steps - t))) for steps in times]
        drawn.setdefault(_time_title([steps[j] for steps, j in zip(times, picks, strict=True)]), picks)
    return drawn


def _interval(steps: np.ndarray) -> float:
    """The usual interval between recomputations (0 with a single one)."""
    return float(np.median(np.diff(steps))) if len(steps) > 1 else 0.0


def _time_title(times: Sequence[float]) -> str:
    low, high = min(times), max(times)
    return f"t = {low:,.0f}" if low == high else f"t = {low:,.0f} to {high:,.0f}"


def _transfer_matrix_figure(
    title: str, runs: Sequence[Run], heatmaps: dict[str, list[int]], opts: PlotOptions
) -> Figure:
    """Heatmaps of the N x N matrix J_i(theta^k) - J_i(theta) (mean over seeds) at the recomputations drawn."""
    names = [short_task_name(name) for name in runs[0].task_names]
    side = 3.2 + 0.25 * len(names)
    fig = new_figure(side * len(heatmaps) + 0.8, side)
    for ax, (time, picks) in zip(fig.subplots(1, len(heatmaps), squeeze=False)[0], heatmaps.items(), strict=True):
        matrices = [np.asarray(run.nt_records[j]["transfer_matrix"]) for run, j in zip(runs, picks, strict=True)]
        matrix = np.mean(matrices, axis=0)
        scale = float(np.max(np.abs(matrix))) or 1.0
        image = ax.imshow(matrix, cmap="RdBu", norm=TwoSlopeNorm(0.0, -scale, scale))
        ax.set_title(time, fontsize=9)
        ax.set_xticks(range(len(names)), names, fontsize=7, rotation=90)
        ax.set_yticks(range(len(names)), names, fontsize=7)
        ax.set_xlabel("task i (affected)", fontsize=8)
        ax.set_ylabel("task k (virtual step)", fontsize=8)
        fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04).ax.tick_params(labelsize=7)
    wrapped_title(
        fig,
        f"{title}, {seeds_text(runs)}: J_i(theta^k) - J_i(theta) (red < 0: a step on k hurts i); t in {opts.xlabel}",
        9,
    )
    return fig


def _matrix_times(runs: Sequence[Run], opts: PlotOptions) -> list[float]:
    if opts.matrix_times:
        return list(opts.matrix_times)
    steps = _recomputation_times(runs[0], opts)
    return sorted({float(steps[0]), float(steps[len(steps) // 2]), float(steps[-1])})


__all__ = [
    "PlotOptions",
    "algorithm_styles",
    "new_figure",
    "panel_grid",
    "plot_bellman",
    "plot_negative_transfer",
    "safe_name",
    "save_figure",
    "wrapped_title",
]
