"""How fast the task information reaches the policy through z, and how that depends on MTSACTE's J^rep schedule.

Trains MTSACTE on ``toy-conflict`` with its zoo settings and one setting changed at a time (``--grid``), and records
per iteration the linear probe of the task from sampled z (what the policy sees), from E_phi's mean, and E_phi's
standard deviation; and the mean success (5 episodes per task) every 500 vector steps. Prints one JSON object;
``--out FILE`` also writes it.

    python scripts/studies/rep_study.py --seeds 0 1 --out docs/results/rep_study_toy.json
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from nt_robustness import BENCHMARK, SuccessTrace, print_and_write, toy_settings, versions

from sb3_mtte import MTSACTE, make_mt_env

GRID: dict[str, dict[str, Any]] = {
    "zoo toy settings": {},
    "rep_learning_rate 3e-4": {"rep_learning_rate": 3e-4},
    "rep_gradient_steps 2": {"rep_gradient_steps": 2},
    "iteration_length 250": {"iteration_length": 250},
    "c_vae 0": {"c_vae": 0.0},
}


def first_step_at(trace: list[tuple[int, float]], threshold: float) -> int | None:
    return next((steps for steps, value in trace if value >= threshold), None)


def run(seed: int, name: str, budget: int, kwargs: dict[str, Any]) -> dict[str, Any]:
    env = make_mt_env(BENCHMARK, seed=seed)
    model = MTSACTE("MlpPolicy", env, seed=seed, device="cpu", **{**kwargs, **GRID[name]})
    probes: list[tuple[int, float, float, float]] = []
    update = model.update_representation

    def recorded_update(batch_size: int) -> None:
        update(batch_size)
        probes.append((model.num_timesteps, model.task_probe_accuracy, model.task_probe_accuracy_of_mean, model.z_std))

    model.update_representation = recorded_update  # type: ignore[method-assign]
    trace = SuccessTrace(seed)
    model.learn(budget, callback=trace)
    env.close()
    probe_z = [(steps, z) for steps, z, _, _ in probes]
    return {
        "seed": seed,
        "setting": name,
        "probe": probes,
        "success_trace": trace.trace,
        "env_steps_to_probe_0.5": first_step_at(probe_z, 0.5),
        "env_steps_to_success_0.9": first_step_at(trace.trace, 0.9),
        "final_z_std": probes[-1][3],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--settings", nargs="+", choices=list(GRID), default=list(GRID))
    parser.add_argument("--num-threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()
    th.set_num_threads(args.num_threads)
    budget, kwargs = toy_settings()
    runs = [run(seed, name, budget, kwargs) for name in args.settings for seed in args.seeds]
    summary = {}
    for name in args.settings:
        group = [r for r in runs if r["setting"] == name]
        summary[name] = {
            key: [r[key] for r in group]
            for key in ("env_steps_to_probe_0.5", "env_steps_to_success_0.9", "final_z_std")
        }
        summary[name]["final_success_trace_mean"] = float(np.mean([r["success_trace"][-1][1] for r in group]))
    result = {
        "benchmark": BENCHMARK,
        "env_steps": budget,
        "base_settings": {k: repr(v) for k, v in kwargs.items()},
        "summary": summary,
        "runs": runs,
        "versions": versions(),
        "command": f"python scripts/studies/rep_study.py --seeds {' '.join(map(str, args.seeds))}",
    }
    print_and_write(result, args.out)


if __name__ == "__main__":
    main()
