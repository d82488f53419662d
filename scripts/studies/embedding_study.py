"""How fast z ~ E_phi carries the task on the development benchmark, for each setting where the paper is silent.

One run per call: MTSACTE (or SAC-MT with ``--setting sac_mt``) on ``--benchmark`` (default ``DEV6``, six
Meta-World tasks outside MT10 and MT20 in three pairs that share a scene) with the paper's Meta-World settings
(the ``MT10`` entry of ``zoo_configs/mtsacte.yml``: 2 x 400 nets, L = 128, M = N // 2, K = 30, H = 500, ...) and
one setting of :data:`GRID` on top. Records the held-out linear probe of the task from sampled z (what the policy
sees), from E_phi's mean, and E_phi's standard deviation at every J^rep update (thinned to one per
``--probe-every`` vector steps), the wall time per vector step, and, with ``--eval-episodes``, the final
per-task success (deterministic actions, one goal variation per episode). Writes one JSON file per run.

    python scripts/studies/embedding_study.py --setting chosen_defaults --seed 0 --per-task-steps 6000 --out-dir study
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import torch as th
from nt_robustness import versions
from stable_baselines3.common.callbacks import BaseCallback

from sb3_mtte import MTSAC, MTSACTE, evaluate_success, make_mt_env
from sb3_mtte.experiments.zoo.configs import zoo_hyperparameters

FORMER = {"c_vae": 1e-2, "policy_kwargs": {"z_init_std": None, "z_mean_init_gain": 1.0}}
"""The defaults before this study: E_phi at PyTorch's initialisation (std ~1, mean gain 1), c_vae 1e-2."""


def former(policy_kwargs: dict[str, Any] | None = None, **factors: Any) -> dict[str, Any]:
    """The former defaults with some factors changed."""
    return {**FORMER, **factors, "policy_kwargs": {**FORMER["policy_kwargs"], **(policy_kwargs or {})}}


FIRST_ORDER_50 = {"rep_gradient_steps": 50, "nt_estimator": "gradient_dot"}
GRID: dict[str, dict[str, Any]] = {
    "chosen_defaults": {},
    "former_defaults": former(),
    "sac_mt": {},
    # one factor at a time from the former defaults
    "rep_steps_50_first_order": former(**FIRST_ORDER_50),
    "rep_lr_1e-3": former(rep_learning_rate=1e-3),
    "alpha_1e-2": former(nt_step_size=1e-2),
    "c_vae_1e-3": former(c_vae=1e-3),
    "z_init_std_0.1": former({"z_init_std": 0.1}),
    # combinations
    "init_0.1_rep_steps_50_first_order": former({"z_init_std": 0.1}, **FIRST_ORDER_50),
    "init_0.1_alpha_1e-2": former({"z_init_std": 0.1}, nt_step_size=1e-2),
    "init_0.1_c_vae_1e-4": former({"z_init_std": 0.1}, c_vae=1e-4),
    "init_0.1_c_vae_0": former({"z_init_std": 0.1}, c_vae=0.0),
    "init_0.1_c_vae_1e-4_rep_lr_1e-3": former({"z_init_std": 0.1}, c_vae=1e-4, rep_learning_rate=1e-3),
    "init_0.1_c_vae_1e-4_rep_steps_50_first_order": former({"z_init_std": 0.1}, c_vae=1e-4, **FIRST_ORDER_50),
    "init_0.01_c_vae_1e-4": former({"z_init_std": 0.01}, c_vae=1e-4),  # the defaults before the mean gain
    # E_phi's mean head scaled at initialisation, from std 0.01 and c_vae 1e-4 (gain 50: the chosen defaults)
    "mean_gain_50": {"policy_kwargs": {"z_mean_init_gain": 50.0}},
    "mean_gain_10": {"policy_kwargs": {"z_mean_init_gain": 10.0}},
}
LAUNCHER_KEYS = ("n_timesteps", "policy", "eval_freq", "eval_episodes", "save_freq")
MTSACTE_ONLY = ("use_vae", "use_topk", "n_select", "top_k", "iteration_length", "rep_gradient_steps")
MTSACTE_ONLY += ("nt_step_size", "c_vae", "rep_learning_rate", "nt_estimator")


