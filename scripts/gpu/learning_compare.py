"""GPU runs against CPU runs of the same algorithms and benchmark, as fixed before the GPU runs (docs/results.md):

- each GPU run's final success against the range of the CPU runs of its algorithm;
- the GPU mean minus the CPU mean: a 95% percentile bootstrap interval over runs (10,000 resamples, seed 0) and
  Welch's t;
- the in-training evaluations of every GPU run against the CPU runs' range at each evaluation;
- each GPU run's soft Bellman error against the runaway criterion (some task's window-mean critic loss above 100),
  and the count of runaway runs against the CPU runs' with Fisher's exact test.

    python scripts/gpu/learning_compare.py --cpu docs/records/MT10-100k --gpu docs/records/MT10-100k-gpu
        [--benchmark MT10-100k] [--out FILE]

Only runs with a final evaluation count. Needs the package's ``plots`` extra.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from itertools import pairwise
from math import comb
from pathlib import Path

import numpy as np
from scipy import stats

from sb3_mtte.experiments.results.bellman_table import evaluation_steps
from sb3_mtte.experiments.results.compare import DIFFERENCE_REPS, MeanDifference, mean_difference, runaway
from sb3_mtte.experiments.results.records import load_runs
from sb3_mtte.experiments.results.runs import GPU_SUFFIX, Run, group_runs, label_order, success_curve
from sb3_mtte.experiments.results.statistics import final_task_scores, has_final_evaluation

RUNAWAY_LOSS = 100.0
"""The criterion fixed for MT10-100k (docs/results.md)."""


def finished_runs(folder: str | Path, benchmark: str) -> dict[str, list[Run]]:
    """Label -> the runs of ``benchmark`` under ``folder`` with a final evaluation, by seed."""
    groups = group_runs(load_runs([folder])).get(benchmark, {})
    chosen = {label: [run for run in runs if has_final_evaluation(run)] for label, runs in groups.items()}
    return {label: sorted(runs, key=lambda run: run.seed or 0) for label, runs in chosen.items() if runs}


def final_means(runs: Sequence[Run]) -> np.ndarray:
    return np.array([float(np.mean(final_task_scores(run))) for run in runs])


def chance_all_inside(n_cpu: int, n_gpu: int) -> float:
    """The chance that all ``n_gpu`` runs fall inside the range of ``n_cpu`` runs when all come from one distribution
    (exchangeable, no ties): the smallest and the largest of the ``n_cpu + n_gpu`` must both be CPU runs."""
    return n_cpu * (n_cpu - 1) / ((n_cpu + n_gpu) * (n_cpu + n_gpu - 1))


def chance_all_beyond_one_side(n_cpu: int, n_gpu: int) -> float:
    """The chance that all ``n_gpu`` runs lie below the CPU minimum, or all above its maximum, under one
    distribution."""
    return 2 / comb(n_cpu + n_gpu, n_gpu)


def side(value: float, low: float, high: float) -> str:
    return "below" if value < low else "above" if value > high else "inside"


def difference_reading(diff: MeanDifference | None) -> str:
    """Fixed before the runs: shown only when the bootstrap interval excludes 0 and Welch's p is below 0.05."""
    if diff is None:
        return "too few runs for the difference"
    if (diff.low > 0 or diff.high < 0) and diff.p < 0.05:
        return f"the GPU mean is {'above' if diff.value > 0 else 'below'} the CPU mean"
    return "no difference shown"


def pct(value: float) -> str:
    return f"{100 * value:.1f}"


