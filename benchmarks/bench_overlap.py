"""Env steps/s of MTSAC training in SB3's order and with the env step overlapped with the update, in one run.

=========  ==================================================================================================
order      one vector step
=========  ==================================================================================================
plain      act, step the envs, store, update (SB3's order; ``overlap_env_step=False``)
overlap    act, send the actions, update, receive the observations, store (``overlap_env_step=True``)
=========  ==================================================================================================

Both train MTSAC (its defaults: 2 x 400, L = 128 per task) on the CPU, on the benchmark stepped by ``SubprocVecEnv``
(one process per task), where the processes step while the update runs. Each order builds its model and envs once
and trains ``--warm-steps`` env steps (past ``learning_starts``, half of them). Then the rounds alternate: each round
times ``--timed-steps`` more env steps of each order, the first order changing from round to round, so that a drift
of the machine hits both alike. The report gives each order's median, every figure, the command, the versions and
the machine::

    python benchmarks/bench_overlap.py --out docs/results/overlap_cpu.json                  # MT10, 5 rounds
    python benchmarks/bench_overlap.py --benchmark toy-conflict --warm-steps 80 --timed-steps 40 --rounds 1 \\
        --net-arch 16 16 --batch-size 8                                                    # a dry run
"""

from __future__ import annotations

import sb3_mtte

sb3_mtte.tune_process()  # before torch loads, as the package's commands do

# isort: split

import argparse
import json
import os
import platform
import statistics
import sys
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from stable_baselines3.common.vec_env import SubprocVecEnv

from sb3_mtte import MTSAC, make_mt_env

ORDERS = {"plain": False, "overlap": True}
"""Order -> ``overlap_env_step``."""
PACKAGES = ("sb3-mtte", "torch", "stable-baselines3", "gymnasium", "metaworld", "mujoco", "numpy")


def build(args: argparse.Namespace, overlap: bool) -> MTSAC:
    env = make_mt_env(args.benchmark, seed=args.seed, vec_env_cls=SubprocVecEnv)
    return MTSAC(
        "MlpPolicy",
        env,
        learning_starts=args.warm_steps // 2,
        batch_size=args.batch_size,
        policy_kwargs={"net_arch": args.net_arch},
        overlap_env_step=overlap,
        seed=args.seed,
        device="cpu",
    )


def timed_learn(model: MTSAC, env_steps: int) -> float:
    """Env steps/s of ``env_steps`` more env steps of ``model``."""
    start = time.perf_counter()
    model.learn(env_steps, reset_num_timesteps=False)
    return env_steps / (time.perf_counter() - start)


def measure(args: argparse.Namespace) -> dict[str, list[float]]:
    """Order -> its env steps/s in each round."""
    models = {name: build(args, overlap) for name, overlap in ORDERS.items()}
    rates: dict[str, list[float]] = {name: [] for name in ORDERS}
    try:
        for model in models.values():
            model.learn(args.warm_steps)
        names = list(ORDERS)
        for round_index in range(args.rounds):
            for name in names[round_index % 2 :] + names[: round_index % 2]:
                rates[name].append(round(timed_learn(models[name], args.timed_steps), 2))
            print(f"round {round_index + 1}/{args.rounds}: {json.dumps({n: r[-1] for n, r in rates.items()})}")
    finally:
        for model in models.values():
            model.get_env().close()  # type: ignore[union-attr]
    return rates


def summary(rates: dict[str, list[float]]) -> dict:
    medians = {name: statistics.median(values) for name, values in rates.items()}
    return {
        name: {
            "median_env_steps_per_s": round(medians[name], 2),
            "over_plain": round(medians[name] / medians["plain"], 3),
            "all_env_steps_per_s": values,
        }
        for name, values in rates.items()
    }


def machine() -> dict:
    """What the figures were measured on."""
    cpuinfo = Path("/proc/cpuinfo")
    lines = cpuinfo.read_text().splitlines() if cpuinfo.exists() else []
    names = [line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")]
    return {
        "cpu": names[0] if names else platform.processor(),
        "cpus": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "load_average_at_start": [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None,
        "platform": platform.platform(),
        "python": platform.python_version(),
    }


def versions() -> dict[str, str | None]:
    found: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = None
    return found


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--benchmark", default="MT10", help="benchmark of make_mt_env (MT10)")
    parser.add_argument("--warm-steps", type=int, default=2000, help="env steps before timing (2000)")
    parser.add_argument("--timed-steps", type=int, default=2000, help="env steps of each order in a round (2000)")
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds of both orders (5)")
    parser.add_argument("--net-arch", type=int, nargs="+", default=[400, 400], help="hidden widths (400 400)")
    parser.add_argument("--batch-size", type=int, default=128, help="L, transitions per task in a batch (128)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="also write the JSON report here")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.timed_steps < 1 or args.warm_steps < 2:
        parser.error("--rounds and --timed-steps must be at least 1, --warm-steps at least 2.")
    return args


def main(argv: list[str] | None = None) -> dict:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    started = time.time()
    header = {
        "command": " ".join(["python", "benchmarks/bench_overlap.py", *argv]),
        "machine": machine(),
        "versions": versions(),
        "workload": {
            "algorithm": f"MTSAC, {' x '.join(map(str, args.net_arch))} nets, L = {args.batch_size}, device cpu",
            "benchmark": args.benchmark,
            "vec_env": "SubprocVecEnv",
            "warm_env_steps": args.warm_steps,
            "learning_starts": args.warm_steps // 2,
            "timed_env_steps_per_round": args.timed_steps,
            "seed": args.seed,
        },
        "vector_step": {"plain": "act, step, store, update", "overlap": "act, send, update, receive, store"},
        "rounds": args.rounds,
    }
    results = summary(measure(args))
    report = {**header, "wall_seconds": round(time.time() - started, 1), "orders": results}
    text = json.dumps(report, indent=2)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    print(json.dumps({name: result["median_env_steps_per_s"] for name, result in results.items()}, indent=2))
    return report


if __name__ == "__main__":
    main()
