"""Figures and Table 1 of the paper from a folder of runs.

Usage::

    sb3-mtte plot RUNS_DIR [--out RUNS_DIR] [--tasks reach pick-place] [--matrix-times 1e5 2.5e6 5e6]
                           [--freq-window-episodes 20] [--smooth 1] [--x per-task|total]

Run folders (their files: :mod:`sb3_mtte.experiments.runs`) are found anywhere under RUNS_DIR by their
``run_info.json``; the zoo writes them as ``RUNS_DIR/<algo>/<env>_<id>/`` (``sb3-mtte train ... -f RUNS_DIR``, or
``sb3-mtte sweep ... --out RUNS_DIR``). Runs are grouped by benchmark (the env id, so ``MT10`` and ``MT10-smoke``
stay apart) and by algorithm (``label`` of run_info: SAC-MT, Ours, ...); the runs of a group are its seeds.

Written to ``--out``: the figures of :mod:`sb3_mtte.experiments.figures` (heatmaps at ``--matrix-times``), and

- ``results_<b>.json`` (or ``<DIR>/<b>.json`` with ``--results-dir DIR``): one record per run that has a
  ``success.json``: algo, label, benchmark, seed, env_steps, episodes_per_task and success ``{mean, per_task}``;
- ``table1.md``: final success, mean +- std over seeds, per algorithm and benchmark (also printed). A run's final
  success is its ``success.json`` when present, else its last evaluation.

Success curves come from ``evaluations.npz``, else the ``eval/`` scalars, else the training episodes
(``rollout/``). Times are env steps per task (``--x total`` for steps over all tasks).
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

from sb3_mtte.experiments import command_prog
from sb3_mtte.experiments.figures import (
    PlotOptions,
    plot_bellman,
    plot_negative_transfer,
    plot_per_task,
    plot_success,
    safe_name,
)
from sb3_mtte.experiments.results import results_records, table1
from sb3_mtte.experiments.runs import Run, discover_runs, group_runs


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
            _write_results(bench, [run for by_seed in by_label.values() for run in by_seed], opts, written)
    table = table1(groups)
    (opts.out / "table1.md").write_text(table)
    written.append(opts.out / "table1.md")
    print(table)
    return written


def _write_results(bench: str, runs: list[Run], opts: PlotOptions, written: list[Path]) -> None:
    """The benchmark's results JSON (one record per evaluated run), when some run has a final evaluation."""
    records = results_records(runs)
    if not records:
        return
    results_dir = opts.results_dir or opts.out
    results_dir.mkdir(parents=True, exist_ok=True)
    name = f"{safe_name(bench)}.json" if opts.results_dir else f"results_{safe_name(bench)}.json"
    (results_dir / name).write_text(json.dumps(records, indent=1) + "\n")
    written.append(results_dir / name)


def main(argv: Sequence[str] | None = None) -> list[Path]:
    """``python -m sb3_mtte.plot RUNS_DIR [--out DIR] ...``"""
    parser = argparse.ArgumentParser(prog=command_prog("plot", "sb3_mtte.plot"), description=__doc__.split("\n\n")[0])
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
