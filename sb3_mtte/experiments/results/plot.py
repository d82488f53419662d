"""Figures and Table 1 of the paper from run folders and records.

Usage::

    sb3-mtte plot SOURCE [SOURCE ...] [--out DIR] [--reps 2000] [--seed 0] [--tasks reach pick-place]
                  [--matrix-times 1e5 2.5e6 5e6] [--freq-window-episodes 20] [--smooth 1] [--x per-task|total]

Each SOURCE is a folder searched for run folders (by their ``run_info.json``; the zoo writes them as
``<folder>/<algo>/<env>_<id>/``) and for records (``sb3-mtte record``: ``docs/records/<env id>/<algo>_seed<k>.json``),
so ``sb3-mtte plot docs/records --out docs/figures`` redraws the figures and tables from the repository alone. A
record of a run whose folder is also found is left out. Runs are grouped by benchmark (the env id, so ``MT10`` and
``MT10-smoke`` stay apart) and by algorithm (``label`` of run_info: SAC-MT, Ours, ...); the runs of a group are its
seeds.

Written to ``--out``, per benchmark ``<b>``:

- ``success_<b>.png``, ``per_task_<b>.png`` and ``profile_<b>.png``, every algorithm in each
  (:mod:`sb3_mtte.experiments.results.summary_figures`: means over seeds with 95% stratified-bootstrap bands);
- ``table1_<b>.md`` (also printed): per algorithm n (seeds), mean and IQM of the final success over runs x tasks and
  the probability of improvement of Ours (``mtsacte``) over it, each with its 95% stratified-bootstrap interval
  (rliable, ``--reps`` resamples drawn from ``--seed``); a run's final success is its final evaluation
  (``success.json``) when present, else its last evaluation; a run that did not finish (``finished: false`` in its
  ``run_info`` or record: crashed, stopped, killed, still training) is left out of every figure and table, and named
  in one line on stderr (``--include-unfinished`` draws it, counts its final or last evaluation and marks it
  ``unfinished`` in the tables);
- ``compare_<b>.md``, for a benchmark with a comparison fixed before its runs (MT10-100k: Ours against SAC-MT,
  :mod:`sb3_mtte.experiments.results.compare`): the comparison in full; its summary goes under Table 1;
- ``runs_<b>.md``: every run, seed by seed: its final and last in-training success, the tasks above 0 at the end and
  its package commit;
- ``bellman_<b>.md``, for runs that log the per-task critic loss: every run, seed by seed: between consecutive
  evaluations the task with the largest soft Bellman error and its mean, the peak, and the share of samples the
  clip of Eq. 16 dropped (:mod:`sb3_mtte.experiments.results.bellman_table`);
- ``results_<b>.json`` (or ``<DIR>/<b>.json`` with ``--results-dir DIR``): one entry per run with a final evaluation;
- the figures of :mod:`sb3_mtte.experiments.results.figures`: Bellman error (from run folders and from records that
  keep the training losses) and, from run folders only (they need the logs that records leave out), train frequency,
  mu and w, and transfer-matrix heatmaps at ``--matrix-times``, each titled with the time of the recomputation it draws,
  the nearest; a time past the log is skipped with a line naming the run whose log stops first.

Each benchmark gets a line on stdout as its drawing starts, and each file one as it is written.

Success curves come from ``evaluations.npz`` (a record's ``curve``), else the ``eval/`` scalars, else the training
episodes (``rollout/``). Times are env steps per task (``--x total`` for steps over all tasks).
"""

from __future__ import annotations

import json
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

from sb3_mtte.common.utils import short_task_name
from sb3_mtte.experiments.cli import CommandParser, command_prog, output_folder_error
from sb3_mtte.experiments.results.bellman_table import bellman_table
from sb3_mtte.experiments.results.compare import PREREGISTERED, comparison_report, comparison_summary
from sb3_mtte.experiments.results.figures import PlotOptions, plot_bellman, plot_negative_transfer, safe_name
from sb3_mtte.experiments.results.records import load_runs
from sb3_mtte.experiments.results.runs import Run, group_runs
from sb3_mtte.experiments.results.statistics import (
    DEFAULT_REPS,
    DEFAULT_SEED,
    has_final_evaluation,
    leave_out_unevaluated,
    leave_out_unfinished,
)
from sb3_mtte.experiments.results.summary_figures import curve_bands, plot_per_task, plot_profile, plot_success
from sb3_mtte.experiments.results.tables import (
    BenchmarkStatistics,
    benchmark_statistics,
    results_records,
    runs_table,
    table1,
)


