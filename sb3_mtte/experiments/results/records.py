"""The record of a finished run: a small, versioned JSON file that figures and tables can be redrawn from.

A run folder holds the models, the replay buffer and the logs; its record keeps what the results need and fits in a
repository. Its fields (format :data:`RECORD_VERSION`):

- ``record_version``; ``algo`` (zoo key), ``label``, ``env_id`` (e.g. ``MT10-cpu``), ``benchmark`` (e.g. ``MT10``),
  ``seed``, ``task_names``, ``n_tasks``, ``episode_length``, ``started`` (when the run started: with env id, label and
  seed it names the run), ``reward_function_version`` (Meta-World's reward functions, null for a toy benchmark; a
  record without the field was made with ``"v2"``), ``env_protocol`` (how the training envs differ from Meta-World's
  benchmark, :func:`sb3_mtte.envs.env_protocol`; a record without it was trained on Meta-World's own envs),
  ``mu_computation`` (MTSACTE: the precision of the transfer matrix mu was counted from, ``"float32"`` before it was
  exact, ``"float64"`` after; null without mu);
- ``device``: the machine's CPU count, torch threads and CUDA device, its ``host`` and ``trained_on`` (``"cuda"``,
  ``"cpu"``); a record without it was trained on a CPU;
- ``budget``: ``n_timesteps`` (planned env steps, all tasks), ``timesteps`` (reached) and ``finished``;
- ``hyperparams`` (every hyperparameter as loaded), ``versions`` (packages), ``git`` (commit, branch, dirty flag),
  ``resumes`` (how many times the run was resumed);
- ``curve``: ``env_steps`` (all tasks) and ``success_rate`` ``(evaluations, tasks)`` of every periodic evaluation,
  and its ``episodes_per_task``;
- ``final``: the final evaluation (``success.json``): ``mean``, ``per_task``, ``episodes_per_task``, ``env_steps``,
  ``deterministic``;
- ``training``: the per-task critic loss (soft Bellman error) ``(points, tasks)`` and, with a clip, the share of samples
  Eq. 16 dropped, at up to :data:`TRAINING_POINTS` of the log's dumps (``env_steps``), for Figs. 3 and 6;
- ``representation`` (MTSACTE): at every recomputation the linear probes of the task from z and from E_phi's mean,
  z's std and how far w is from uniform (``weights_distance``: total variation distance, 0 for uniform weights, at
  most 1 - 1/N; absent in records made before it), and from the transfer matrix T the share of its off-diagonal
  entries below zero (``harmful_fraction``) and mean |T[k, i]| (k != i) over mean |T[k, k]| (``coupling``: how far
  a virtual step on one task moves the others' objectives next to its own; both absent in records made before
  them); the mean of mu, of w and of C_s membership per task over the run.

A run that did not finish (``finished: false``) is skipped, named in one line, unless ``--include-unfinished`` is
given; its record then says so, and the tables mark it.

Records live in the repository as ``docs/records/<env id>/<algo>_seed<k>.json`` (``<env id>-reward-v1/`` for runs on
Meta-World's v1 rewards, ``<env id>-envpool/`` for runs trained on EnvPool, ``<env id>-exact-mu/`` for MTSACTE runs
whose mu was counted in float64, ``<env id>-gpu/`` for runs trained on CUDA; the default ``--out`` is
``docs/records``)::

    sb3-mtte record RUNS_DIR [--out docs/records] [--include-unfinished]
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sb3_mtte.common.utils import task_log_key
from sb3_mtte.experiments.cli import CommandParser, command_prog, output_folder_error
from sb3_mtte.experiments.results.figures import safe_name
from sb3_mtte.experiments.results.metrics import distance_from_uniform, harmful_fraction, transfer_coupling
from sb3_mtte.experiments.results.runs import (
    Run,
    Series,
    device_type_of,
    discover_runs,
    results_benchmark,
    task_scalar,
)
from sb3_mtte.experiments.results.statistics import leave_out_unfinished
from sb3_mtte.experiments.run_info import read_json
from sb3_mtte.mtsac.task_logs import CLIP_FRACTION_KEY, CRITIC_LOSS_KEY

RECORD_VERSION = 2
DEFAULT_RECORDS_DIR = Path("docs/records")
PROBE_KEYS = ("task_probe_accuracy", "task_probe_accuracy_of_mean", "z_std")
TRAINING_POINTS = 200


def _curve(run: Run) -> dict[str, Any] | None:
    if run.evaluations is None:
        return None
    return {
        "env_steps": [int(t) for t in run.evaluations["timesteps"]],
        "success_rate": np.round(np.asarray(run.evaluations["success_rate"], dtype=float), 6).tolist(),
        "episodes_per_task": run.info.get("hyperparams", {}).get("eval_episodes"),
    }


def _training(run: Run) -> dict[str, Any] | None:
    """Per-task critic loss and the clip's share of dropped samples at up to TRAINING_POINTS evenly spaced dumps."""
    losses = [task_scalar(run, CRITIC_LOSS_KEY, i) for i in range(run.n_tasks)]
    if not losses or any(series is None for series in losses):
        return None
    steps = losses[0][0]
    if any(not np.array_equal(series[0], steps) for series in losses):
        return None
    kept = np.unique(np.linspace(0, len(steps) - 1, min(len(steps), TRAINING_POINTS)).round().astype(int))
    training: dict[str, Any] = {
        "env_steps": [int(t) for t in steps[kept]],
        "critic_loss": np.stack([series[1][kept] for series in losses], axis=1).round(6).tolist(),
    }
    clip = run.scalar(CLIP_FRACTION_KEY)
    if clip is not None:
        at_steps = {int(t): float(v) for t, v in zip(*clip, strict=True)}
        training["q_loss_clip_fraction"] = [
            None if t not in at_steps else round(at_steps[t], 6) for t in training["env_steps"]
        ]
    return training


