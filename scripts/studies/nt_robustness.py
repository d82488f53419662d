"""How often mu singles out the conflicting task of toy-conflict, for each ``nt_measure`` of MTSACTE and each gain
of E_phi's initial mean head (``z_mean_init_gain``).

For each seed, gain and measure (``per_batch``: the paper; ``mean`` and ``significant``: over an iteration's batches),
trains MTSACTE on ``toy-conflict`` with its zoo settings (``zoo_configs/mtsacte.yml``) and records mu, C_s and w
after every iteration's J^rep steps (the values that weight the policy during the iteration). Reports, per measure
and gain, the fraction of iterations in which the conflicting task (the last one) has the strictly largest mu (over
the whole run and over its first quarter) and the same over every recomputation (one per J^rep step), whether its
mean mu over the first six iterations and over the first six recomputations is strictly the largest, its share of
C_s and its mean weight, how far w is from uniform (total variation distance, mean over the run and over its first
quarter), the final success (10 episodes per task) and the env steps until the periodic evaluation first
reaches 90%. Prints one JSON object; ``--out FILE`` also writes it.

    python scripts/studies/nt_robustness.py --seeds 0 1 2 --out docs/results/nt_robustness.json
    python scripts/studies/nt_robustness.py --seeds 0 1 2 --measures per_batch --gains 1 50 \
        --out docs/results/nt_gain_study.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
import yaml
from stable_baselines3.common.callbacks import BaseCallback

from sb3_mtte import MTSACTE, __version__, evaluate_success, make_mt_env
from sb3_mtte.experiments.results.metrics import distance_from_uniform
from sb3_mtte.experiments.zoo.configs import find_config_dir

from nt_gain_runs import strictly_largest  # beside this script

BENCHMARK = "toy-conflict"
LAUNCHER_KEYS = ("n_timesteps", "policy", "eval_freq", "eval_episodes", "save_freq")


def toy_settings() -> tuple[int, dict[str, Any]]:
    """Budget and MTSACTE arguments of the ``toy-conflict`` entry of the zoo config."""
    path = find_config_dir() / "mtsacte.yml"
    entry = dict(yaml.safe_load(path.read_text())[BENCHMARK])
    budget = int(entry["n_timesteps"])
    kwargs = {key: value for key, value in entry.items() if key not in LAUNCHER_KEYS}
    kwargs["policy_kwargs"] = eval(kwargs["policy_kwargs"], {"dict": dict})  # a literal dict(...) of the config
    return budget, kwargs


MEASURES = ("per_batch", "mean", "significant")
EVAL_EVERY = 500  # vector steps


class SuccessTrace(BaseCallback):
    """Mean success (5 episodes per task) every ``EVAL_EVERY`` vector steps."""

    def __init__(self, seed: int) -> None:
        super().__init__()
        self.seed, self.trace = seed, []

    def _on_step(self) -> bool:
        n_tasks = self.training_env.num_envs
        if (self.num_timesteps // n_tasks) % EVAL_EVERY == 0:
            result = evaluate_success(self.model, BENCHMARK, episodes_per_task=5, seed=self.seed + 2000)
            self.trace.append((self.num_timesteps, result.mean))
        return True


FIRST_ITERATIONS = 6


def run(seed: int, measure: str, budget: int, kwargs: dict[str, Any], gain: float | None = None) -> dict[str, Any]:
    env = make_mt_env(BENCHMARK, seed=seed)
    if gain is not None:
        kwargs = {**kwargs, "policy_kwargs": {**kwargs["policy_kwargs"], "z_mean_init_gain": gain}}
    model = MTSACTE("MlpPolicy", env, seed=seed, device="cpu", nt_measure=measure, **kwargs)
    records: list[dict[str, Any]] = []
    update = model.update_representation

    def recorded_update(batch_size: int) -> None:
        update(batch_size)
        records.append(
            {
                "mu": model.mu.tolist(),
                "weights": model.task_weights.tolist(),
                "selected": model.selected_tasks.tolist(),
            }
        )

    model.update_representation = recorded_update  # type: ignore[method-assign]
    recomputed: list[list[float]] = []
    set_selection = model._set_selection

    def recorded_selection(selection: Any) -> None:
        set_selection(selection)
        recomputed.append(model.mu.tolist())

    model._set_selection = recorded_selection  # type: ignore[method-assign]
    start = time.perf_counter()
    trace = SuccessTrace(seed)
    model.learn(budget, callback=trace)
    seconds = time.perf_counter() - start
    success = evaluate_success(model, BENCHMARK, episodes_per_task=10, seed=seed + 1000)
    env.close()
    mu = np.array([r["mu"] for r in records], dtype=float)
    weights = np.array([r["weights"] for r in records])
    selected = np.array([r["selected"] for r in records], dtype=float)
    singled_out = strictly_largest(mu)
    every_mu = np.array(recomputed, dtype=float)
    quarter = max(1, len(records) // 4)
    distance = distance_from_uniform(weights)
    reached = [steps for steps, success in trace.trace if success >= 0.9]
    return {
        "seed": seed,
        "nt_measure": measure,
        "z_mean_init_gain": kwargs["policy_kwargs"].get("z_mean_init_gain"),
        "iterations": len(records),
        "conflicting_strictly_largest": float(singled_out.mean()),
        "conflicting_strictly_largest_first_quarter": float(singled_out[:quarter].mean()),
        "conflicting_largest_mean_mu_first_six": bool(strictly_largest(mu[:FIRST_ITERATIONS].mean(axis=0))),
        "recomputations": len(recomputed),
        "conflicting_strictly_largest_recomputations": float(strictly_largest(every_mu).mean()),
        "conflicting_largest_mean_mu_first_six_recomputations": bool(
            strictly_largest(every_mu[:FIRST_ITERATIONS].mean(axis=0))
        ),
        "conflicting_strictly_largest_first_six_recomputations": float(
            strictly_largest(every_mu[:FIRST_ITERATIONS]).mean()
        ),
        "conflicting_selected": float(selected[:, -1].mean()),
        "weights_distance_from_uniform": float(distance.mean()),
        "weights_distance_from_uniform_first_quarter": float(distance[:quarter].mean()),
        "mu_over_time": mu.tolist(),
        "weights_distance_over_time": distance.round(5).tolist(),
        "conflicting_mean_weight": float(weights[:, -1].mean()),
        "mean_mu": mu.mean(axis=0).tolist(),
        "mean_weights": weights.mean(axis=0).tolist(),
        "success_trace": trace.trace,
        "env_steps_to_90": reached[0] if reached else None,
        "success": success.as_dict(),
        "train_seconds": round(seconds, 1),
    }


SUMMARISED = (
    "conflicting_strictly_largest",
    "conflicting_strictly_largest_recomputations",
    "conflicting_strictly_largest_first_six_recomputations",
    "conflicting_strictly_largest_first_quarter",
    "conflicting_selected",
    "conflicting_mean_weight",
    "weights_distance_from_uniform",
    "weights_distance_from_uniform_first_quarter",
)


def summarise_group(group: list[dict[str, Any]]) -> dict[str, Any]:
    """[mean, std] over seeds of each SUMMARISED value, success and steps to 90%, and counts of seeds."""
    summary: dict[str, Any] = {
        key: [float(np.mean(values)), float(np.std(values))]
        for key, values in {
            **{key: [r[key] for r in group] for key in SUMMARISED},
            "success": [r["success"]["mean"] for r in group],
            "env_steps_to_90": [r["env_steps_to_90"] or float("nan") for r in group],
        }.items()
    }
    summary["conflicting_mu_largest_on_average"] = sum(
        int(np.argmax(r["mean_mu"]) == len(r["mean_mu"]) - 1) for r in group
    )
    summary["conflicting_weight_smallest_on_average"] = sum(
        int(np.argmin(r["mean_weights"]) == len(r["mean_weights"]) - 1) for r in group
    )
    summary["conflicting_largest_mean_mu_first_six"] = sum(
        int(r["conflicting_largest_mean_mu_first_six"]) for r in group
    )
    summary["seeds"] = len(group)
    return summary


def summarise(runs: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Summaries by measure, or by ``measure, gain z_mean_init_gain`` when the runs are of several gains."""
    gains = sorted({r["z_mean_init_gain"] for r in runs}, key=lambda g: (g is None, g))
    summary = {}
    for measure in MEASURES:
        for gain in gains:
            group = [r for r in runs if r["nt_measure"] == measure and r["z_mean_init_gain"] == gain]
            if group:
                summary[measure if len(gains) == 1 else f"{measure}, gain {gain:g}"] = summarise_group(group)
    return summary