class PlotInputError(ValueError):
    """Sources or options that name nothing to plot."""


def _check_tasks(runs: Sequence[Run], wanted: Sequence[str] | None) -> None:
    """Refuse a ``--tasks`` name that is no task (full or short name) of any run."""
    names = {n for run in runs for name in run.task_names for n in (name, short_task_name(name))}
    unknown = [task for task in wanted or [] if task not in names]
    if unknown:
        raise PlotInputError(
            f"--tasks {' '.join(unknown)}: no task of these runs; their tasks: "
            f"{' '.join(sorted({short_task_name(name) for run in runs for name in run.task_names}))}."
        )


class WrittenFiles(list):
    """The paths a plot has written, each named on stdout as it is written: a long plot shows its progress."""

    def append(self, path: Path) -> None:
        super().append(path)
        print(f"  wrote {path}", flush=True)


def make_plots(sources: Sequence[str | Path], opts: PlotOptions) -> list[Path]:
    """Write every figure and table for the runs and records under ``sources``; return the written paths."""
    runs = load_runs(sources)
    if not runs:
        raise PlotInputError(
            f"No run folder (run_info.json) or record under {', '.join(map(str, sources))}. Give the folder of the "
            "runs (train's -f) or docs/records."
        )
    _check_tasks(runs, opts.tasks)
    kept = leave_out_unfinished(runs, opts.include_unfinished)
    if not kept:
        raise PlotInputError(_nothing_finished(runs))
    leave_out_unevaluated(kept, scope="Table 1")  # named here; their curves are still drawn
    opts.out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = WrittenFiles()
    groups = sorted(group_runs(kept).items())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for k, (bench, by_label) in enumerate(groups, start=1):
            n_runs = sum(len(by_seed) for by_seed in by_label.values())
            runs_of = f"{n_runs} run{'s' * (n_runs != 1)} of {len(by_label)} algorithm{'s' * (len(by_label) != 1)}"
            print(f"{bench} ({k} of {len(groups)}): {runs_of}", flush=True)
            _plot_benchmark(bench, by_label, opts, written)
    return list(written)


def _nothing_finished(runs: Sequence[Run]) -> str:
    if any(has_final_evaluation(run) for run in runs):
        return (
            "every run stopped before its budget (each named above): resume them, or give --include-unfinished to "
            "draw them, marked unfinished"
        )
    return (
        "every run stopped before its budget without a final evaluation (each named above): evaluate them, or give "
        "--include-unfinished to draw them at their last evaluation"
    )


def _plot_benchmark(bench: str, by_label: dict[str, list[Run]], opts: PlotOptions, written: list[Path]) -> None:
    """Every figure and table of one benchmark."""
    bands = curve_bands(by_label, opts)
    plot_success(bench, bands, opts, written)
    plot_per_task(bench, bands, next(iter(by_label.values()))[0].task_names, opts, written)
    plot_bellman(bench, by_label, opts, written)
    bellman = bellman_table(bench, by_label)
    if bellman is not None:
        _write_table(f"bellman_{safe_name(bench)}.md", bellman, opts, written, echo=False)
    plot_negative_transfer(bench, by_label, opts, written)
    stats = benchmark_statistics(by_label, opts.reps, opts.seed)
    bench_runs = [run for by_seed in by_label.values() for run in by_seed]
    if stats.scores:
        plot_profile(bench, stats.scores, opts, written)
        _write_table1(bench, stats, bench_runs, opts, written)
        _write_table(f"runs_{safe_name(bench)}.md", runs_table(bench, by_label), opts, written, echo=False)
    _write_results(bench, bench_runs, opts, written)


def _write_table1(
    bench: str, stats: BenchmarkStatistics, runs: list[Run], opts: PlotOptions, written: list[Path]
) -> None:
    """Table 1, and for a benchmark with a comparison fixed before its runs, its summary under the table and the
    comparison in full (``compare_<b>.md``)."""
    table = table1(bench, stats, opts.reps, opts.seed)
    cmp = PREREGISTERED.get(bench)
    if cmp is not None and {cmp.a, cmp.b} <= set(stats.scores):
        _write_table(
            f"compare_{safe_name(bench)}.md", comparison_report(bench, runs, cmp, opts.reps), opts, written, False
        )
        table += "\n" + comparison_summary(bench, runs, cmp) + "\n"
    _write_table(f"table1_{safe_name(bench)}.md", table, opts, written)