def settings(name: str, n_tasks: int, per_task_steps: int) -> tuple[type, dict[str, Any]]:
    """The algorithm and its keyword arguments: the paper's MT10 entry, sized to the run, plus ``GRID[name]``."""
    entry = dict(zoo_hyperparameters("mtsacte")["MT10"])
    kwargs = {key: value for key, value in entry.items() if key not in LAUNCHER_KEYS}
    kwargs["policy_kwargs"] = eval(kwargs["policy_kwargs"], {"dict": dict})  # a literal dict(...) of the config
    kwargs.update(buffer_size=n_tasks * per_task_steps, learning_starts=n_tasks * 1500, n_select=n_tasks // 2)
    overrides = dict(GRID[name])
    kwargs["policy_kwargs"] = {**kwargs["policy_kwargs"], **overrides.pop("policy_kwargs", {})}
    kwargs.update(overrides)
    if name == "sac_mt":
        return MTSAC, {key: value for key, value in kwargs.items() if key not in MTSACTE_ONLY}
    return MTSACTE, kwargs


class WallClock(BaseCallback):
    """Wall time of the training steps after ``learning_starts`` (when updates run)."""

    def __init__(self, learning_starts: int) -> None:
        super().__init__()
        self.learning_starts, self.start, self.steps = learning_starts, None, 0

    def _on_step(self) -> bool:
        if self.start is None and self.num_timesteps > self.learning_starts:
            self.start, self.steps = time.perf_counter(), self.num_timesteps
        return True

    def seconds_per_vector_step(self, n_tasks: int) -> float:
        return (time.perf_counter() - self.start) / ((self.num_timesteps - self.steps) / n_tasks)


def run(args: argparse.Namespace) -> dict[str, Any]:
    th.set_num_threads(args.num_threads)
    env = make_mt_env(args.benchmark, seed=args.seed)
    n_tasks = env.num_envs
    algorithm, kwargs = settings(args.setting, n_tasks, args.per_task_steps)
    model = algorithm("MlpPolicy", env, seed=args.seed, device="cpu", **kwargs)
    probes: list[list[float]] = []
    if isinstance(model, MTSACTE):
        update = model.update_representation

        def recorded_update(batch_size: int) -> None:
            update(batch_size)
            vector_steps = model.num_timesteps // n_tasks
            if not probes or vector_steps - probes[-1][0] / n_tasks >= args.probe_every:
                probes.append(
                    [model.num_timesteps, model.task_probe_accuracy, model.task_probe_accuracy_of_mean, model.z_std]
                )

        model.update_representation = recorded_update  # type: ignore[method-assign]
    clock = WallClock(kwargs["learning_starts"])
    model.learn(n_tasks * args.per_task_steps, callback=clock)
    result: dict[str, Any] = {
        "benchmark": args.benchmark,
        "setting": args.setting,
        "overrides": GRID[args.setting],
        "seed": args.seed,
        "per_task_steps": args.per_task_steps,
        "probe": probes,
        "probe_columns": ["env_steps", "probe_sampled_z", "probe_mean_z", "z_std"],
        "seconds_per_vector_step": clock.seconds_per_vector_step(n_tasks),
        "num_threads": args.num_threads,
        "versions": versions(),
    }
    if args.eval_episodes:
        success = evaluate_success(model, args.benchmark, episodes_per_task=args.eval_episodes, seed=args.seed + 1000)
        result["success"] = success.as_dict()
        if isinstance(model, MTSACTE):  # the same model, deterministic actions on the other choice of z
            other = "sample" if model.policy.deterministic_z == "mean" else "mean"
            model.policy.deterministic_z = other
            success = evaluate_success(
                model, args.benchmark, episodes_per_task=args.eval_episodes, seed=args.seed + 1000
            )
            result[f"success_deterministic_z_{other}"] = success.as_dict()
    env.close()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--setting", choices=list(GRID), required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--benchmark", default="DEV6")
    parser.add_argument("--per-task-steps", type=int, default=6000)
    parser.add_argument("--probe-every", type=int, default=100, help="vector steps between recorded probes")
    parser.add_argument("--eval-episodes", type=int, default=0, help="final evaluation episodes per task (0: none)")
    parser.add_argument("--num-threads", type=int, default=1)
    parser.add_argument("--out-dir", type=Path, required=True)
    args = parser.parse_args()
    result = run(args)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    path = args.out_dir / f"{args.benchmark}_{args.setting}_{args.per_task_steps}_seed{args.seed}.json"
    path.write_text(json.dumps(result))
    last = result["probe"][-1] if result["probe"] else None
    print(path, "last probe:", last, "s/vector step:", round(result["seconds_per_vector_step"], 4))


if __name__ == "__main__":
    main()
