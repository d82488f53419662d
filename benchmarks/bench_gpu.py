"""The eager path against the fast path (a CUDA graph of the update, the replay buffer on the device, one process
per task); prints one JSON object (``docs/results/gpu_check.json`` on a GPU). Two parts, run together or one a run:

- ``updates``: updates/s of every variant at each N on synthetic Meta-World-shaped batches (2 x 400 nets, L = 128
  per task), eager and fast timed round-robin;
- ``end_to_end``: env steps/s of ``learn()`` on MT10 and MT50 for MTSAC and MTSACTE after learning starts, eager
  (``update_path="eager"``, host buffer, tasks stepped one after another) and fast (``SubprocVecEnv`` where
  ``default_vec_env`` picks it: at least 4 cores), and the hours the paper's budget then takes.

"Fast" is what ``update_path="auto"`` and ``storage="auto"`` pick with the fast path as the default
(:data:`sb3_mtte.common.gpu_defaults.FAST_PATH_BY_DEFAULT`, set here): the graph where the update's hooks allow it,
the GPU's replay storage. ``--out`` writes the JSON after every part; a file there from the same device and torch
keeps the parts this run does not measure, so two runs, one per part, make one file.

    python benchmarks/bench_gpu.py --n-tasks 10 20 50 --benchmarks MT10 MT50 --vector-steps 300
    python benchmarks/bench_gpu.py --parts updates --out gpu_check.json       # then
    python benchmarks/bench_gpu.py --parts end_to_end --out gpu_check.json    # adds MT10 and MT50 to it
    python benchmarks/bench_gpu.py --n-tasks 10 --benchmarks MT10 --vector-steps 20 --repeats 3  # a dry run
"""

from __future__ import annotations

import sb3_mtte

sb3_mtte.tune_process()  # before torch loads, as the package's commands do

# isort: split

import argparse
import json
import os
import platform

import torch as th
from bench_updates import VARIANTS, fill_buffer, interleaved_medians, learn_rate, quiet, synthetic_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_mtte import MTSAC, MTSACTE, __version__, make_mt_env
from sb3_mtte.common import gpu_defaults
from sb3_mtte.experiments.env_ids import default_vec_env

PAPER_ENV_STEPS = {"MT10": 50_000_000, "MT50": 100_000_000}
"""The paper's MT10 budget (5M env steps per task) and MT50 at 2M per task."""
PATHS = {"eager": {"update_path": "eager", "replay_buffer_kwargs": {"storage": "host"}}, "fast": {}}
"""Keyword arguments of each path: the fast path is the defaults, with the fast path as the default."""
PARTS = ("updates", "end_to_end")


def update_models(n_tasks: int, device: str) -> dict[str, object]:
    """Every MTSAC variant and MTSACTE's every-step update on each path, with a filled buffer."""
    rows, models = 512, {}
    variants = {label: (MTSAC, policy, kwargs) for label, (policy, kwargs) in VARIANTS.items()}
    variants["MTSACTE-update"] = (MTSACTE, "MlpPolicy", {})
    for label, (cls, policy, kwargs) in variants.items():
        for path, path_kwargs in PATHS.items():
            model = cls(policy, synthetic_env(n_tasks), buffer_size=rows * n_tasks, device=device, seed=0,
                        **kwargs, **path_kwargs)  # fmt: skip
            fill_buffer(quiet(model), rows)
            if cls is MTSACTE:
                model._last_iteration = model._iteration_of_step(0)  # the every-step update alone: no recomputation
            models[f"{label}|{path}"] = model
    return models


def bench_updates(n_tasks: int, device: str, repeats: int) -> dict:
    models = update_models(n_tasks, device)
    seconds = interleaved_medians({k: (lambda m=m: m.train(1, 128)) for k, m in models.items()}, repeats, warmup=5)
    labels = sorted({key.split("|")[0] for key in seconds})
    return {
        "n_tasks": n_tasks,
        "path": {label: models[f"{label}|fast"].resolved_update_path() for label in labels},
        "updates_per_s": {label: {p: round(1 / seconds[f"{label}|{p}"], 1) for p in PATHS} for label in labels},
        "speedup": {label: round(seconds[f"{label}|eager"] / seconds[f"{label}|fast"], 2) for label in labels},
    }


