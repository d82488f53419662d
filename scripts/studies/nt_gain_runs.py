"""What E_phi's initial mean head (``z_mean_init_gain``) does to the negative-transfer measure, read from MTSACTE run
folders and grouped by benchmark and gain.

Each line of a run's ``negative_transfer.jsonl`` holds one iteration's last recomputation: the transfer matrix T
(entry [k, i] = J_i(theta^k) - J_i(theta), Eq. 5), mu (Eq. 6), C_s (Eq. 7) and w (Eq. 8), written after its
J^rep steps. Per run:

- ``harmful_fraction``: the share of off-diagonal entries of T below zero (the pairs mu counts), over the run and
  over its first quarter;
- ``coupling``: mean |T[k, i]| over k != i divided by mean |T[k, k]|, the median over iterations (how far a virtual
  step on task k moves the other tasks' objectives next to its own; 0: the tasks are decoupled);
- ``mu_consecutive_correlation`` and ``weights_consecutive_correlation``: Pearson's r of consecutive iterations' mu
  and w, the mean over pairs where neither is constant (near 1: the same tasks are found harmful from one iteration
  to the next; near 0: a new draw each time);
- ``weights_distance``: total variation distance of w from uniform (0: uniform, at most 1 - 1/N), run and first
  quarter;
- per task: mean mu, share of iterations in C_s, mean w; the task with the largest mean mu;
- with ``--conflicting``: that task's share of iterations with the strictly largest mu, and the mean of its row of T
  off the diagonal over mean |T[k, k]| (below 0: its step lowers the other tasks' objectives on average);
- final success (``success.json``, else the last evaluation) and the mean task probe of sampled z.

Runs still training (or stopped before their budget) are skipped, with a line naming them, unless ``--running``.
Summaries are [mean, std] over seeds; ``most_harmful_agree`` counts the seeds whose most harmful task on average is
the group's most common one.

    python scripts/studies/nt_gain_runs.py runs/dev6_gain1 runs/dev6_gain50 runs/toy_gain1 \
        runs/toy_gain50 --conflicting toy-conflict=3 --out docs/results/nt_gain_runs.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from sb3_mtte.experiments.results.metrics import distance_from_uniform, harmful_fraction, transfer_coupling
from sb3_mtte.experiments.results.runs import Run, discover_runs, nt_arrays
from sb3_mtte.experiments.results.statistics import final_task_scores, unfinished


DEFAULT_GAIN = 50.0  # MTSACTEPolicy's z_mean_init_gain


def run_gain(run: Run) -> float:
    """``z_mean_init_gain`` of the run's policy_kwargs; the class default (50) when they do not set it."""
    kwargs = run.info.get("hyperparams", {}).get("policy_kwargs", "")
    if isinstance(kwargs, dict):
        return float(kwargs.get("z_mean_init_gain", DEFAULT_GAIN))
    found = re.search(r"z_mean_init_gain\W*([0-9.eE+-]+)", str(kwargs))
    return float(found.group(1)) if found else DEFAULT_GAIN


def mean_consecutive_correlation(rows: np.ndarray) -> float:
    """Mean Pearson's r of consecutive rows, over the pairs where neither row is constant (to 1e-9; nan when none)."""
    pairs = [np.corrcoef(a, b)[0, 1] for a, b in itertools.pairwise(rows) if np.ptp(a) > 1e-9 and np.ptp(b) > 1e-9]
    return float(np.mean(pairs)) if pairs else float("nan")


def strictly_largest(mu: np.ndarray, task: int = -1) -> np.ndarray:
    """Per row of ``mu`` ``(..., tasks)``: whether task ``task``'s value is strictly the largest (default: the last)."""
    return mu[..., task] > np.delete(mu, task, axis=-1).max(axis=-1)