def _representation(run: Run) -> dict[str, Any] | None:
    """MTSACTE: probes, z's std and w's distance from uniform at every recomputation, and mu and w averaged over
    the run."""
    records = run.nt_records
    if not records:
        return None
    summary: dict[str, Any] = {"env_steps": [int(r["timesteps"]) for r in records]}
    for key in PROBE_KEYS:
        summary[key] = [None if r.get(key) is None else round(float(r[key]), 6) for r in records]
    summary["weights_distance"] = distance_from_uniform([r["weights"] for r in records]).round(6).tolist()
    if all("transfer_matrix" in r for r in records):
        matrices = np.array([r["transfer_matrix"] for r in records], dtype=float)
        summary["harmful_fraction"] = harmful_fraction(matrices).round(6).tolist()
        summary["coupling"] = transfer_coupling(matrices).round(6).tolist()
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
        "n_tasks": run.n_tasks,
        "episode_length": info.get("episode_length"),
        "reward_function_version": run.reward_function_version,
        "env_protocol": run.env_protocol,
        "mu_computation": run.mu_computation,
        **_device_field(info),
        "started": info.get("started"),
        "budget": {
            "n_timesteps": info.get("n_timesteps", info.get("hyperparams", {}).get("n_timesteps")),
            "timesteps": info.get("timesteps"),
            "finished": info.get("finished"),
        },
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
        "training": _training(run),
        "representation": _representation(run),
    }


def _device_field(info: dict[str, Any]) -> dict[str, Any]:
    """``{"device": ...}``: run_info's ``device`` with its ``host`` and what the run trained on
    (:func:`~sb3_mtte.experiments.results.runs.device_type_of`); empty when run_info names no device."""
    if info.get("device") is None:
        return {}
    return {"device": {**info["device"], "host": info.get("host"), "trained_on": device_type_of(info)}}


def record_path(record: dict[str, Any], out: Path) -> Path:
    """``out/<benchmark>/<algo>_seed<k>.json``, the benchmark of
    :func:`~sb3_mtte.experiments.results.runs.results_benchmark` (the env id for Meta-World's default rewards and
    envs on a CPU)."""
    bench = results_benchmark(
        str(record["env_id"]),
        record.get("reward_function_version"),
        record.get("env_protocol"),
        device_type_of(record),
        record.get("mu_computation"),
    )
    return out / safe_name(bench) / f"{safe_name(str(record['algo']))}_seed{record['seed']}.json"


