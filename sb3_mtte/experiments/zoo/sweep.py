"""Run a grid of zoo training runs (algorithms x envs x seeds) on Ray Tune, one trial per run.

Usage::

    sb3-mtte sweep --algos mtsacte mtsac_mt mtsac_mh --envs MT10 MT20 --seeds 0 1 2 3 4 \\
        --budget smoke --out runs/ [--address ray://HEAD:10001] [--cpus-per-trial 2] [--gpus-per-trial 0.5] \\
        [--max-concurrent 8] [--retries 2] [--resume] [-- EXTRA ZOO TRAIN FLAGS]

Every trial runs ``sb3-mtte train --algo A --env E --seed S -f OUT --exp-id K`` in a Ray worker
(``ray.init()`` starts a local Ray by default; ``--address`` joins a cluster, whose nodes need this package and a
file system shared at OUT). Results land in the zoo layout that ``sb3-mtte plot OUT`` reads:
``OUT/<algo>/<env>_<K>/``; ``--budget smoke`` trains the ``<env>-smoke`` entry of each hyperparameter file
(``OUT/<algo>/<env>-smoke_<K>/``). The trial list, with each trial's run folder, is kept in ``OUT/sweep.json``;
``--resume`` re-runs the same trials: finished ones are skipped and the others continue from their last
checkpoint (a retried trial, ``--retries``, does the same). Ray Tune's own records go to ``OUT/_ray``.

Several runs share a machine (:func:`trial_resources`):

==================  ==============================================================================================
resource            each trial's share
==================  ==============================================================================================
GPU                 ``--gpus-per-trial``; by default 1/:data:`TRIALS_PER_GPU` of one with CUDA, none without
CPU cores           ``--cpus-per-trial`` cores of its own, pinned (:mod:`~sb3_mtte.experiments.zoo.sweep_trial`)
torch threads       ``--num-threads`` of its cores, unless the zoo flags give one
process settings    :func:`sb3_mtte.tune_process`, applied before torch loads in the worker
==================  ==============================================================================================

Ray is an optional dependency: ``pip install "sb3-mtte[ray]"`` (or ``pip install "ray[tune]"``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from huggingface_sb3 import EnvironmentName
from rl_zoo3.utils import get_latest_run_id

from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.cli import CommandParser, command_prog, output_folder_error
from sb3_mtte.experiments.env_ids import BUDGET_SUFFIXES, benchmark_help, register_env_id
from sb3_mtte.experiments.variants import algo_classes
from sb3_mtte.experiments.zoo import launcher
from sb3_mtte.experiments.zoo.configs import missing_entries_message
from sb3_mtte.experiments.zoo.sweep_run import last_success
from sb3_mtte.experiments.zoo.sweep_trial import run_trial
from sb3_mtte.process import SPIN_VARIABLES

SWEEP_FILE = "sweep.json"
TRIALS_PER_GPU = 4
"""Trials that share one GPU by default (``--gpus-per-trial`` 0.25): one run leaves the GPU idle most of a step."""
BUDGETS = ("full", *BUDGET_SUFFIXES)


def import_ray() -> Any:
    """Import ray (with Tune), or fail with how to install it."""
    try:
        import ray
        from ray import tune  # noqa: F401
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError(
            f'{command_prog("sweep")} needs Ray Tune: pip install "sb3-mtte[ray]" (or pip install "ray[tune]").'
        ) from error
    return ray


def repeated_values(args: argparse.Namespace) -> str | None:
    """The first of ``--algos``, ``--envs``, ``--seeds`` that names a value twice, with that value, or None."""
    for flag in ("algos", "envs", "seeds"):
        values = getattr(args, flag)
        twice = [value for i, value in enumerate(values) if value in values[:i]]
        if twice:
            return f"--{flag} {' '.join(map(str, values))}: {twice[0]} is given twice"
    return None


def env_id_for(env: str, budget: str) -> str:
    """The env id of a benchmark at a budget: ``MT10`` + ``smoke`` -> ``MT10-smoke``."""
    if budget not in BUDGETS:
        raise ValueError(f"budget must be one of {BUDGETS}, got {budget!r}.")
    return env if budget == "full" else f"{env}-{budget}"


def plan_trials(
    out: Path, algos: Sequence[str], envs: Sequence[str], seeds: Sequence[int], budget: str, resume: bool
) -> list[dict[str, Any]]:
    """The trials of the grid, each with its run folder (reused from ``sweep.json`` when resuming)."""
    previous = []
    if resume and (out / SWEEP_FILE).is_file():
        previous = json.loads((out / SWEEP_FILE).read_text()).get("trials", [])
    known = {(t["algo"], t["env_id"], t["seed"]): t for t in previous}
    next_id: dict[tuple[str, str], int] = {}
    trials = []
    for algo in algos:
        for env in envs:
            env_id = env_id_for(env, budget)
            for seed in seeds:
                if (algo, env_id, seed) in known:
                    trials.append(dict(known[(algo, env_id, seed)]))
                    continue
                key = (algo, env_id)
                if key not in next_id:
                    next_id[key] = get_latest_run_id(str(out / algo), EnvironmentName(env_id)) + 1
                exp_id = next_id[key]
                next_id[key] += 1
                run_dir = out / algo / f"{EnvironmentName(env_id)}_{exp_id}"
                trials.append(
                    {"algo": algo, "env_id": env_id, "seed": int(seed), "exp_id": exp_id, "run_dir": str(run_dir)}
                )
    return trials


def trial_resources(cpus_per_trial: float, gpus_per_trial: float | None, cuda_count: int) -> dict[str, float]:
    """What Ray reserves for each trial: ``cpus_per_trial`` CPUs, and a share of a GPU where there is one.

    :param cpus_per_trial: ``--cpus-per-trial``.
    :param gpus_per_trial: ``--gpus-per-trial``; None: ``1 / TRIALS_PER_GPU`` with CUDA, none without.
    :param cuda_count: the CUDA devices of this machine.
    """
    if gpus_per_trial is None:
        gpus_per_trial = 1 / TRIALS_PER_GPU if cuda_count > 0 else 0.0
    resources = {"cpu": float(cpus_per_trial)}
    if gpus_per_trial > 0:
        resources["gpu"] = float(gpus_per_trial)
    return resources


def cuda_device_count() -> int:
    """The CUDA devices torch sees here (0 without CUDA)."""
    import torch as th

    return th.cuda.device_count() if th.cuda.is_available() else 0


def write_sweep_file(out: Path, trials: list[dict[str, Any]], args: argparse.Namespace, extra: Sequence[str]) -> None:
    """Write the trial list of the sweep (``OUT/sweep.json``)."""
    record = {
        "updated": run_info.now(),
        "command": " ".join(getattr(sys, "orig_argv", sys.argv)),
        "budget": args.budget,
        "extra_zoo_args": list(extra),
        "trials": trials,
    }
    (out / SWEEP_FILE).write_text(json.dumps(record, indent=2) + "\n")


def run_sweep(args: argparse.Namespace, extra: Sequence[str], ray: Any) -> list[dict[str, Any]]:
    """Plan the trials, run them on Ray Tune (``ray``: :func:`import_ray`'s module) and return them with their
    status and result."""
    tune = ray.tune

    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    trials = plan_trials(out, args.algos, args.envs, args.seeds, args.budget, args.resume)
    write_sweep_file(out, trials, args, extra)
    init_kwargs: dict[str, Any] = {"ignore_reinit_error": True, "include_dashboard": False}
    if args.address:
        init_kwargs["address"] = args.address
    elif args.num_cpus is not None:
        init_kwargs["num_cpus"] = args.num_cpus
    spin = {name: os.environ[name] for name in SPIN_VARIABLES if name in os.environ}
    if spin:  # a cluster's workers get the driver's OpenMP wait policy too
        init_kwargs["runtime_env"] = {"env_vars": spin}
    ray.init(**init_kwargs)
    resources = trial_resources(args.cpus_per_trial, args.gpus_per_trial, cuda_device_count())
    tuner = tune.Tuner(
        tune.with_resources(run_trial, resources),
        param_space={
            "trial": tune.grid_search([{**trial, "index": i} for i, trial in enumerate(trials)]),
            "out": str(out),
            "extra": list(extra),
            "cpus": args.cpus_per_trial,
        },
        tune_config=tune.TuneConfig(max_concurrent_trials=args.max_concurrent),
        run_config=tune.RunConfig(
            name=f"sweep_{time.strftime('%Y%m%d-%H%M%S')}",
            storage_path=str(out / "_ray"),
            failure_config=tune.FailureConfig(max_failures=args.retries),
            verbose=args.ray_verbose,
        ),
    )
    results = tuner.fit()
    for trial, result in zip(trials, _results_by_trial(results, trials), strict=True):
        trial["status"] = "error" if result is None or result.error else "done"
        if result is not None and result.error:
            trial["error"] = str(result.error).splitlines()[0][:500]
        info = run_info.read_run_info(trial["run_dir"]) or {}
        trial["finished"] = bool(info.get("finished"))
        trial["timesteps"] = info.get("timesteps")
        trial["success"] = last_success(Path(trial["run_dir"]))
    write_sweep_file(out, trials, args, extra)
    _print_summary(trials)
    return trials


def _results_by_trial(results: Any, trials: list[dict[str, Any]]) -> list[Any]:
    """Ray results in the order of ``trials`` (matched by run folder)."""
    by_dir = {}
    for result in results:
        config = result.config or {}
        run_dir = config.get("trial", {}).get("run_dir")
        by_dir[run_dir] = result
    return [by_dir.get(trial["run_dir"]) for trial in trials]


def _print_summary(trials: list[dict[str, Any]]) -> None:
    print(f"\n{'algo':<22} {'env':<16} {'seed':>4}  {'status':<6} {'steps':>10}  success  run folder")
    for t in trials:
        success = "" if t.get("success") is None else f"{100 * t['success']:6.1f}%"
        steps = t.get("timesteps") or 0
        print(
            f"{t['algo']:<22} {t['env_id']:<16} {t['seed']:>4}  {t.get('status', ''):<6} {steps:>10}  "
            f"{success:>7}  {t['run_dir']}"
        )


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """``sb3-mtte sweep --algos ... --envs ... --seeds ... [options] [-- zoo train flags]``"""
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        cut = argv.index("--")
        argv, extra = argv[:cut], argv[cut + 1 :]
    parser = CommandParser(prog=command_prog("sweep"), description=__doc__.split("\n\n")[0])
    parser.add_argument("--algos", nargs="+", required=True, help="zoo algorithm keys (mtsacte, mtsac_mt, ...)")
    parser.add_argument(
        "--envs",
        nargs="+",
        required=True,
        help="benchmarks (MT10, MT20, MT25, MT50, DEV6, toy-conflict, a task list such as reach-v3_push-v3)",
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=[0], help="seeds (default 0)")
    parser.add_argument(
        "--budget",
        choices=BUDGETS,
        default="full",
        help="hyperparameter entry: full (the paper's budget) or an env id suffix: " + ", ".join(BUDGETS[1:]),
    )
    parser.add_argument("--out", required=True, help="runs folder (the zoo's -f)")
    parser.add_argument("--address", default=None, help="Ray cluster address (default: start Ray locally)")
    parser.add_argument("--num-cpus", type=int, default=None, help="CPUs of the local Ray (default: all)")
    parser.add_argument("--cpus-per-trial", type=float, default=1.0, help="CPUs Ray reserves for each run (default 1)")
    parser.add_argument(
        "--gpus-per-trial",
        type=float,
        default=None,
        help=f"GPUs Ray reserves for each run, a fraction shares one (default: 1/{TRIALS_PER_GPU} with CUDA, 0 "
        "without); each run is also pinned to its own --cpus-per-trial cores",
    )
    parser.add_argument("--max-concurrent", type=int, default=0, help="max trials at once (0: as resources allow)")
    parser.add_argument("--retries", type=int, default=0, help="retries of a failed trial (each resumes its run)")
    parser.add_argument("--resume", action="store_true", help="re-run the trials of OUT/sweep.json: skip finished")
    parser.add_argument("--ray-verbose", type=int, default=1, help="Ray Tune verbosity (0-3)")
    args = parser.parse_args(argv)
    repeated = repeated_values(args)
    if repeated:
        parser.error(f"{repeated}: each value once (a repeated one would run the same trials twice)")
    unknown_algos = [algo for algo in args.algos if algo not in algo_classes()]
    if unknown_algos:
        parser.error(f"unknown --algos {' '.join(unknown_algos)}: choose from {' '.join(algo_classes())}")
    unknown_envs = [env for env in args.envs if not register_env_id(env_id_for(env, args.budget))]
    if unknown_envs:
        if args.budget != "full":
            parser.error(f"unknown --envs {' '.join(unknown_envs)}: give the benchmark (MT10) and --budget the budget")
        parser.error(f"unknown --envs {' '.join(unknown_envs)}: {benchmark_help(unknown_envs[0])}")
    if not launcher.has_flag(extra, "-conf", "--conf-file"):
        for algo in args.algos:
            missing = missing_entries_message(algo, [env_id_for(env, args.budget) for env in args.envs], "-- -conf")
            if missing:
                parser.error(missing)
    if args.gpus_per_trial is not None and args.gpus_per_trial < 0:
        parser.error(f"--gpus-per-trial {args.gpus_per_trial}: give 0 or more (a fraction shares one GPU)")
    problem = output_folder_error("--out", args.out)
    try:
        ray = import_ray()
    except ImportError as error:
        problem = problem or str(error)
    if problem:
        parser.exit(2, f"{parser.prog}: error: {problem}\n")
    return run_sweep(args, extra, ray)