def run_summary(run: Run, conflicting: int | None) -> dict[str, Any]:
    matrices = nt_arrays(run, "transfer_matrix")[1]
    mu = nt_arrays(run, "mu")[1]
    weights = nt_arrays(run, "weights")[1]
    selected = nt_arrays(run, "selected")[1]
    quarter = max(1, len(mu) // 4)
    harmful = harmful_fraction(matrices)
    coupling = transfer_coupling(matrices)
    distance = distance_from_uniform(weights)
    probes = [r["task_probe_accuracy"] for r in run.nt_records if r.get("task_probe_accuracy") is not None]
    scores = final_task_scores(run)
    summary: dict[str, Any] = {
        "path": str(run.path),
        "seed": run.seed,
        "iterations": len(mu),
        "harmful_fraction": float(harmful.mean()),
        "harmful_fraction_first_quarter": float(harmful[:quarter].mean()),
        "coupling": float(np.median(coupling)),
        "coupling_first_quarter": float(np.median(coupling[:quarter])),
        "mu_consecutive_correlation": mean_consecutive_correlation(mu),
        "weights_consecutive_correlation": mean_consecutive_correlation(weights),
        "weights_distance": float(distance.mean()),
        "weights_distance_first_quarter": float(distance[:quarter].mean()),
        "mean_mu": mu.mean(axis=0).round(4).tolist(),
        "selected_fraction": selected.mean(axis=0).round(4).tolist(),
        "mean_weights": weights.mean(axis=0).round(5).tolist(),
        "most_harmful_task": int(np.argmax(mu.mean(axis=0))),
        "probe_of_sampled_z": float(np.mean(probes)) if probes else None,
        "final_success": None if scores is None else float(scores.mean()),
        "final_success_per_task": None if scores is None else scores.round(4).tolist(),
    }
    if conflicting is not None:
        summary["conflicting_strictly_largest"] = float(strictly_largest(mu, conflicting).mean())
        diagonal = np.abs(np.diagonal(matrices, axis1=1, axis2=2)).mean(axis=1)
        row = np.delete(matrices[:, conflicting], conflicting, axis=-1).mean(axis=1)
        summary["conflicting_row_mean"] = float(np.median(row / diagonal))
    return summary


SUMMARISED = (
    "harmful_fraction",
    "harmful_fraction_first_quarter",
    "coupling",
    "coupling_first_quarter",
    "mu_consecutive_correlation",
    "weights_consecutive_correlation",
    "weights_distance",
    "weights_distance_first_quarter",
    "probe_of_sampled_z",
    "final_success",
    "conflicting_strictly_largest",
    "conflicting_row_mean",
)


def group_summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    summary: dict[str, Any] = {}
    for key in SUMMARISED:
        values = [r[key] for r in runs if r.get(key) is not None and not np.isnan(r[key])]
        if values:
            summary[key] = [float(np.mean(values)), float(np.std(values))]
    common, count = Counter(r["most_harmful_task"] for r in runs).most_common(1)[0]
    summary["most_harmful_task"] = common
    summary["most_harmful_agree"] = count
    summary["seeds"] = sorted(r["seed"] for r in runs)
    return summary


def study(sources: list[Path], conflicting: dict[str, int], running: bool = False) -> dict[str, Any]:
    groups: dict[str, list[dict[str, Any]]] = {}
    task_names: dict[str, list[str]] = {}
    for source in sources:
        for run in discover_runs(source):
            if not run.nt_records or (unfinished(run) and not running):
                print(f"skipped {run.path}: no negative_transfer.jsonl or still training", file=sys.stderr)
                continue
            bench = str(run.info.get("env_id", run.benchmark))
            base = bench.split("-cpu")[0]
            key = f"{bench}, gain {run_gain(run):g}"
            groups.setdefault(key, []).append(run_summary(run, conflicting.get(base, conflicting.get(bench))))
            task_names[bench] = run.task_names
    return {
        "summary": {key: group_summary(runs) for key, runs in sorted(groups.items())},
        "task_names": task_names,
        "runs": groups,
        "summary_format": "[mean, std] over seeds; most_harmful_agree counts seeds",
    }


TABLE_COLUMNS = (
    ("harmful_fraction", "off-diagonal entries of T below 0: run", "{:.0%}"),
    ("harmful_fraction_first_quarter", "first quarter", "{:.0%}"),
    ("coupling", "coupling: run", "{:.3f}"),
    ("coupling_first_quarter", "first quarter", "{:.3f}"),
    ("mu_consecutive_correlation", "r of consecutive mu", "{:+.2f}"),
    ("weights_distance", "w from uniform", "{:.2f}"),
    ("probe_of_sampled_z", "probe of sampled z", "{:.2f}"),
    ("final_success", "final success", "{:.1%}"),
)


def markdown_table(summary: dict[str, dict[str, Any]]) -> str:
    """One row per group: mean ± std over seeds of the TABLE_COLUMNS."""
    lines = [
        "| benchmark, gain | seeds | " + " | ".join(title for _, title, _ in TABLE_COLUMNS) + " |",
        "|---|---|" + "--:|" * len(TABLE_COLUMNS),
    ]
    for group, values in summary.items():
        cells = []
        for key, _, form in TABLE_COLUMNS:
            mean, std = values.get(key, (float("nan"), float("nan")))
            cells.append(form.format(mean) + (" ± " + form.format(std).lstrip("+") if len(values["seeds"]) > 1 else ""))
        seeds = ", ".join(map(str, values["seeds"]))
        lines.append(f"| {group} | {seeds} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def parse_conflicting(items: list[str]) -> dict[str, int]:
    pairs = {}
    for item in items:
        bench, _, index = item.partition("=")
        if not index.isdigit():
            raise SystemExit(f"--conflicting takes BENCHMARK=TASK_INDEX (e.g. toy-conflict=3), got {item!r}.")
        pairs[bench] = int(index)
    return pairs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sources", nargs="+", type=Path, help="folders holding MTSACTE run folders")
    parser.add_argument("--conflicting", nargs="*", default=[], help="BENCHMARK=TASK_INDEX of a known conflict")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    parser.add_argument("--running", action="store_true", help="also read runs still training")
    parser.add_argument("--markdown", action="store_true", help="print the summary as a markdown table")
    args = parser.parse_args()
    result = study(args.sources, parse_conflicting(args.conflicting), args.running)
    result["command"] = "python scripts/studies/nt_gain_runs.py " + " ".join(
        [*map(str, args.sources), *(["--conflicting", *args.conflicting] if args.conflicting else [])]
    )
    text = json.dumps(result, indent=1)
    print(markdown_table(result["summary"]) if args.markdown else json.dumps(result["summary"], indent=1))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
