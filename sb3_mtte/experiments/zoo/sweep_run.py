"""One trial's run in ``sb3-mtte sweep``: the train command of its run folder, and its result."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.zoo import launcher


def trial_command(trial: dict[str, Any], out: Path, extra: Sequence[str], cpus: float) -> list[str]:
    """``sb3-mtte`` arguments of a trial: a new run, or the resumption of its run folder."""
    run_dir = Path(trial["run_dir"])
    argv = ["train", "--algo", trial["algo"], "--env", trial["env_id"], "-f", str(out), "--no-progress"]
    if run_info.read_run_info(run_dir) is not None:
        argv += ["--resume", str(run_dir)]
    else:
        argv += ["--seed", str(trial["seed"]), "--exp-id", str(trial["exp_id"])]
    if "--num-threads" not in extra:
        argv += ["--num-threads", str(max(1, int(cpus)))]
    return argv + list(extra)


def run_one(config: dict[str, Any]) -> dict[str, Any]:
    """Run (or resume, or skip when finished) one zoo training run and return its result; Ray runs it through
    :func:`~sb3_mtte.experiments.zoo.sweep_trial.run_trial`."""
    trial = config["trial"]
    run_dir = Path(trial["run_dir"])
    info = run_info.read_run_info(run_dir)
    if info is None or not info.get("finished"):
        command = trial_command(trial, Path(config["out"]), config["extra"], config["cpus"])
        launcher.train(command[1:])
        info = run_info.read_run_info(run_dir) or {}
    result = {"timesteps": int(info.get("timesteps", 0)), "finished": bool(info.get("finished"))}
    success = last_success(run_dir)
    if success is not None:
        result["success"] = success
    return result


def last_success(run_dir: Path) -> float | None:
    """Mean success of the last evaluation of a run folder (``evaluations.npz``), or None."""
    path = run_dir / "evaluations.npz"
    if not path.is_file():
        return None
    data = run_info.read_npz(path)
    if len(data["timesteps"]) == 0:
        return None
    return float(np.mean(data["success_rate"][-1]))
