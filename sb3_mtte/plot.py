"""Figures and Table 1 of the paper from a folder of runs.

Usage::

    python -m sb3_mtte.plot RUNS_DIR [--out RUNS_DIR] [--tasks reach pick-place] [--matrix-times 1e5 2.5e6 5e6]
                            [--freq-window-episodes 20] [--smooth 1] [--x per-task|total]

Run folders are found anywhere under RUNS_DIR by their ``run_info.json``; the zoo writes them as
``RUNS_DIR/<algo>/<env>_<id>/`` (``python -m sb3_mtte.zoo train ... -f RUNS_DIR``, or ``python -m sb3_mtte.sweep
... --out RUNS_DIR``). Runs are grouped by benchmark (the env id, so ``MT10`` and ``MT10-smoke`` stay apart) and
by algorithm (``label`` of run_info: SAC-MT, Ours, ...); the runs of a group are its seeds. A run folder holds:

- ``run_info.json``: algorithm, env, seed, task names (required);
- ``evaluations.npz``: ``timesteps`` (T,), ``success_rate`` (T, N), ``task_names`` (periodic evaluations);
- ``progress.csv``: SB3's csv log (``eval/success/NN_task``, ``rollout/success/NN_task``,
  ``train/critic_loss/NN_task``, ``nt/mu/NN_task``, ...); tensorboard events are read instead when it is missing;
- ``negative_transfer.jsonl`` (MTSACTE): per recomputation ``timesteps``, ``mu``, ``selected``, ``weights``,
  ``transfer_matrix``;
- ``success.json`` (``python -m sb3_mtte.evaluate``): the final evaluation.

Written to ``--out`` (``<b>`` = benchmark, ``<a>`` = algorithm label):

- ``success_<b>.png`` (Fig. 4; Fig. 7 for the ablations): mean success over tasks, mean +- std over seeds;
- ``per_task_<b>.png`` (Figs. 8-9): success of every task, mean +- std over seeds;
- ``bellman_<b>_<a>.png`` (Fig. 3): per task, soft Bellman error (critic loss) and success;
- ``bellman_avg_<b>.png`` (Fig. 6): Bellman error and success averaged over tasks, one row per algorithm;
- ``train_frequency_<b>_<a>.png`` (Fig. 5): per task, the fraction of recomputations in which it was in C_s
  over a sliding window, and its success;
- ``nt_<b>_<a>.png``: mu, the task weights w and the task information in z (linear-probe accuracy) over time;
- ``nt_matrix_<b>_<a>.png``: the N x N matrix [k, i] = J_i(theta^k) - J_i(theta) at ``--matrix-times``;
- ``results_<b>.json`` (or ``<DIR>/<b>.json`` with ``--results-dir DIR``): one record per run that has a
  ``success.json``: algo, label, benchmark, seed, env_steps, episodes_per_task and success ``{mean, per_task}``;
- ``table1.md``: final success, mean +- std over seeds, per algorithm and benchmark (also printed). A run's final
  success is its ``success.json`` when present, else its last evaluation.

Success curves come from ``evaluations.npz``, else the ``eval/`` scalars, else the training episodes
(``rollout/``). Times are env steps per task (``--x total`` for steps over all tasks).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sb3_mtte.common.utils import short_task_name, task_log_key

TABLE1_ORDER = [
    "SAC-Ind",
    "SAC-MT",
    "SAC-MT-MH",
    "SAC-soft-modular",
    "SAC-MT-with-clip",
    "Ours",
    "Ours-VAE",
    "Ours-clip",
    "Ours-bestbatch",
]
"""Row order of Table 1 (then Fig. 7's ablations, then anything else, alphabetically)."""

PAPER_TABLE1 = {
    "SAC-Ind": {"MT10": 94.0, "MT20": 94.1},
    "SAC-MT": {"MT10": 74.3, "MT20": 56.2},
    "SAC-MT-MH": {"MT10": 76.9, "MT20": 65.3},
    "SAC-soft-modular": {"MT10": 83.3, "MT20": 65.0},
    "SAC-MT-with-clip": {"MT10": 85.9, "MT20": 65.5},
    "Ours": {"MT10": 89.3, "MT20": 70.1},
}
"""The paper's Table 1 (%, Meta-World v2)."""

ABLATIONS = ["Ours", "Ours-VAE", "Ours-clip", "Ours-bestbatch"]

Series = tuple[np.ndarray, np.ndarray]


# --------------------------------------------------------------------------------------------------------------
# Reading runs
# --------------------------------------------------------------------------------------------------------------
def read_progress_csv(path: Path) -> dict[str, Series]:
    """Scalars of an SB3 ``progress.csv``: tag -> (total timesteps, values), rows without the value dropped."""
    with open(path, newline="") as file:
        rows = list(csv.DictReader(file))
    if not rows:
        return {}

    def number(text: str | None) -> float:
        try:
            return float(text) if text not in (None, "") else math.nan
        except ValueError:
            return math.nan

    steps = np.array([number(row.get("time/total_timesteps")) for row in rows])
    scalars = {}
    for key in rows[0]:
        if key is None or key == "time/total_timesteps":
            continue
        values = np.array([number(row.get(key)) for row in rows])
        keep = np.isfinite(values) & np.isfinite(steps)
        if keep.any():
            scalars[key] = (steps[keep], values[keep])
    return scalars


def read_tensorboard(run_dir: Path) -> dict[str, Series]:
    """Scalars of the tensorboard events under ``run_dir``: tag -> (steps, values)."""
    from tensorboard.backend.event_processing import event_accumulator

    scalars: dict[str, Series] = {}
    folders = sorted({p.parent for p in run_dir.rglob("events.out.tfevents.*")})
    for folder in folders:
        accumulator = event_accumulator.EventAccumulator(str(folder), size_guidance={event_accumulator.SCALARS: 0})
        accumulator.Reload()
        for tag in accumulator.Tags().get("scalars", []):
            events = accumulator.Scalars(tag)
            steps = np.array([e.step for e in events], dtype=float)
            values = np.array([e.value for e in events], dtype=float)
            if tag in scalars:  # several event folders: keep the later folder's values at equal steps
                old_steps, old_values = scalars[tag]
                keep = ~np.isin(old_steps, steps)
                steps, values = np.concatenate([old_steps[keep], steps]), np.concatenate([old_values[keep], values])
            order = np.argsort(steps, kind="stable")
            scalars[tag] = (steps[order], values[order])
    return scalars


@dataclass
class Run:
    """One run folder."""

    path: Path
    info: dict[str, Any]
    evaluations: dict[str, np.ndarray] | None = None
    scalars: dict[str, Series] = field(default_factory=dict)
    nt_records: list[dict[str, Any]] = field(default_factory=list)
    final: dict[str, Any] | None = None

    @property
    def label(self) -> str:
        return str(self.info.get("label") or self.info.get("algo") or self.path.parent.name)

    @property
    def benchmark(self) -> str:
        return str(self.info.get("env_id") or self.info.get("benchmark") or "unknown")

    @property
    def seed(self) -> int | None:
        return self.info.get("seed")

    @property
    def task_names(self) -> list[str]:
        names = self.info.get("task_names")
        if not names and self.evaluations is not None:
            names = [str(n) for n in self.evaluations["task_names"]]
        return list(names or [])

    @property
    def n_tasks(self) -> int:
        return int(self.info.get("n_tasks") or len(self.task_names) or 1)

    def scalar(self, key: str) -> Series | None:
        return self.scalars.get(key)


def load_run(path: Path) -> Run:
    """Read a run folder (see the module docstring)."""
    info = json.loads((path / "run_info.json").read_text())
    run = Run(path, info)
    if (path / "evaluations.npz").is_file():
        with np.load(path / "evaluations.npz") as data:
            run.evaluations = {key: np.asarray(data[key]) for key in data.files}
    if (path / "progress.csv").is_file():
        run.scalars = read_progress_csv(path / "progress.csv")
    elif any(path.rglob("events.out.tfevents.*")):
        run.scalars = read_tensorboard(path)
    if (path / "negative_transfer.jsonl").is_file():
        for line in (path / "negative_transfer.jsonl").read_text().splitlines():
            try:
                run.nt_records.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    if (path / "success.json").is_file():
        run.final = json.loads((path / "success.json").read_text())
    return run


def discover_runs(runs_dir: str | Path) -> list[Run]:
    """Every run folder (one holding ``run_info.json``) under ``runs_dir``, sorted by path."""
    paths = sorted(p.parent for p in Path(runs_dir).rglob("run_info.json"))
    return [load_run(p) for p in paths]


def group_runs(runs: Sequence[Run]) -> dict[str, dict[str, list[Run]]]:
    """benchmark -> algorithm label -> runs (its seeds)."""
    groups: dict[str, dict[str, list[Run]]] = {}
    for run in runs:
        groups.setdefault(run.benchmark, {}).setdefault(run.label, []).append(run)
    return groups


def label_order(labels: Sequence[str]) -> list[str]:
    known = [label for label in TABLE1_ORDER if label in labels]
    return known + sorted(label for label in labels if label not in TABLE1_ORDER)


# --------------------------------------------------------------------------------------------------------------
# Curves
# --------------------------------------------------------------------------------------------------------------
def success_curve(run: Run, task: int | None = None) -> Series | None:
    """Success over time (mean over tasks, or of task ``task``): evaluations, else eval/ scalars, else rollout/."""
    if run.evaluations is not None and len(run.evaluations.get("timesteps", [])):
        rates = np.asarray(run.evaluations["success_rate"], dtype=float)
        values = rates.mean(axis=1) if task is None else rates[:, task]
        return np.asarray(run.evaluations["timesteps"], dtype=float), values
    for prefix in ("eval", "rollout"):
        if task is None:
            series = run.scalar(f"{prefix}/success_rate")
        else:
            series = run.scalar(task_log_key(f"{prefix}/success", task, run.task_names[task]))
        if series is not None:
            return series
    if task is None:  # mean of the per-task rollout curves
        curves = [success_curve(run, i) for i in range(run.n_tasks)]
        if all(c is not None for c in curves) and curves:
            return mean_std([c for c in curves if c is not None])[:2]
    return None


def task_scalar(run: Run, prefix: str, task: int) -> Series | None:
    return run.scalar(task_log_key(prefix, task, run.task_names[task] if task < len(run.task_names) else None))


def smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average over ``window`` points (1 = none)."""
    if window <= 1 or len(values) < 2:
        return values
    cumsum = np.cumsum(np.insert(np.asarray(values, dtype=float), 0, 0.0))
    out = np.empty(len(values))
    for j in range(len(values)):
        lo = max(0, j + 1 - window)
        out[j] = (cumsum[j + 1] - cumsum[lo]) / (j + 1 - lo)
    return out


def mean_std(curves: Sequence[Series]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and std over curves (seeds) on a common x grid (their shared range; interpolated where needed)."""
    curves = [(np.asarray(x, float), np.asarray(y, float)) for x, y in curves if len(x)]
    if not curves:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    if len(curves) == 1:
        x, y = curves[0]
        return x, y, np.zeros_like(y)
    lo, hi = max(x.min() for x, _ in curves), min(x.max() for x, _ in curves)
    grid = np.unique(np.concatenate([x[(x >= lo) & (x <= hi)] for x, _ in curves]))
    if len(grid) == 0:
        grid = curves[0][0]
    stacked = np.stack([np.interp(grid, x, y) for x, y in curves])
    return grid, stacked.mean(axis=0), stacked.std(axis=0)


# --------------------------------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------------------------------
@dataclass
class PlotOptions:
    out: Path
    x_per_task: bool = True
    smooth: int = 1
    tasks: list[str] | None = None
    matrix_times: list[float] | None = None
    freq_window_episodes: int = 20
    dpi: int = 120
    results_dir: Path | None = None


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _xscale(run: Run, opts: PlotOptions) -> float:
    return 1.0 / run.n_tasks if opts.x_per_task else 1.0


def _xlabel(opts: PlotOptions) -> str:
    return "environment steps per task" if opts.x_per_task else "environment steps (all tasks)"


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _band(ax, x, mean, std, label=None, color=None, style="-"):
    (line,) = ax.plot(x, mean, style, label=label, color=color)
    if np.any(std > 0):
        ax.fill_between(x, mean - std, mean + std, alpha=0.2, color=line.get_color())
    return line


def _selected_tasks(names: Sequence[str], wanted: Sequence[str] | None) -> list[int]:
    """Indices of the tasks named in ``wanted`` (full or short names, e.g. ``pick-place``); all when None."""
    if not wanted:
        return list(range(len(names)))
    chosen = []
    for want in wanted:
        for i, name in enumerate(names):
            if want in (name, short_task_name(name)) and i not in chosen:
                chosen.append(i)
    return chosen or list(range(len(names)))


def _panels(n: int, max_cols: int, width: float, height: float):
    """A figure with ``n`` panels in a grid of at most ``max_cols`` columns (unused cells hidden)."""
    cols = min(n, max_cols)
    rows = math.ceil(n / cols)
    fig, grid = _pyplot().subplots(rows, cols, figsize=(width * cols, height * rows), squeeze=False)
    axes = [grid[j // cols][j % cols] for j in range(rows * cols)]
    for ax in axes[n:]:
        ax.axis("off")
    return fig, axes[:n]


def _save(fig, path: Path, opts: PlotOptions, written: list[Path]) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=opts.dpi)
    _pyplot().close(fig)
    written.append(path)


def plot_success(bench: str, groups: dict[str, list[Run]], opts: PlotOptions, written: list[Path]) -> None:
    """Fig. 4 (and Fig. 7 when ablation runs are present): mean success, mean +- std over seeds."""
    plt = _pyplot()
    sets = [("success", [label for label in label_order(list(groups)) if label not in ABLATIONS[1:]])]
    if any(label in groups for label in ABLATIONS[1:]):
        sets.append(("ablation", [label for label in ABLATIONS if label in groups]))
    for name, labels in sets:
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for label in labels:
            curves = []
            for run in groups[label]:
                curve = success_curve(run)
                if curve is not None:
                    curves.append((curve[0] * _xscale(run, opts), smooth(curve[1], opts.smooth)))
            if curves:
                x, mean, std = mean_std(curves)
                _band(ax, x, 100 * mean, 100 * std, label=f"{label} (n={len(curves)})")
        ax.set_xlabel(_xlabel(opts))
        ax.set_ylabel("success rate (%)")
        ax.set_ylim(-2, 102)
        ax.set_title(f"{bench}: mean success over tasks" + (" (ablations)" if name == "ablation" else ""))
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=8)
        _save(fig, opts.out / f"{name}_{_safe(bench)}.png", opts, written)


def plot_per_task(bench: str, groups: dict[str, list[Run]], opts: PlotOptions, written: list[Path]) -> None:
    """Figs. 8-9: success of every task, one panel per task, mean +- std over seeds per algorithm."""
    plt = _pyplot()
    names = next(iter(groups.values()))[0].task_names
    fig, axes = _panels(len(names), 5, 3.2, 2.6)
    for i, (ax, name) in enumerate(zip(axes, names)):
        for label in label_order(list(groups)):
            curves = []
            for run in groups[label]:
                curve = success_curve(run, i) if i < run.n_tasks else None
                if curve is not None:
                    curves.append((curve[0] * _xscale(run, opts), smooth(curve[1], opts.smooth)))
            if curves:
                x, mean, std = mean_std(curves)
                _band(ax, x, 100 * mean, 100 * std, label=label)
        ax.set_title(short_task_name(name), fontsize=9)
        ax.set_ylim(-2, 102)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), fontsize=8)
    fig.suptitle(f"{bench}: success rate (%) per task vs {_xlabel(opts)}", fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))
    fig.savefig(opts.out / f"per_task_{_safe(bench)}.png", dpi=opts.dpi)
    plt.close(fig)
    written.append(opts.out / f"per_task_{_safe(bench)}.png")