def bench_end_to_end(benchmark: str, device: str, vector_steps: int) -> dict:
    """Env steps/s of learn() after learning starts (its random warm-up untimed), per algorithm and path."""
    rates, vec_envs = {}, {}
    for path, path_kwargs in PATHS.items():
        cls = SubprocVecEnv if path == "fast" and default_vec_env(benchmark) == "subproc" else DummyVecEnv
        env, vec_envs[path] = make_mt_env(benchmark, seed=0, vec_env_cls=cls), cls.__name__
        for label, algorithm in (("MTSAC", MTSAC), ("MTSACTE", MTSACTE)):
            n_tasks = env.num_envs
            model = quiet(algorithm("MlpPolicy", env, learning_starts=256 * n_tasks, buffer_size=2000 * n_tasks,
                                    device=device, seed=0, **path_kwargs))  # fmt: skip
            rates.setdefault(label, {})[path] = round(learn_rate(model, vector_steps), 1)
        env.close()
    hours = {label: {p: round(PAPER_ENV_STEPS[benchmark] / r / 3600, 1) for p, r in by_path.items()}
             for label, by_path in rates.items()}  # fmt: skip
    return {"env_steps_per_s": rates, "paper_budget_hours": hours, "vec_env": vec_envs}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", nargs="+", default=list(PARTS), choices=PARTS, help="what to measure (both)")
    parser.add_argument("--n-tasks", type=int, nargs="+", default=[10, 20, 50], help="task counts of the updates")
    parser.add_argument("--benchmarks", nargs="+", default=["MT10", "MT50"], choices=sorted(PAPER_ENV_STEPS))
    parser.add_argument("--vector-steps", type=int, default=300, help="timed vector steps of each learn()")
    parser.add_argument("--repeats", type=int, default=11, help="timed rounds of the updates")
    parser.add_argument("--device", default="auto", help="cuda, cpu or auto (default)")
    parser.add_argument(
        "--out", default=None, help="also write the JSON here, after every part (a later crash keeps it)"
    )
    parser.add_argument("--tests-log", default=None, help="with the updates: the CUDA tests' pytest output")
    parser.add_argument("--tests-rc", type=int, default=None, help="with --tests-log: pytest's exit status")
    args = parser.parse_args(argv)
    gpu_defaults.FAST_PATH_BY_DEFAULT = True  # "fast": what "auto" then picks
    device = ("cuda" if th.cuda.is_available() else "cpu") if args.device == "auto" else args.device
    report: dict = {
        "device": device,
        "device_name": th.cuda.get_device_name(0) if device == "cuda" else platform.processor() or "cpu",
        "torch": th.__version__,
        "sb3_mtte": __version__,
        "cpu_count": os.cpu_count(),
    }
    report = {**earlier_parts(args.out, report), **report}
    if args.tests_log is not None:
        report["cuda_tests"] = cuda_tests(args.tests_log, args.tests_rc)
    if "updates" in args.parts:
        report["updates"] = []
        for n_tasks in args.n_tasks:
            report["updates"].append(bench_updates(n_tasks, device, args.repeats))
            if n_tasks == 10:
                report["update_speedup_n10"] = report["updates"][-1]["speedup"]["MTSAC-MT"]
            write(report, args.out)
    for benchmark in args.benchmarks if "end_to_end" in args.parts else []:
        result = bench_end_to_end(benchmark, device, args.vector_steps)
        report[f"end_to_end_{benchmark}"] = result
        for label, by_path in result["env_steps_per_s"].items():
            report.setdefault(label, {})[f"{benchmark.lower()}_env_steps_per_s"] = by_path
        write(report, args.out)
    print(json.dumps(report, indent=1))
    return report


def cuda_tests(log_path: str, rc: int | None) -> dict:
    """The CUDA tests' outcome: pytest's summary line (the log's last line) and its exit status."""
    with open(log_path) as file:
        lines = [line.strip() for line in file if line.strip()]
    return {"summary": lines[-1] if lines else "", "rc": rc}


def earlier_parts(path: str | None, machine: dict) -> dict:
    """The report at ``path`` when one of the same device, torch and package is there (its parts are kept), else
    nothing."""
    if path is None or not os.path.exists(path):
        return {}
    with open(path) as file:
        earlier = json.load(file)
    same = all(earlier.get(key) == machine[key] for key in ("device", "device_name", "torch", "sb3_mtte"))
    return earlier if same else {}


def write(report: dict, path: str | None) -> None:
    if path is not None:
        with open(path, "w") as file:
            json.dump(report, file, indent=1)


if __name__ == "__main__":
    main()