def final_section(label: str, cpu: list[Run], gpu: list[Run]) -> tuple[list[str], list[str]]:
    """The range table and the difference line of one algorithm; the flags they raise."""
    cpu_means, gpu_means = final_means(cpu), final_means(gpu)
    low, high = cpu_means.min(), cpu_means.max()
    sides = [side(value, low, high) for value in gpu_means]
    lines = [f"### {label}: final success", "", "| GPU run | Final (%) | CPU runs' range (%) | Where |"]
    lines.append("|--|--:|--:|--|")
    lines += [f"| seed {run.seed} | {pct(v)} | {pct(low)}-{pct(high)} ({len(cpu)} runs) | {where} |"
              for run, v, where in zip(gpu, gpu_means, sides, strict=True)]  # fmt: skip
    inside, beyond = chance_all_inside(len(cpu), len(gpu)), chance_all_beyond_one_side(len(cpu), len(gpu))
    lines += ["", f"Under one distribution all {len(gpu)} GPU runs fall inside the range with chance {inside:.3f}, "
              f"and all on one side beyond it with chance {beyond:.3f}."]  # fmt: skip
    flags = []
    if len(set(sides)) == 1 and sides[0] != "inside":
        flags.append(f"{label}: every GPU run's final success is {sides[0]} the CPU range")
    diff = mean_difference(gpu_means, cpu_means) if len(gpu) >= 2 and len(cpu) >= 2 else None
    reading = difference_reading(diff)
    if diff is not None:
        lines += ["", f"GPU minus CPU (n = {len(gpu)} and {len(cpu)}): {pct(gpu_means.mean())}% - "
                  f"{pct(cpu_means.mean())}% = {100 * diff.value:+.1f} points [{pct(diff.low)}, {pct(diff.high)}] "
                  f"({DIFFERENCE_REPS:,} resamples, seed 0); Welch t {diff.t:.2f} ({diff.df:.1f} df), "
                  f"p {diff.p:.3f}. Reading: {reading}."]  # fmt: skip
    if reading.startswith("the GPU mean"):
        flags.append(f"{label}: {reading}")
    return lines, flags


def curve_section(label: str, cpu: list[Run], gpu: list[Run]) -> tuple[list[str], list[str]]:
    """Mean success over tasks at each periodic evaluation: the CPU runs' mean and range, and every GPU run's."""
    curves = {id(run): success_curve(run) for run in [*cpu, *gpu]}
    steps = sorted({float(t) for run in cpu for t in curves[id(run)][0]})
    n_tasks = cpu[0].n_tasks
    header = " | ".join(f"GPU seed {run.seed}" for run in gpu)
    lines = [f"### {label}: in-training evaluations (mean success over tasks, %)", "",
             f"| Env steps per task | CPU mean | CPU range | {header} |", "|--:" * (3 + len(gpu)) + "|"]  # fmt: skip
    below = {id(run): [] for run in gpu}
    for step in steps:
        at = [v for run in cpu for t, v in zip(*curves[id(run)], strict=True) if float(t) == step]
        cells = [f"{step / n_tasks / 1000:g}k", pct(np.mean(at)), f"{pct(min(at))}-{pct(max(at))}"]
        for run in gpu:
            value = next((v for t, v in zip(*curves[id(run)], strict=True) if float(t) == step), None)
            cells.append("-" if value is None else f"{pct(value)}{'' if min(at) <= value <= max(at) else ' *'}")
            below[id(run)].append(value is not None and value < min(at))
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "\\* outside the CPU runs' range at that evaluation."]
    flags = [f"{label}: GPU seed {run.seed} below the CPU range at two evaluations in a row"
             for run in gpu if two_in_a_row(below[id(run)])]  # fmt: skip
    return lines, flags


def two_in_a_row(flags: Sequence[bool]) -> bool:
    return any(a and b for a, b in pairwise(flags))