def _twin_panel(ax, success: Series | None, other: Series | None, other_label: str, log: bool = False):
    """Success (left axis, blue) and another quantity (right axis, orange) on one panel."""
    if success is not None and len(success[0]):
        ax.plot(success[0], 100 * success[1], color="tab:blue", label="success")
    ax.set_ylim(-2, 102)
    ax.tick_params(axis="y", labelcolor="tab:blue", labelsize=7)
    ax.tick_params(axis="x", labelsize=7)
    twin = ax.twinx()
    if other is not None and len(other[0]):
        twin.plot(other[0], other[1], color="tab:orange", label=other_label)
        if log and np.all(other[1] > 0):
            twin.set_yscale("log")
    twin.tick_params(axis="y", labelcolor="tab:orange", labelsize=7)
    return twin


def _mean_series(runs: Sequence[Run], get, opts: PlotOptions, window: int = 1) -> Series | None:
    curves = []
    for run in runs:
        series = get(run)
        if series is not None and len(series[0]):
            curves.append((series[0] * _xscale(run, opts), smooth(series[1], window)))
    if not curves:
        return None
    x, mean, _ = mean_std(curves)
    return x, mean


def plot_bellman(bench: str, groups: dict[str, list[Run]], opts: PlotOptions, written: list[Path]) -> None:
    """Fig. 3 (per task, per algorithm) and Fig. 6 (task average, one row per algorithm)."""
    plt = _pyplot()
    with_loss = {
        label: runs
        for label, runs in groups.items()
        if any(task_scalar(r, "train/critic_loss", 0) is not None for r in runs)
    }
    for label in label_order(list(with_loss)):
        runs = with_loss[label]
        names = runs[0].task_names
        tasks = _selected_tasks(names, opts.tasks)
        fig, axes = _panels(len(tasks), 4, 3.6, 2.8)
        for ax, i in zip(axes, tasks):
            success = _mean_series(runs, lambda r, i=i: success_curve(r, i), opts, opts.smooth)
            loss = _mean_series(runs, lambda r, i=i: task_scalar(r, "train/critic_loss", i), opts, opts.smooth)
            _twin_panel(ax, success, loss, "soft Bellman error")
            ax.set_title(short_task_name(names[i]), fontsize=9)
        fig.suptitle(
            f"{bench}, {label}: success rate % (blue) and soft Bellman error J^Q (orange) vs {_xlabel(opts)}",
            fontsize=9,
        )
        _save(fig, opts.out / f"bellman_{_safe(bench)}_{_safe(label)}.png", opts, written)
    if not with_loss:
        return
    labels = label_order(list(with_loss))
    fig, axes = plt.subplots(len(labels), 1, figsize=(7, 2.8 * len(labels)), squeeze=False)
    for row, label in enumerate(labels):
        runs = with_loss[label]

        def mean_loss(run: Run) -> Series | None:
            series = [task_scalar(run, "train/critic_loss", i) for i in range(run.n_tasks)]
            series = [s for s in series if s is not None]
            return mean_std(series)[:2] if series else None

        success = _mean_series(runs, success_curve, opts, opts.smooth)
        loss = _mean_series(runs, mean_loss, opts, opts.smooth)
        _twin_panel(axes[row][0], success, loss, "soft Bellman error")
        axes[row][0].set_title(f"{label}: average over tasks", fontsize=9)
    axes[-1][0].set_xlabel(_xlabel(opts))
    fig.suptitle(f"{bench}: success rate % (blue) and average soft Bellman error (orange)", fontsize=9)
    _save(fig, opts.out / f"bellman_avg_{_safe(bench)}.png", opts, written)


