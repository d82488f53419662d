"""Final success on toy-conflict for several factors on E_phi's initial mean head (``z_mean_init_gain``).

The small settings of the toy learning test (``tests/test_mtsacte_learning.py``: 2 x 64 nets, L = 64, H = 50 vector
steps, 10 J^rep steps per iteration), 16k env steps, evaluated with 50 episodes per task on the seed + 1000
benchmark; one JSON line per run, one torch thread.

    python scripts/studies/toy_gain_study.py --gains 1 3 5 10 50 --seeds 0 1 > docs/results/toy_gain_study.jsonl
"""

from __future__ import annotations

import argparse
import json
import time

import sb3_mtte

sb3_mtte.tune_process()  # before torch loads, as the package's commands do

# isort: split

import torch as th

from sb3_mtte import MTSACTE, evaluate_success, make_mt_env

TOY_SETTINGS = {
    "learning_starts": 800,
    "batch_size": 64,
    "buffer_size": 50_000,
    "learning_rate": 1e-3,
    "top_k": 10,
    "iteration_length": 50,
    "rep_gradient_steps": 10,
    "rep_learning_rate": 1e-3,
    "device": "cpu",
}
"""MTSACTE's arguments in the toy learning test, besides the seed and the networks."""


def learn_toy(steps: int, seed: int, gain: float) -> tuple[float, float]:
    """Mean final success and training seconds of one run at E_phi's mean-head ``gain``."""
    policy_kwargs = {"net_arch": [64, 64], "z_mean_init_gain": gain}
    env = make_mt_env("toy-conflict", seed=seed)
    model = MTSACTE("MlpPolicy", env, policy_kwargs=policy_kwargs, seed=seed, **TOY_SETTINGS)
    start = time.perf_counter()
    model.learn(steps)
    seconds = time.perf_counter() - start
    result = evaluate_success(model, make_mt_env("toy-conflict", seed=1000 + seed), episodes_per_task=50)
    return result.mean, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gains", type=float, nargs="+", default=[1.0, 50.0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--steps", type=int, default=16_000)
    args = parser.parse_args()
    th.set_num_threads(1)
    for gain in args.gains:
        for seed in args.seeds:
            mean, seconds = learn_toy(args.steps, seed, gain)
            row = {"gain": gain, "seed": seed, "env_steps": args.steps, "mean": mean, "seconds": round(seconds)}
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
