"""One trial of ``sb3-mtte sweep``, as a Ray worker runs it: its process tuned and pinned to its cores, then its run.

This module imports nothing that loads torch, so :func:`run_trial` applies :func:`sb3_mtte.tune_process` before
torch loads in the worker. A Ray worker inherits the driver's environment variables, not its malloc thresholds.

Each trial is pinned to its own cores (:func:`trial_cores`): an even split of the cores the worker may use, by the
trial's index. Ray reserves a count of CPUs per trial, not which ones, so the split is the package's own. Trials
run in grid order, so the trials that run at once take consecutive slots.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any


def trial_cores(index: int, cpus_per_trial: float, cores: Sequence[int]) -> list[int]:
    """The cores of the trial ``index``: slot ``index`` modulo the number of slots of ``cpus_per_trial`` cores
    (at least 1) among ``cores``; all of ``cores`` when fewer than one slot's worth.

    :param index: the trial's index in the grid.
    :param cpus_per_trial: the CPUs Ray reserves for each trial.
    :param cores: the cores the worker may use (``os.sched_getaffinity(0)``).
    """
    cores = sorted(cores)
    per_trial = max(1, int(cpus_per_trial))
    n_slots = len(cores) // per_trial
    if n_slots < 1:
        return cores
    slot = index % n_slots
    return cores[slot * per_trial : (slot + 1) * per_trial]


def pin_to_cores(index: int, cpus_per_trial: float) -> list[int] | None:
    """Pin this process (and the processes it starts) to the cores of trial ``index``; None where the platform
    cannot pin (no ``os.sched_setaffinity``)."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    cores = trial_cores(index, cpus_per_trial, os.sched_getaffinity(0))
    os.sched_setaffinity(0, cores)
    return cores


def run_trial(config: dict[str, Any]) -> dict[str, Any]:
    """Ray Tune trainable: tune and pin this process, then run (or resume, or skip when finished) one zoo training
    run and report its result (:func:`~sb3_mtte.experiments.zoo.sweep_run.run_one`)."""
    import sb3_mtte

    sb3_mtte.tune_process()  # before torch loads: the imports below load it
    cores = pin_to_cores(int(config["trial"].get("index", 0)), config["cpus"])
    from ray import tune

    from sb3_mtte.experiments.zoo.sweep_run import run_one

    result = run_one(config)
    if cores is not None:
        result["cores"] = ",".join(map(str, cores))
    tune.report(result)
    return result


__all__ = ["pin_to_cores", "run_trial", "trial_cores"]