def _nt_arrays(run: Run, key: str) -> tuple[np.ndarray, np.ndarray]:
    steps = np.array([record["timesteps"] for record in run.nt_records], dtype=float)
    values = np.array([record[key] for record in run.nt_records], dtype=float)
    return steps, values


def train_frequency(run: Run, window_steps: float) -> tuple[np.ndarray, np.ndarray]:
    """Fraction of the recomputations within the last ``window_steps`` (total env steps) in which each task was
    in C_s: ``(steps (R,), frequency (R, N))``."""
    steps, selected = _nt_arrays(run, "selected")
    freq = np.empty_like(selected)
    start = 0
    for j, t in enumerate(steps):
        while steps[start] <= t - window_steps:
            start += 1
        freq[j] = selected[start : j + 1].mean(axis=0)
    return steps, freq


def _episode_length(run: Run) -> int:
    length = run.info.get("episode_length")
    if length:
        return int(length)
    return 50 if str(run.info.get("benchmark", "")).startswith("toy") else 500


def plot_negative_transfer(bench: str, groups: dict[str, list[Run]], opts: PlotOptions, written: list[Path]) -> None:
    """Fig. 5 (train frequency vs success), mu and weights over time, and the transfer-matrix heatmaps."""
    plt = _pyplot()
    from matplotlib.colors import TwoSlopeNorm

    for label in label_order(list(groups)):
        runs = [r for r in groups[label] if r.nt_records]
        if not runs:
            continue
        names = runs[0].task_names
        n = runs[0].n_tasks
        tasks = _selected_tasks(names, opts.tasks)
        # Fig. 5
        fig, axes = _panels(len(tasks), 4, 3.6, 2.8)
        for ax, i in zip(axes, tasks):

            def frequency(run: Run, i: int = i) -> Series:
                window = opts.freq_window_episodes * _episode_length(run) * run.n_tasks
                steps, freq = train_frequency(run, window)
                return steps, freq[:, i]

            success = _mean_series(runs, lambda r, i=i: success_curve(r, i), opts, opts.smooth)
            twin = _twin_panel(ax, success, _mean_series(runs, frequency, opts), "train frequency")
            twin.set_ylim(-0.02, 1.02)
            ax.set_title(short_task_name(names[i]), fontsize=9)
        fig.suptitle(
            f"{bench}, {label}: success rate % (blue) and train frequency (orange, share of recomputations in C_s "
            f"over {opts.freq_window_episodes} episodes)",
            fontsize=9,
        )
        _save(fig, opts.out / f"train_frequency_{_safe(bench)}_{_safe(label)}.png", opts, written)
        # mu, w and the task information in z over time
        fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
        for key, ax, title in (
            ("mu", axes[0], "mu (negative-transfer count, Eq. 6)"),
            ("weights", axes[1], "w (Eq. 8)"),
        ):
            for i in range(n):
                series = _mean_series(runs, lambda r, i=i, key=key: _nt_series(r, key, i), opts, opts.smooth)
                if series is not None:
                    ax.plot(series[0], series[1], label=short_task_name(names[i]), lw=1)
            ax.set_ylabel(title)
            ax.grid(alpha=0.3)
        for key, style, name in (
            ("task_probe_accuracy", "-", "z ~ E_phi (what the policy sees)"),
            ("task_probe_accuracy_of_mean", ":", "mean of E_phi"),
        ):
            with_key = [r for r in runs if all(key in record for record in r.nt_records)]
            probe = _mean_series(with_key, lambda r, key=key: _nt_arrays(r, key), opts, opts.smooth)
            if probe is not None:
                axes[2].plot(probe[0], probe[1], color="k", ls=style, lw=1, label=name)
        axes[2].axhline(1.0 / n, color="gray", ls="--", lw=0.8, label="chance (1/N)")
        axes[2].set_ylim(-0.02, 1.02)
        axes[2].set_ylabel("linear probe of the task")
        axes[2].legend(fontsize=7, loc="lower right")
        axes[2].grid(alpha=0.3)
        axes[2].set_xlabel(_xlabel(opts))
        axes[0].legend(fontsize=7, ncol=max(1, math.ceil(n / 10)), loc="upper left", bbox_to_anchor=(1.0, 1.0))
        fig.suptitle(
            f"{bench}, {label}: negative-transfer measure, task weights and task information in z (mean over seeds)",
            fontsize=10,
        )
        _save(fig, opts.out / f"nt_{_safe(bench)}_{_safe(label)}.png", opts, written)
        # heatmaps
        times = _matrix_times(runs, opts)
        fig, axes = plt.subplots(1, len(times), figsize=(4.2 * len(times) + 0.8, 4.2), squeeze=False)
        for ax, t in zip(axes[0], times):
            matrices = []
            for run in runs:
                steps = np.array([r["timesteps"] for r in run.nt_records], float) * _xscale(run, opts)
                matrices.append(np.asarray(run.nt_records[int(np.argmin(np.abs(steps - t)))]["transfer_matrix"]))
            matrix = np.mean(matrices, axis=0)
            scale = float(np.max(np.abs(matrix))) or 1.0
            image = ax.imshow(matrix, cmap="RdBu", norm=TwoSlopeNorm(0.0, -scale, scale))
            ax.set_title(f"t = {t:,.0f}", fontsize=9)
            ax.set_xticks(range(n))
            ax.set_yticks(range(n))
            ax.set_xticklabels([str(i) for i in range(n)], fontsize=6)
            ax.set_yticklabels([str(i) for i in range(n)], fontsize=6)
            ax.set_xlabel("task i (affected)", fontsize=8)
            ax.set_ylabel("task k (virtual step)", fontsize=8)
            fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04)
        fig.suptitle(
            f"{bench}, {label}: J_i(theta^k) - J_i(theta) (red < 0: step on k hurts i); x = {_xlabel(opts)}",
            fontsize=9,
        )
        _save(fig, opts.out / f"nt_matrix_{_safe(bench)}_{_safe(label)}.png", opts, written)