def write_records(
    runs_dir: str | Path, out: str | Path = DEFAULT_RECORDS_DIR, include_unfinished: bool = False
) -> list[Path]:
    """Write the record of every run folder under ``runs_dir`` that has a final evaluation and finished into
    ``out`` (:func:`record_path`), naming each run skipped in one line on stderr: no final evaluation, or it did not
    finish (recorded all the same with ``include_unfinished``, its ``budget`` saying so). Two runs that would share
    a record file stop it before anything is written."""
    planned: dict[Path, tuple[Run, dict[str, Any]]] = {}
    evaluated = [run for run in discover_runs(runs_dir) if _evaluated(run)]
    for run in leave_out_unfinished(evaluated, include_unfinished, "the records", "records"):
        record = run_record(run)
        path = record_path(record, Path(out))
        if path in planned:
            raise SystemExit(
                f"{planned[path][0].path} and {run.path} would both be recorded as {path}: "
                "record them one at a time (pass one run folder) into different --out folders"
            )
        planned[path] = (run, record)
    for path, (_, record) in planned.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(record, indent=1) + "\n")
    return list(planned)


def _evaluated(run: Run) -> bool:
    """Whether a run has a final evaluation; one line on stderr names a run without and how to evaluate it."""
    if run.final is not None:
        return True
    model = run.path / str(run.info.get("final_model") or f"{run.benchmark}.zip")
    if model.is_file():
        fix = f"evaluate it first: {command_prog('evaluate')} {model} --episodes 50"
    else:  # stopped or killed: no final model
        checkpoints = sorted(run.path.glob("rl_model_*_steps.zip"), key=lambda path: int(path.stem.split("_")[-2]))
        fix = f"it has no final model: finish it with {command_prog('train')} --resume {run.path}"
        if checkpoints:
            fix += f", or evaluate its last checkpoint: {command_prog('evaluate')} {checkpoints[-1]} --episodes 50"
    print(
        f"Skipped {run.path} ({run.benchmark}, {run.label}, seed {run.seed}): no final evaluation (success.json); "
        f"{fix}",
        file=sys.stderr,
    )
    return False


def read_records(folder: str | Path) -> list[tuple[Path, dict[str, Any]]]:
    """Every record (``*.json`` holding a ``record_version``) under ``folder``, with its path, sorted by path.

    Folders whose name starts with ``_`` or ``.`` (Ray's ``_ray`` state of a sweep, hidden folders) are not read."""
    records = []
    root = Path(folder)
    for path in sorted(root.rglob("*.json")):
        if any(part.startswith(("_", ".")) for part in path.relative_to(root).parts[:-1]):
            continue
        data = read_json(path)
        if isinstance(data, dict) and "record_version" in data:
            if data["record_version"] > RECORD_VERSION:
                raise SystemExit(
                    f"{path} has record format {data['record_version']}, newer than this package's "
                    f"{RECORD_VERSION}: update sb3-mtte"
                )
            records.append((path, data))
    return records


def run_from_record(record: dict[str, Any], path: Path) -> Run:
    """A :class:`Run` holding what a record keeps (no scalars or negative-transfer log), for the figures and tables."""
    keys = (
        "algo",
        "label",
        "env_id",
        "benchmark",
        "seed",
        "task_names",
        "n_tasks",
        "episode_length",
        "started",
        "reward_function_version",
        "env_protocol",
        "mu_computation",
        "device",
    )
    info = {key: record.get(key) for key in keys}
    info["hyperparams"] = record.get("hyperparams") or {}
    info["git"] = record.get("git") or {}
    budget = record.get("budget") or {}
    info.update({key: budget[key] for key in ("n_timesteps", "timesteps", "finished") if budget.get(key) is not None})
    run = Run(path, info)
    curve = record.get("curve")
    if curve:
        run.evaluations = {
            "timesteps": np.asarray(curve["env_steps"], dtype=float),
            "success_rate": np.asarray(curve["success_rate"], dtype=float),
            "task_names": np.asarray(record.get("task_names") or []),
        }
    training = record.get("training")
    if training:
        run.scalars.update(_training_scalars(training, run))
    final = record.get("final")
    if final:
        run.final = {key: final.get(key) for key in ("mean", "per_task", "episodes_per_task", "deterministic")}
        run.final["timesteps"] = final.get("env_steps")
    return run


