"""How far MTSACTE's task weights w were from uniform over a run, per window of env steps per task.

Reads run folders (``negative_transfer.jsonl``) and records (``representation.weights_distance``) under the given
folders. Per run and window: the mean total variation distance of w from uniform over the window's iterations (w as
set by each iteration's last recomputation; 0: uniform; at most 1 - 1/N), and, from run folders, the correlation of
consecutive iterations' w (near 1: the same tasks weighted up from one iteration to the next; near 0: a new draw each
time) and the task weighted most on average over the window. Where the run logged the transfer matrix T (run folders,
and records that keep it), also the median coupling (mean |T[k, i]|, k != i, over mean |T[k, k]|) and the share of
off-diagonal entries below 0 (the pairs Eq. 6 counts as harmful) over the window.

    python scripts/studies/weights_over_time.py runs/mt10_100k/mtsacte docs/records/MT10-100k --window 20000
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from sb3_mtte.experiments.results.metrics import distance_from_uniform, harmful_fraction, transfer_coupling

from nt_gain_runs import mean_consecutive_correlation  # beside this script


def from_run_folder(path: Path) -> tuple[str, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The run's name, env steps per task of its recomputations, w at each ``(recomputations, tasks)``, and T's
    coupling and harmful share at each."""
    info = json.loads((path / "run_info.json").read_text())
    lines = [json.loads(line) for line in (path / "negative_transfer.jsonl").read_text().splitlines() if line]
    steps = np.array([r["timesteps"] for r in lines], dtype=float) / info["n_tasks"]
    return (
        f"{info['label']} seed {info['seed']} (run folder)",
        steps,
        np.array([r["weights"] for r in lines]),
        transfer_summary(np.array([r["transfer_matrix"] for r in lines], dtype=float)),
    )


def transfer_summary(matrices: np.ndarray) -> dict[str, np.ndarray]:
    return {"coupling": transfer_coupling(matrices), "harmful": harmful_fraction(matrices)}


def windows(steps: np.ndarray, width: float) -> list[np.ndarray]:
    edges = np.arange(0.0, steps.max() + width, width)
    return [(steps > low) & (steps <= low + width) for low in edges[:-1]]


def report(
    name: str,
    steps: np.ndarray,
    distance: np.ndarray,
    weights: np.ndarray | None,
    transfer: dict[str, np.ndarray],
    width: float,
) -> None:
    print(f"{name}: {len(steps)} iterations, mean distance {distance.mean():.3f}")
    for inside in windows(steps, width):
        if not inside.any():
            continue
        low, high = steps[inside].min(), steps[inside].max()
        line = f"  {low / 1000:6.1f}k-{high / 1000:6.1f}k: distance {distance[inside].mean():.3f}"
        if weights is not None and inside.sum() > 2:
            w = weights[inside]
            line += f", consecutive correlation {mean_consecutive_correlation(w):+.2f}"
            line += f", most weighted task {int(w.mean(0).argmax())}"
        if transfer:
            line += f", coupling {np.median(transfer['coupling'][inside]):.3f}"
            line += f", T below 0 {transfer['harmful'][inside].mean():.0%}"
        print(line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sources", nargs="+", type=Path)
    parser.add_argument("--window", type=float, default=20_000, help="env steps per task")
    args = parser.parse_args()
    for source in args.sources:
        for log in sorted(source.rglob("negative_transfer.jsonl")):
            name, steps, weights, transfer = from_run_folder(log.parent)
            report(name, steps, distance_from_uniform(weights), weights, transfer, args.window)
        for path in sorted(source.rglob("*.json")):
            record = json.loads(path.read_text())
            representation = record.get("representation") if isinstance(record, dict) else None
            if representation and "weights_distance" in representation:
                steps = np.array(representation["env_steps"], dtype=float) / record["n_tasks"]
                name = f"{record['label']} seed {record['seed']} (record)"
                transfer = {
                    key: np.array(representation[field])
                    for key, field in (("coupling", "coupling"), ("harmful", "harmful_fraction"))
                    if field in representation
                }
                report(name, steps, np.array(representation["weights_distance"]), None, transfer, args.window)


if __name__ == "__main__":
    main()