def _nt_series(run: Run, key: str, task: int) -> Series:
    steps, values = _nt_arrays(run, key)
    return steps, values[:, task]


def _matrix_times(runs: Sequence[Run], opts: PlotOptions) -> list[float]:
    if opts.matrix_times:
        return list(opts.matrix_times)
    steps = np.array([r["timesteps"] for r in runs[0].nt_records], float) * _xscale(runs[0], opts)
    return sorted({float(steps[0]), float(steps[len(steps) // 2]), float(steps[-1])})


# --------------------------------------------------------------------------------------------------------------
# Table 1
# --------------------------------------------------------------------------------------------------------------
def final_success(run: Run) -> float | None:
    """Final mean success of a run: its ``success.json``, else its last evaluation, else its last success scalar."""
    if run.final is not None and "mean" in run.final:
        return float(run.final["mean"])
    curve = success_curve(run)
    if curve is None or not len(curve[1]):
        return None
    return float(curve[1][-1])


def results_records(runs: Sequence[Run]) -> list[dict[str, Any]]:
    """One record per run with a final evaluation (``success.json``): algo, label, benchmark, seed, env_steps and
    success ``{"mean": m, "per_task": {task: rate}}``, sorted by algorithm order and seed."""
    records = []
    for run in runs:
        if run.final is None or "per_task" not in run.final:
            continue
        records.append(
            {
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


def table1(groups: dict[str, dict[str, list[Run]]], with_paper: bool = True) -> str:
    """Markdown Table 1: final success (%) mean +- std over seeds, per algorithm (rows) and benchmark (columns)."""
    benches = sorted(groups)
    labels = label_order(sorted({label for by_label in groups.values() for label in by_label}))
    lines = [
        "| Algorithm | " + " | ".join(benches) + " |",
        "|:--|" + "--:|" * len(benches),
    ]
    for label in labels:
        cells = []
        for bench in benches:
            values = [v for v in (final_success(r) for r in groups[bench].get(label, [])) if v is not None]
            if not values:
                cells.append("-")
            else:
                cells.append(f"{100 * np.mean(values):.1f} ± {100 * np.std(values):.1f}% (n={len(values)})")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    text = (
        "Final success rate, mean ± std over seeds (n = number of seeds); a run's final success is its "
        "success.json (python -m sb3_mtte.evaluate) when present, else its last evaluation.\n\n" + "\n".join(lines)
    )
    shown = [b for b in ("MT10", "MT20") if any(b == bench.split("-")[0] for bench in benches)]
    if with_paper and shown:
        paper = ["| Algorithm | " + " | ".join(shown) + " |", "|:--|" + "--:|" * len(shown)]
        for label, values in PAPER_TABLE1.items():
            paper.append(f"| {label} | " + " | ".join(f"{values[b]:.1f}%" for b in shown) + " |")
        text += "\n\nThe paper's Table 1 (Meta-World v2, 5 seeds), for reference:\n\n" + "\n".join(paper)
    return text + "\n"


# --------------------------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------------------------
def make_plots(runs_dir: str | Path, opts: PlotOptions) -> list[Path]:
    """Write every figure and ``table1.md`` for the runs under ``runs_dir``; return the written paths."""
    runs = discover_runs(runs_dir)
    if not runs:
        raise FileNotFoundError(f"No run folder (run_info.json) under {runs_dir}.")
    opts.out.mkdir(parents=True, exist_ok=True)
    groups = group_runs(runs)
    written: list[Path] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for bench, by_label in sorted(groups.items()):
            plot_success(bench, by_label, opts, written)
            plot_per_task(bench, by_label, opts, written)
            plot_bellman(bench, by_label, opts, written)
            plot_negative_transfer(bench, by_label, opts, written)
            records = results_records([run for by_seed in by_label.values() for run in by_seed])
            if records:
                results_dir = opts.results_dir or opts.out
                results_dir.mkdir(parents=True, exist_ok=True)
                name = f"{_safe(bench)}.json" if opts.results_dir else f"results_{_safe(bench)}.json"
                (results_dir / name).write_text(json.dumps(records, indent=1) + "\n")
                written.append(results_dir / name)
    table = table1(groups)
    (opts.out / "table1.md").write_text(table)
    written.append(opts.out / "table1.md")
    print(table)
    return written


def main(argv: Sequence[str] | None = None) -> list[Path]:
    """``python -m sb3_mtte.plot RUNS_DIR [--out DIR] ...``"""
    parser = argparse.ArgumentParser(prog="python -m sb3_mtte.plot", description=__doc__.split("\n\n")[0])
    parser.add_argument("runs_dir", help="folder holding run folders (found by their run_info.json)")
    parser.add_argument("--out", default=None, help="output folder (default: RUNS_DIR itself, beside the runs)")
    parser.add_argument("--x", choices=["per-task", "total"], default="per-task", help="time axis (default per-task)")
    parser.add_argument("--smooth", type=int, default=1, help="moving-average window in points (default 1: none)")
    parser.add_argument("--tasks", nargs="+", default=None, help="tasks of Figs. 3 and 5 (default: all)")
    parser.add_argument(
        "--matrix-times", nargs="+", type=float, default=None, help="times of the heatmaps (x units; default 3)"
    )
    parser.add_argument("--freq-window-episodes", type=int, default=20, help="train-frequency window (episodes)")
    parser.add_argument("--dpi", type=int, default=120)
    parser.add_argument(
        "--results-dir",
        default=None,
        help="write each benchmark's final results as <DIR>/<env id>.json (default: results_<env id>.json in --out)",
    )
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    opts = PlotOptions(
        out=Path(args.runs_dir if args.out is None else args.out),
        x_per_task=args.x == "per-task",
        smooth=args.smooth,
        tasks=args.tasks,
        matrix_times=args.matrix_times,
        freq_window_episodes=args.freq_window_episodes,
        dpi=args.dpi,
        results_dir=None if args.results_dir is None else Path(args.results_dir),
    )
    written = make_plots(args.runs_dir, opts)
    print(f"Wrote {len(written)} files to {opts.out}/")
    return written


if __name__ == "__main__":
    from sb3_mtte.plot import main as _main  # the imported module, so that its objects pickle by reference

    _main()