def bellman_section(label: str, cpu: list[Run], gpu: list[Run]) -> tuple[list[str], list[str]]:
    """Each GPU run's largest window-mean critic loss against the criterion; runaway counts with Fisher's test."""
    edges = [list(grid) for grid in (evaluation_steps(run) for run in cpu) if grid is not None]
    if not edges:
        return [f"### {label}: soft Bellman error", "", "No per-task critic loss in the CPU runs."], []
    grid = max(edges, key=len)
    found = {id(run): runaway(run, grid, RUNAWAY_LOSS) for run in [*cpu, *gpu]}
    ran = {id(run): found[id(run)] is not None and found[id(run)].window is not None for run in [*cpu, *gpu]}
    cpu_count, gpu_count = sum(ran[id(run)] for run in cpu), sum(ran[id(run)] for run in gpu)
    cpu_peaks = [found[id(run)].peak for run in cpu if found[id(run)] is not None]
    lines = [f"### {label}: soft Bellman error", "", "| GPU run | Largest window mean | Task | Ran away (above 100) |",
             "|--|--:|--:|--|"]  # fmt: skip
    for run in gpu:
        hit = found[id(run)]
        if hit is None:
            lines.append(f"| seed {run.seed} | - | - | no critic loss recorded |")
            continue
        task = run.task_names[hit.task] if run.task_names else str(hit.task)
        window = f"yes, from window {hit.window + 1}" if hit.window is not None else "no"
        lines.append(f"| seed {run.seed} | {hit.peak:,.1f} | {task} | {window} |")
    _, p = stats.fisher_exact([[gpu_count, len(gpu) - gpu_count], [cpu_count, len(cpu) - cpu_count]])
    lines += ["", f"Ran away: GPU {gpu_count} of {len(gpu)}, CPU {cpu_count} of {len(cpu)} (Fisher's exact test, "
              f"two-sided, p {float(p):.3f}). The CPU runs' largest window means: {min(cpu_peaks):,.1f} to "
              f"{max(cpu_peaks):,.1f}."]  # fmt: skip
    flags = [f"{label}: {gpu_count} GPU run(s) ran away where no CPU run did"] if gpu_count and not cpu_count else []
    return lines, flags


def comparison_report(cpu_folder: str | Path, gpu_folder: str | Path, benchmark: str) -> str:
    """The markdown report of the comparison fixed before the GPU runs."""
    cpu = finished_runs(cpu_folder, benchmark)
    # records that name CUDA group as <benchmark>-gpu; older ones name no device
    gpu = finished_runs(gpu_folder, benchmark + GPU_SUFFIX) or finished_runs(gpu_folder, benchmark)
    labels = [label for label in label_order(list(gpu)) if label in cpu]
    if not labels:
        raise SystemExit(
            f"no algorithm with finished runs of {benchmark} in both {cpu_folder} ({', '.join(cpu) or 'none'}) and "
            f"{gpu_folder} ({', '.join(gpu) or 'none'})"
        )
    lines, flags = [f"## {benchmark}: GPU runs against CPU runs", ""], []
    for label in labels:
        for section in (final_section, curve_section, bellman_section):
            part, raised = section(label, cpu[label], gpu[label])
            lines += [*part, ""]
            flags += raised
    verdict = "no sign of drift" if not flags else "drift suspected: " + "; ".join(flags)
    return "\n".join([*lines, f"Reading fixed before the runs: {verdict}.", ""])


def main(argv: Sequence[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cpu", required=True, help="folder of the CPU runs' records (or run folders)")
    parser.add_argument("--gpu", required=True, help="folder of the GPU runs' records (or run folders)")
    parser.add_argument("--benchmark", default="MT10-100k", help="env id of the runs (default MT10-100k)")
    parser.add_argument("--out", help="also write the report to this markdown file")
    args = parser.parse_args(argv)
    missing = [folder for folder in (args.cpu, args.gpu) if not Path(folder).is_dir()]
    if missing:
        parser.error(f"{missing[0]} is not a folder: give folders of records, e.g. docs/records/MT10-100k")
    report = comparison_report(args.cpu, args.gpu, args.benchmark)
    if args.out:
        Path(args.out).write_text(report)
    sys.stdout.write(report)
    return report


if __name__ == "__main__":
    main()
