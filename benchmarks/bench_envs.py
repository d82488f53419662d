"""Env steps/s of a Meta-World benchmark under random actions, through Meta-World's envs and through EnvPool; prints
one JSON object. No model and no update: the env step alone, the floor of a training run's vector step.

Setups (``--setups``), each ``make_mt_env`` of the benchmark with the same seed and the same actions:

- ``metaworld``: Meta-World's own envs, stepped one after another in this process (``DummyVecEnv``);
- ``metaworld-subproc``: the same, one process per task (``SubprocVecEnv``);
- ``envpool-sequential``: EnvPool's tasks, each pool stepped and received before the next (``DummyVecEnv``);
- ``envpool``: EnvPool's tasks, every pool's step sent before any is received (``backend="envpool"``).

The setups are timed round-robin, ``--vector-steps`` a round, so that drifts of the machine hit every one alike;
the report gives each setup's median rate and its spread. EnvPool's setups need ``pip install "sb3-mtte[envpool]"``.

    python benchmarks/bench_envs.py                                    # MT10, every setup
    python benchmarks/bench_envs.py --benchmark MT50 --out env_steps.json
    python benchmarks/bench_envs.py --vector-steps 20 --rounds 1 --setups metaworld envpool   # a dry run
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable

import numpy as np
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from sb3_mtte import __version__
from sb3_mtte.envs import env_protocol, make_env_fns, make_mt_env

SETUPS: dict[str, Callable[[str, int], VecEnv]] = {
    "metaworld": lambda benchmark, seed: make_mt_env(benchmark, seed=seed),
    "metaworld-subproc": lambda benchmark, seed: make_mt_env(
        benchmark, seed=seed, vec_env_cls=SubprocVecEnv, vec_env_kwargs={"start_method": "forkserver"}
    ),
    "envpool-sequential": lambda benchmark, seed: DummyVecEnv(make_env_fns(benchmark, seed=seed, backend="envpool")),
    "envpool": lambda benchmark, seed: make_mt_env(benchmark, seed=seed, backend="envpool"),
}
"""Setup -> how to build its VecEnv from a benchmark and a seed."""


def time_steps(env: VecEnv, actions: np.ndarray) -> float:
    """Seconds to step ``env`` through ``actions`` (vector step, task, action), episode ends included."""
    start = time.perf_counter()
    for action in actions:
        env.step(action)
    return time.perf_counter() - start


def measure(benchmark: str, setups: list[str], vector_steps: int, rounds: int, seed: int) -> dict:
    envs = {name: SETUPS[name](benchmark, seed) for name in setups}
    n_tasks = next(iter(envs.values())).num_envs
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, (vector_steps, n_tasks, 4)).astype(np.float32)
    seconds: dict[str, list[float]] = {name: [] for name in setups}
    try:
        for env in envs.values():
            env.reset()
            time_steps(env, actions[: min(50, vector_steps)])  # warm-up
        for _ in range(rounds):
            for name, env in envs.items():
                seconds[name].append(time_steps(env, actions))
    finally:
        for env in envs.values():
            env.close()
    rates = {name: [n_tasks * vector_steps / s for s in values] for name, values in seconds.items()}
    return {
        name: {
            "env_steps_per_s": round(statistics.median(values), 1),
            "min": round(min(values), 1),
            "max": round(max(values), 1),
            "vec_env": type(envs[name]).__name__,
        }
        for name, values in rates.items()
    }


def machine() -> dict:
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "sb3_mtte": __version__,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--benchmark", default="MT10", help="benchmark or task list (MT10)")
    parser.add_argument("--setups", nargs="+", default=list(SETUPS), choices=list(SETUPS), help="what to time (all)")
    parser.add_argument("--vector-steps", type=int, default=1000, help="vector steps of each timed round (1000)")
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds of every setup (5)")
    parser.add_argument("--seed", type=int, default=0, help="benchmark seed and actions' seed (0)")
    parser.add_argument("--out", default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    results = measure(args.benchmark, args.setups, args.vector_steps, args.rounds, args.seed)
    baseline = results.get("metaworld", {}).get("env_steps_per_s")
    if baseline:
        for result in results.values():
            result["vs_metaworld"] = round(result["env_steps_per_s"] / baseline, 2)
    report = {
        "benchmark": args.benchmark,
        "actions": "uniform random, the same for every setup",
        "vector_steps_per_round": args.vector_steps,
        "rounds": args.rounds,
        "machine": machine(),
        "protocols": {name: (env_protocol(args.benchmark, _backend(name)) or {}).get("label") for name in args.setups},
        "setups": results,
    }
    print(json.dumps(report, indent=2))
    if args.out:
        with open(args.out, "w") as file:
            json.dump(report, file, indent=2)
            file.write("\n")
    return report


def _backend(setup: str) -> dict[str, str]:
    return {"backend": "envpool"} if setup.startswith("envpool") else {}


if __name__ == "__main__":
    main()
