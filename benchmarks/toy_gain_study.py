"""Final success on toy-conflict for several factors on E_phi's initial mean head (``z_mean_init_gain``).

The settings of ``tests/test_mtsacte_learning.py::test_learns_toy_conflict`` (its ``_learn_toy``: 2 x 64 nets, L = 64,
H = 50 vector steps, 10 J^rep steps per iteration), 16k env steps, evaluated with 50 episodes per task on the seed +
1000 benchmark; one JSON line per run, one torch thread.

    python benchmarks/toy_gain_study.py --gains 1 3 5 10 50 --seeds 0 1 > docs/results/toy_gain_study.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import sb3_mtte  # noqa: F401  # first: the package sets OpenMP's spin-wait before torch loads

# isort: split

import torch as th

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_mtsacte_learning import _learn_toy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gains", type=float, nargs="+", default=[1.0, 50.0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--steps", type=int, default=16_000)
    args = parser.parse_args()
    th.set_num_threads(1)
    for gain in args.gains:
        for seed in args.seeds:
            policy_kwargs = {"net_arch": [64, 64], "z_mean_init_gain": gain}
            result, seconds = _learn_toy(args.steps, seed, policy_kwargs=policy_kwargs)
            row = {"gain": gain, "seed": seed, "env_steps": args.steps, "mean": result.mean, "seconds": round(seconds)}
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