def _write_table(name: str, table: str, opts: PlotOptions, written: list[Path], echo: bool = True) -> None:
    path = opts.out / name
    path.write_text(table)
    written.append(path)
    if echo:
        print(table)


def _write_results(bench: str, runs: list[Run], opts: PlotOptions, written: list[Path]) -> None:
    """The benchmark's results JSON (one record per evaluated run), when some run has a final evaluation."""
    records = results_records(runs)
    if not records:
        print(f"No results file for {bench}: none of its runs has a final evaluation (sb3-mtte evaluate writes one).")
        return
    results_dir = opts.results_dir or opts.out
    results_dir.mkdir(parents=True, exist_ok=True)
    name = f"{safe_name(bench)}.json" if opts.results_dir else f"results_{safe_name(bench)}.json"
    (results_dir / name).write_text(json.dumps(records, indent=1) + "\n")
    written.append(results_dir / name)


def main(argv: Sequence[str] | None = None) -> list[Path]:
    """``sb3-mtte plot SOURCE [SOURCE ...] [--out DIR] ...``"""
    parser = CommandParser(prog=command_prog("plot"), description=__doc__.split("\n\n")[0])
    parser.add_argument("sources", nargs="+", help="folders holding run folders (run_info.json) and/or records")
    parser.add_argument("--out", default=None, help="output folder (default: the first SOURCE, beside the runs)")
    parser.add_argument("--reps", type=int, default=DEFAULT_REPS, help=f"bootstrap resamples (default {DEFAULT_REPS})")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help=f"bootstrap seed (default {DEFAULT_SEED})")
    parser.add_argument("--x", choices=["per-task", "total"], default="per-task", help="time axis (default per-task)")
    parser.add_argument("--smooth", type=int, default=1, help="moving-average window in points (default 1: none)")
    parser.add_argument("--tasks", nargs="+", default=None, help="tasks of Figs. 3 and 5 (default: all)")
    parser.add_argument(
        "--matrix-times",
        nargs="+",
        type=float,
        default=None,
        help="times of the heatmaps (x units; each draws the nearest recomputation; default: first, middle, last)",
    )
    parser.add_argument("--freq-window-episodes", type=int, default=20, help="train-frequency window (episodes)")
    parser.add_argument("--dpi", type=int, default=120, help="resolution of the PNG figures (default 120)")
    parser.add_argument(
        "--include-unfinished",
        action="store_true",
        help="draw a run that did not finish (crashed, stopped, killed, still training), count its final or last "
        "evaluation and mark it in the tables (default: left out of every figure and table, named)",
    )
    parser.add_argument(
        "--results-dir",
        default=None,
        help="write each benchmark's final results as <DIR>/<env id>.json (default: results_<env id>.json in --out)",
    )
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    opts = PlotOptions(
        out=Path(args.sources[0] if args.out is None else args.out),
        x_per_task=args.x == "per-task",
        smooth=args.smooth,
        tasks=args.tasks,
        matrix_times=args.matrix_times,
        freq_window_episodes=args.freq_window_episodes,
        dpi=args.dpi,
        results_dir=None if args.results_dir is None else Path(args.results_dir),
        reps=args.reps,
        seed=args.seed,
        include_unfinished=args.include_unfinished,
    )
    if args.reps < 1:
        parser.error("--reps must be at least 1")
    counts = {"--dpi": args.dpi, "--smooth": args.smooth, "--freq-window-episodes": args.freq_window_episodes}
    for flag, value in counts.items():
        if value < 1:
            parser.error(f"{flag} {value}: give a positive int" + (" (1: no smoothing)" if flag == "--smooth" else ""))
    missing = [source for source in args.sources if not Path(source).is_dir()]
    problem = output_folder_error("--out", opts.out)
    if opts.results_dir is not None:
        problem = problem or output_folder_error("--results-dir", opts.results_dir)
    if missing:
        problem = f"{missing[0]}: no such folder; give folders of runs (train's -f) or records"
    if not 0 <= args.seed < 2**32:
        problem = f"--seed {args.seed}: the bootstrap seed is an int from 0 to 2**32 - 1, e.g. --seed 0"
    if problem:
        parser.exit(2, f"{parser.prog}: error: {problem}\n")
    try:
        written = make_plots(args.sources, opts)
    except PlotInputError as error:
        parser.exit(2, f"{parser.prog}: error: {error}\n")
    print(f"Wrote {len(written)} files to {opts.out}/")
    return written