def versions() -> dict[str, str]:
    return {"sb3_mtte": __version__, "torch": th.__version__, "python": platform.python_version()}


def print_and_write(result: dict[str, Any], out: Path | None) -> None:
    """Print the result as JSON and, when ``out`` is given, write it there too."""
    text = json.dumps(result, indent=1)
    print(text)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--measures", nargs="+", choices=MEASURES, default=list(MEASURES))
    parser.add_argument("--gains", type=float, nargs="+", help="z_mean_init_gain values (default: the config's)")
    parser.add_argument("--num-threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()
    th.set_num_threads(args.num_threads)
    budget, kwargs = toy_settings()
    gains = args.gains or [None]
    runs = [
        run(seed, measure, budget, kwargs, gain) for seed in args.seeds for measure in args.measures for gain in gains
    ]
    result = {
        "benchmark": BENCHMARK,
        "env_steps": budget,
        "settings": {k: repr(v) for k, v in kwargs.items()},
        "summary": summarise(runs),
        "runs": runs,
        "versions": versions(),
        "summary_format": "[mean, std] over seeds; counts are out of `seeds`",
        "command": "python scripts/studies/nt_robustness.py --seeds "
        + " ".join(map(str, args.seeds))
        + " --measures "
        + " ".join(args.measures)
        + ("" if args.gains is None else " --gains " + " ".join(f"{g:g}" for g in args.gains)),
    }
    print_and_write(result, args.out)


if __name__ == "__main__":
    main()
