"""The run folders of the learning runs (``learning_runs.py``): their names, their state, and what comes back.

A run's state decides what a call does with it: ``new`` (train), ``unfinished`` (resume from its last checkpoint),
``trained`` (evaluate) or ``evaluated`` (record). Only a run whose ``run_info.json`` says it finished, with its final
model, is ever evaluated or recorded.
"""

from __future__ import annotations

import argparse
import csv
import json
import tarfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

CALLS_FILE = "learning_calls.json"
SUMMARY_FILE = "learning_runs.json"
RUN_FILES = "run_files.tar.gz"
SMALL_FILES = ("*.json", "*.csv", "*.npz", "*.jsonl", "*.txt", "*/*.yml", "*/*.txt")
"""A run folder's files that come back (its config under ``<env>/``); models, buffers and events stay."""
MAX_OUT_FILES = 8
"""Files the device machine sends back from OUT."""


@dataclass
class Run:
    """One run: its algorithm, seed, folder, cores, and what this call did with it."""

    algo: str
    seed: int
    env_id: str
    run_dir: Path
    cores: list[int]
    state_before: str = ""
    events: list[str] = field(default_factory=list)
    call: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.algo}_seed{self.seed}"


def core_list(cores: Sequence[int]) -> str:
    """``taskset -c``'s form of a core list: ``0-3,8``."""
    parts, ordered = [], sorted(cores)
    start = prev = ordered[0]
    for core in [*ordered[1:], None]:
        if core is not None and core == prev + 1:
            prev = core
            continue
        parts.append(str(start) if start == prev else f"{start}-{prev}")
        if core is not None:
            start = prev = core
    return ",".join(parts)


def run_dir_of(runs_dir: Path, algo: str, env_id: str, seed: int) -> Path:
    """``<runs_dir>/<algo>/<env_id>_<seed + 1>``: rl-zoo's run folder with experiment id ``seed + 1`` (0 is its
    "next free id")."""
    return runs_dir / algo / f"{env_id}_{seed + 1}"


def record_name(env_id: str, algo: str, seed: int) -> str:
    """Where a record lands under ``OUT/records``: ``<env id>-gpu/<algo>_seed<k>.json``, beside the CPU records'
    ``<env id>/`` folder, never in it."""
    return f"{env_id}-gpu/{algo}_seed{seed}.json"


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def run_state(run_dir: Path) -> str:
    """``new`` (no run yet), ``unfinished`` (to resume), ``trained`` (finished, not evaluated) or ``evaluated``."""
    info = read_json(run_dir / "run_info.json")
    if not isinstance(info, dict):
        return "new"
    model = run_dir / str(info.get("final_model") or "")
    if not (info.get("finished") and model.is_file()):
        return "unfinished"
    return "evaluated" if (run_dir / "success.json").is_file() else "trained"


def checkpoint_markers(run_dir: Path) -> list[tuple[int, float]]:
    """(env steps, time written) of every checkpoint's marker (``rl_model_<t>_steps.json``, written last)."""
    found = []
    for path in run_dir.glob("rl_model_*_steps.json"):
        steps = path.name[len("rl_model_") : -len("_steps.json")]
        if steps.isdigit():
            found.append((int(steps), path.stat().st_mtime))
    return sorted(found)


def steps_reached(run_dir: Path) -> int:
    """Env steps a resumed run would start from: the final model's when finished, else the last checkpoint's."""
    info = read_json(run_dir / "run_info.json") or {}
    if info.get("finished"):
        return int(info.get("timesteps") or 0)
    markers = checkpoint_markers(run_dir)
    return markers[-1][0] if markers else 0


def last_logged_fps(run_dir: Path) -> float | None:
    """SB3's last ``time/fps`` in ``progress.csv`` (env steps/s of the training loop since its learn() began)."""
    try:
        with (run_dir / "progress.csv").open() as file:
            values = [row.get("time/fps") for row in csv.DictReader(file)]
    except OSError:
        return None
    values = [float(v) for v in values if v not in (None, "")]
    return values[-1] if values else None


def append_call(run: Run) -> list[dict[str, Any]]:
    """Add this call's entry to the run folder's ``learning_calls.json``; every entry so far."""
    path = run.run_dir / CALLS_FILE
    calls = read_json(path) if path.is_file() else []
    if run.call and run.run_dir.is_dir():
        calls.append(dict(run.call))
        path.write_text(json.dumps(calls, indent=1) + "\n")
    return calls


def run_summary(run: Run, calls: list[dict[str, Any]]) -> dict[str, Any]:
    info = read_json(run.run_dir / "run_info.json") or {}
    final = read_json(run.run_dir / "success.json") or {}
    wall = sum(c.get("train_wall_s") or 0 for c in calls)
    steps = steps_reached(run.run_dir)
    return {
        "algo": run.algo, "seed": run.seed, "env_id": run.env_id, "run_dir": str(run.run_dir),
        "cores": core_list(run.cores), "state_before": run.state_before, "state_after": run_state(run.run_dir),
        "finished": bool(info.get("finished")), "env_steps": steps, "n_timesteps": info.get("n_timesteps"),
        "final_mean": final.get("mean") if info.get("finished") else None, "device": info.get("device"),
        "this_call": run.call, "events": run.events, "calls": len(calls),
        "train_wall_s_all_calls": round(wall, 1), "env_steps_per_s_all_calls": round(steps / wall, 1) if wall else None,
    }  # fmt: skip


def write_output(groups: list[list[Run]], ctx: argparse.Namespace, call_started: float, final: bool) -> None:
    """``learning_runs.json`` and ``run_files.tar.gz`` in OUT (the calls' history only once, at the end)."""
    runs = [run for group in groups for run in group]
    summaries = [run_summary(run, append_call(run) if final else read_json(run.run_dir / CALLS_FILE) or [])
                 for run in runs]  # fmt: skip
    summary = {"call_wall_s": round(time.time() - call_started, 1), "budget_s": ctx.budget_s, "device": ctx.device,
               "software": ctx.software, "complete": final, "runs": summaries}  # fmt: skip
    (ctx.out / SUMMARY_FILE).write_text(json.dumps(summary, indent=1) + "\n")
    records = sorted((ctx.out / "records").rglob("*.json")) if (ctx.out / "records").is_dir() else []
    with tarfile.open(ctx.out / RUN_FILES, "w:gz") as archive:
        for run in runs:
            for pattern in SMALL_FILES:
                for path in sorted(run.run_dir.glob(pattern)):
                    archive.add(path, arcname=str(path.relative_to(ctx.runs_dir)))
        for path in sorted((ctx.runs_dir / "logs").glob("*.log")):
            archive.add(path, arcname=f"logs/{path.name}")
        for path in records:
            archive.add(path, arcname=str(path.relative_to(ctx.out)))
    others = [path for path in ctx.out.rglob("*") if path.is_file() and path not in records]  # a log of the call too
    if final and len(records) + len(others) > MAX_OUT_FILES:  # too many to come back: the records stay in the archive
        for path in records:
            path.unlink()
