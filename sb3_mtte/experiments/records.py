"""The record of a finished run: a small, versioned JSON file that figures and tables can be redrawn from.

A run folder holds the models, the replay buffer and the logs; its record keeps what the results need and fits in a
repository: the evaluation curve (env steps and per-task success at every periodic evaluation), the final
evaluation (``success.json``: per-task success and its episode count), for MTSACTE the task probes of z, E_phi's
standard deviation and the mean of mu and w over the run, and the run's zoo key, benchmark, seed, budget,
hyperparameters, package versions and commit.

    sb3-mtte record RUNS_DIR --out docs/records/MT10-cpu
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sb3_mtte.experiments import command_prog
from sb3_mtte.experiments.runs import Run, discover_runs

RECORD_VERSION = 1
PROBE_KEYS = ("task_probe_accuracy", "task_probe_accuracy_of_mean", "z_std")


def _curve(run: Run) -> dict[str, Any] | None:
    if run.evaluations is None:
        return None
    return {
        "env_steps": [int(t) for t in run.evaluations["timesteps"]],
        "success_rate": np.round(np.asarray(run.evaluations["success_rate"], dtype=float), 6).tolist(),
    }


def _representation(run: Run) -> dict[str, Any] | None:
    """MTSACTE: probes and z's std at every recomputation, and mu and w averaged over the run."""
    records = run.nt_records
    if not records:
        return None
    summary: dict[str, Any] = {"env_steps": [int(r["timesteps"]) for r in records]}
    for key in PROBE_KEYS:
        summary[key] = [None if r.get(key) is None else round(float(r[key]), 6) for r in records]
    summary["mean_mu"] = np.mean([r["mu"] for r in records], axis=0).round(4).tolist()
    summary["mean_weights"] = np.mean([r["weights"] for r in records], axis=0).round(6).tolist()
    summary["selected_fraction"] = np.mean([r["selected"] for r in records], axis=0).round(4).tolist()
    return summary


def run_record(run: Run) -> dict[str, Any]:
    """The record of one run folder (see the module docstring)."""
    info = run.info
    final = run.final or {}
    return {
        "record_version": RECORD_VERSION,
        "algo": info.get("algo"),
        "label": run.label,
        "env_id": info.get("env_id"),
        "benchmark": info.get("benchmark"),
        "seed": run.seed,
        "task_names": run.task_names,
        "env_steps": info.get("hyperparams", {}).get("n_timesteps"),
        "hyperparams": info.get("hyperparams"),
        "versions": info.get("versions"),
        "git": info.get("git"),
        "resumes": len(info.get("resumes", [])),
        "curve": _curve(run),
        "final": None
        if not final
        else {
            "mean": final.get("mean"),
            "per_task": final.get("per_task"),
            "episodes_per_task": final.get("episodes_per_task"),
            "env_steps": final.get("timesteps"),
            "deterministic": final.get("deterministic"),
        },
        "representation": _representation(run),
    }


def record_name(record: dict[str, Any]) -> str:
    return f"{record['env_id']}_{record['algo']}_seed{record['seed']}.json"


def write_records(runs_dir: str | Path, out: str | Path) -> list[Path]:
    """Write the record of every run folder under ``runs_dir`` that has a final evaluation into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for run in discover_runs(runs_dir):
        if run.final is None:
            continue
        record = run_record(run)
        path = out / record_name(record)
        path.write_text(json.dumps(record, indent=1) + "\n")
        written.append(path)
    return written


def read_records(folder: str | Path) -> list[dict[str, Any]]:
    """Every record (``*.json`` with a ``record_version``) under ``folder``."""
    records = []
    for path in sorted(Path(folder).rglob("*.json")):
        data = json.loads(path.read_text())
        if isinstance(data, dict) and "record_version" in data:
            records.append(data)
    return records


def main(argv: Sequence[str] | None = None) -> list[Path]:
    parser = argparse.ArgumentParser(
        prog=command_prog("record", "sb3_mtte.record"), description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("runs_dir", help="folder holding run folders (found by their run_info.json)")
    parser.add_argument("--out", required=True, help="folder for the records")
    args = parser.parse_args(argv)
    paths = write_records(args.runs_dir, args.out)
    for path in paths:
        print(path)
    if not paths:
        parser.exit(2, f"{parser.prog}: no run with a final evaluation (success.json) under {args.runs_dir}\n")
    return paths


__all__ = ["RECORD_VERSION", "main", "read_records", "run_record", "write_records"]