def _training_scalars(training: dict[str, Any], run: Run) -> dict[str, Series]:
    """The log keys of a record's ``training`` field, as a run folder's scalars."""
    steps = np.asarray(training["env_steps"], dtype=float)
    losses = np.asarray(training["critic_loss"], dtype=float)
    scalars = {task_log_key(CRITIC_LOSS_KEY, i, name): (steps, losses[:, i]) for i, name in enumerate(run.task_names)}
    clip = training.get("q_loss_clip_fraction")
    if clip is not None:
        values = np.asarray([np.nan if v is None else v for v in clip], dtype=float)
        scalars[CLIP_FRACTION_KEY] = (steps[np.isfinite(values)], values[np.isfinite(values)])
    return scalars


def _run_key(run: Run) -> tuple[Any, ...]:
    return run.benchmark, run.label, run.seed, run.info.get("started")


def load_runs(sources: Sequence[str | Path]) -> list[Run]:
    """The runs under every source folder: its run folders (``run_info.json``) and its records; a record of a run
    whose folder is also found (same env id, label, seed and start time) is left out, the folder holding more."""
    folders = [run for source in sources for run in discover_runs(source)]
    seen = {_run_key(run) for run in folders}
    from_records = []
    for source in sources:
        for path, record in read_records(source):
            run = run_from_record(record, path)
            if _run_key(run) not in seen:
                seen.add(_run_key(run))
                from_records.append(run)
    return folders + from_records


def main(argv: Sequence[str] | None = None) -> list[Path]:
    parser = CommandParser(prog=command_prog("record"), description=__doc__.split("\n\n")[0])
    parser.add_argument("runs_dir", help="folder holding run folders (found by their run_info.json)")
    parser.add_argument(
        "--out",
        default=str(DEFAULT_RECORDS_DIR),
        help=f"folder for the records, written as <env id>/<algo>_seed<k>.json (default: {DEFAULT_RECORDS_DIR})",
    )
    parser.add_argument(
        "--include-unfinished",
        action="store_true",
        help="also record a run that did not finish (its record says so; default: skipped, named)",
    )
    args = parser.parse_args(argv)
    problem = output_folder_error("--out", args.out)
    if not Path(args.runs_dir).is_dir():
        problem = f"{args.runs_dir}: no such folder; give train's -f"
    if problem:
        parser.exit(2, f"{parser.prog}: error: {problem}\n")
    paths = write_records(args.runs_dir, args.out, args.include_unfinished)
    for path in paths:
        print(path)
    found = [] if paths else discover_runs(args.runs_dir)
    if not paths and not found:
        parser.exit(2, f"{parser.prog}: error: no run folder (run_info.json) under {args.runs_dir}: give train's -f\n")
    if not paths and any(run.final is not None for run in found):
        parser.exit(
            2,
            f"{parser.prog}: error: no finished run under {args.runs_dir} (each named above): resume them, or give "
            "--include-unfinished to record them as unfinished\n",
        )
    if not paths:
        parser.exit(
            2,
            f"{parser.prog}: error: no run with a final evaluation (success.json) under {args.runs_dir}; evaluate "
            f"each run first: {command_prog('evaluate')} <run folder>/<env id>.zip --episodes 50\n",
        )
    return paths


__all__ = [
    "DEFAULT_RECORDS_DIR",
    "RECORD_VERSION",
    "load_runs",
    "main",
    "read_records",
    "record_path",
    "run_from_record",
    "run_record",
    "write_records",
]
