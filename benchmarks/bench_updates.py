"""Throughput of one gradient update (and env stepping) for SB3's SAC, every MTSAC variant and MTSACTE.

Prints one JSON object. Updates run on synthetic replay data of N tasks x L transitions (39-d state + one-hot,
4-d actions, 2x400 nets by default, ``--net-arch``: the Meta-World setting); every ratio compares timings taken in
the same run.

    python benchmarks/bench_updates.py --n-tasks 10 20 50 --device cpu
    python benchmarks/bench_updates.py --n-tasks 10 --env-steps 200   # + Meta-World MT10 vector steps/s
    python benchmarks/bench_updates.py --n-tasks 10 --net-arch 400 400 400
"""

from __future__ import annotations

import sb3_mtte

sb3_mtte.tune_process()  # before torch loads, as the package's commands do

# isort: split

import argparse
import json
import platform
import statistics
import time
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import DummyVecEnv
from torch.utils.flop_counter import FlopCounterMode

from sb3_mtte import MTSAC, MTSACTE, __version__
from sb3_mtte.common.relu_mlp import fused_relu_mlp
from sb3_mtte.common.utils import polyak_update
from sb3_mtte.experiments.variants import VARIANTS as REGISTERED_VARIANTS

STATE_DIM, ACTION_DIM = 39, 4
VARIANTS = {
    f"MTSAC-{variant.label.removeprefix('SAC-')}": (variant.build.policy, dict(variant.build.overrides))
    for variant in REGISTERED_VARIANTS.values()
    if variant.build.algorithm is MTSAC
}
"""Label -> (policy, keyword arguments) of every MTSAC variant of the registry (default network sizes)."""
VARIANTS["MTSAC-MT-shared-critic"] = ("MlpPolicy", {"critic_arch": "shared"})


class SyntheticTaskEnv(gym.Env):
    """A sub-env with the Meta-World layout (39-d state + one-hot) and random observations."""

    def __init__(self, index: int, n_tasks: int) -> None:
        self.index, self.n_tasks, self.task_name = index, n_tasks, f"task{index}"
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (STATE_DIM + n_tasks,), np.float32)
        self.action_space = gym.spaces.Box(-1, 1, (ACTION_DIM,), np.float32)

    def _obs(self) -> np.ndarray:
        obs = np.zeros(STATE_DIM + self.n_tasks, np.float32)
        obs[:STATE_DIM] = self.np_random.normal(size=STATE_DIM)
        obs[STATE_DIM + self.index] = 1.0
        return obs

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        return self._obs(), {}

    def step(self, action):
        return self._obs(), float(self.np_random.normal()), False, False, {"is_success": False}


def synthetic_env(n_tasks: int) -> DummyVecEnv:
    return DummyVecEnv([lambda i=i: SyntheticTaskEnv(i, n_tasks) for i in range(n_tasks)])


def fill_buffer(model, n_rows: int) -> None:
    """Fill the replay buffer with random transitions (one row per sub-env and step)."""
    buffer = model.replay_buffer
    n_envs = buffer.n_envs
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(n_rows, n_envs, buffer.obs_shape[0])).astype(np.float32)
    obs[..., STATE_DIM:] = 0
    if obs.shape[-1] > STATE_DIM:
        obs[..., STATE_DIM:] = np.eye(n_envs, obs.shape[-1] - STATE_DIM, dtype=np.float32)[None]
    buffer.observations[:n_rows] = obs
    buffer.next_observations[:n_rows] = obs
    buffer.actions[:n_rows] = rng.uniform(-1, 1, size=buffer.actions[:n_rows].shape)
    buffer.rewards[:n_rows] = rng.normal(size=(n_rows, n_envs))
    buffer.pos = n_rows


def time_once(fn: Callable[[], None]) -> float:
    start = time.perf_counter()
    fn()
    if th.cuda.is_available():
        th.cuda.synchronize()
    return time.perf_counter() - start


def interleaved_medians(fns: dict[str, Callable[[], None]], repeats: int, warmup: int = 3) -> dict[str, float]:
    """Median time of each function, timed round-robin so that drifts of the machine hit every one alike."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    times: dict[str, list[float]] = {label: [] for label in fns}
    for _ in range(repeats):
        for label, fn in fns.items():
            times[label].append(time_once(fn))
    return {label: statistics.median(values) for label, values in times.items()}


def matmul_probes(total_batch: int, device: str) -> dict[str, tuple[Callable[[], None], float]]:
    """Dense ``torch.mm`` at the update's own layer shape and at 2048^2: the machine's matmul peak, timed beside the
    updates. Label -> (function, GFLOP of one call)."""
    probes = {}
    for label, (m, k, n) in {"mm-update-shape": (total_batch, 400, 400), "mm-2048": (2048, 2048, 2048)}.items():
        a, b = th.randn(m, k, device=device), th.randn(k, n, device=device)
        probes[label] = (lambda a=a, b=b: th.mm(a, b), 2 * m * k * n / 1e9)
    return probes


def layer_by_layer(update: Callable[[], None]) -> Callable[[], None]:
    """The same update with every ReLU MLP as its layer-by-layer autograd graph instead of one node."""

    def run() -> None:
        with fused_relu_mlp(False):
            update()

    return run


def critic_parameter_passes(model) -> Callable[[], None]:
    """The critic's Adam step and Polyak update: memory-bound passes over its parameters, N times as many with
    per-task critics (run after an update, so that the gradients exist)."""

    def passes() -> None:
        model.critic.optimizer.step()
        polyak_update(model.critic.parameters(), model.critic_target.parameters(), model.tau)

    return passes


def update_gflop(update: Callable[[], None]) -> float:
    """Matmul GFLOP of one update (after a first one), counted by ``torch.utils.flop_counter``."""
    update()
    with FlopCounterMode(display=False) as counter:
        update()
    return counter.get_total_flops() / 1e9


def quiet(model):
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


def bench_n_tasks(n_tasks: int, batch_per_task: int, device: str, repeats: int, net_arch: list[int]) -> dict:
    total_batch = n_tasks * batch_per_task
    rows = 4 * batch_per_task
    updates: dict[str, Callable[[], None]] = {}

    sac = quiet(
        SAC(
            "MlpPolicy",
            synthetic_env(n_tasks),
            policy_kwargs={"net_arch": net_arch},
            buffer_size=rows * n_tasks,
            device=device,
            seed=0,
        )
    )
    fill_buffer(sac, rows)
    updates["SB3-SAC"] = lambda: sac.train(1, total_batch)

    critic_passes: dict[str, Callable[[], None]] = {}
    for label, (policy, kwargs) in VARIANTS.items():
        model = quiet(
            MTSAC(
                policy,
                synthetic_env(n_tasks),
                buffer_size=rows * n_tasks,
                device=device,
                seed=0,
                policy_kwargs={"net_arch": net_arch},
                **kwargs,
            )
        )
        fill_buffer(model, rows)
        updates[label] = lambda m=model: m.train(1, batch_per_task)
        if label in ("MTSAC-MT", "MTSAC-MT-shared-critic"):
            critic_passes[f"critic-parameter-passes:{label}"] = critic_parameter_passes(model)
            updates[f"{label} (layer by layer)"] = layer_by_layer(updates[label])

    te = quiet(
        MTSACTE(
            "MlpPolicy",
            synthetic_env(n_tasks),
            buffer_size=rows * n_tasks,
            device=device,
            seed=0,
            policy_kwargs={"net_arch": net_arch},
        )
    )
    fill_buffer(te, rows)
    te._last_iteration_start = 0  # the every-step update alone: no recomputation is due at num_timesteps 0
    updates["MTSACTE-update"] = lambda: te.train(1, batch_per_task)
    probes = matmul_probes(total_batch, device)
    gflop = {label: update_gflop(fn) for label, fn in updates.items()}
    results = interleaved_medians(
        {**updates, **critic_passes, **{label: fn for label, (fn, _) in probes.items()}}, repeats
    )
    peak = {label: flop / results.pop(label) for label, (_, flop) in probes.items()}
    passes = {label.split(":")[1]: results.pop(label) for label in critic_passes}

    recomputations: dict[str, Callable[[], None]] = {}
    for estimator in ("virtual_step", "gradient_dot"):
        model = quiet(
            MTSACTE(
                "MlpPolicy",
                synthetic_env(n_tasks),
                buffer_size=rows * n_tasks,
                device=device,
                seed=0,
                nt_estimator=estimator,
                rep_gradient_steps=1,
                policy_kwargs={"net_arch": net_arch},
            )
        )
        fill_buffer(model, rows)
        recomputations[f"MTSACTE-recompute-{estimator}"] = lambda m=model: m.update_representation(batch_per_task)
    results.update(interleaved_medians(recomputations, max(3, repeats // 3), warmup=1))

    base = results["SB3-SAC"]
    report = {
        "n_tasks": n_tasks,
        "total_batch": total_batch,
        "seconds": {k: round(v, 5) for k, v in results.items()},
        "updates_per_s": {k: round(1 / v, 2) for k, v in results.items() if "recompute" not in k},
        "ratio_to_sb3_sac": {k: round(v / base, 3) for k, v in results.items()},
        "recompute_over_mtsac_update": {
            k: round(v / results["MTSAC-MT"], 2) for k, v in results.items() if "recompute" in k
        },
        "one_node_mlp_speedup": {
            k: round(results[f"{k} (layer by layer)"] / results[k], 3) for k in ("MTSAC-MT", "MTSAC-MT-shared-critic")
        },
        "per_task_over_shared_critic": round(results["MTSAC-MT"] / results["MTSAC-MT-shared-critic"], 3),
        "critic_parameter_passes_seconds": {k: round(v, 5) for k, v in passes.items()},
        # the ratio if the per-task critics cost what the shared one costs in everything but these passes
        "per_task_over_shared_floor": round(
            1 + (passes["MTSAC-MT"] - passes["MTSAC-MT-shared-critic"]) / results["MTSAC-MT-shared-critic"], 3
        ),
        "matmul_peak_gflops": {k: round(v, 1) for k, v in peak.items()},
        "update_gflop": {k: round(v, 2) for k, v in gflop.items()},
        "achieved_gflops": {k: round(gflop[k] / results[k], 1) for k in gflop},
        "fraction_of_peak": {k: round(gflop[k] / results[k] / max(peak.values()), 3) for k in gflop},
    }
    return report


def bench_env_steps(n_tasks: int, steps: int) -> float:
    from sb3_mtte import make_mt_env

    benchmark = {10: "MT10", 20: "MT20", 50: "MT50"}[n_tasks]
    env = make_mt_env(benchmark, seed=0)
    env.reset()
    actions = np.zeros((n_tasks, ACTION_DIM), np.float32)
    start = time.perf_counter()
    for _ in range(steps):
        env.step(actions)
    return steps / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-tasks", type=int, nargs="+", default=[10, 20, 50])
    parser.add_argument("--batch-per-task", type=int, default=128)
    parser.add_argument("--net-arch", type=int, nargs="+", default=[400, 400], help="hidden widths of every network")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--env-steps", type=int, default=0, help="vector steps of Meta-World to time (0: skip)")
    parser.add_argument("--iteration-length", type=int, default=500)
    parser.add_argument("--rep-gradient-steps", type=int, default=10)
    parser.add_argument("--nt-estimator", choices=("virtual_step", "gradient_dot"), default="virtual_step")
    parser.add_argument(
        "--end-to-end",
        type=int,
        default=0,
        help="also time real MT10 learn() of MTSAC and MTSACTE over this many vector steps",
    )
    args = parser.parse_args(argv)
    device = ("cuda" if th.cuda.is_available() else "cpu") if args.device == "auto" else args.device

    report = {
        "device": device,
        "torch_threads": th.get_num_threads(),
        "net_arch": args.net_arch,
        "versions": {"sb3_mtte": __version__, "torch": th.__version__, "python": platform.python_version()},
        "results": [],
    }
    for n_tasks in args.n_tasks:
        entry = bench_n_tasks(n_tasks, args.batch_per_task, device, args.repeats, args.net_arch)
        seconds = entry["seconds"]
        recompute = seconds[f"MTSACTE-recompute-{args.nt_estimator}"]
        env_step = 0.0
        if args.env_steps:
            env_rate = bench_env_steps(n_tasks, args.env_steps)
            entry["env_vector_steps_per_s"] = round(env_rate, 1)
            entry["env_steps_per_s"] = round(env_rate * n_tasks, 1)
            env_step = 1 / env_rate
        # Per vector step: env step + update (+ R recomputations by the chosen estimator every H steps).
        entry["schedule"] = {k: getattr(args, k) for k in ("iteration_length", "rep_gradient_steps", "nt_estimator")}
        mtsac_step = env_step + seconds["MTSAC-MT"]
        te_step = env_step + seconds["MTSACTE-update"] + args.rep_gradient_steps * recompute / args.iteration_length
        entry["train_step_seconds"] = {
            "SB3-SAC": round(env_step + seconds["SB3-SAC"], 5),
            "MTSAC-MT": round(mtsac_step, 5),
            "MTSACTE": round(te_step, 5),
        }
        entry["mtsacte_over_mtsac_per_vector_step"] = round(te_step / mtsac_step, 3)
        if env_step:
            entry["train_env_steps_per_s"] = {
                label: round(n_tasks / (env_step + seconds[label]), 1)
                for label in ("SB3-SAC", *VARIANTS, "MTSACTE-update")
            }
            entry["train_env_steps_per_s"]["MTSACTE"] = round(n_tasks / te_step, 1)
        report["results"].append(entry)
    if len(args.n_tasks) > 1 and 10 in args.n_tasks:
        first = next(r for r in report["results"] if r["n_tasks"] == 10)
        report["recompute_scaling_vs_n10"] = {
            str(r["n_tasks"]): {
                est: round(r["seconds"][f"MTSACTE-recompute-{est}"] / first["seconds"][f"MTSACTE-recompute-{est}"], 2)
                for est in ("virtual_step", "gradient_dot")
            }
            for r in report["results"]
        }
    if args.end_to_end:
        report["end_to_end_mt10"] = bench_end_to_end(args.end_to_end, device)
    print(json.dumps(report, indent=2))
    return report


def learn_rate(model, vector_steps: int) -> float:
    """Env steps/s of ``learn()`` over ``vector_steps`` vector steps after learning starts (the random warm-up, the
    first updates and MTSACTE's first recomputation untimed)."""
    n_tasks = model.n_tasks
    model.learn(model.learning_starts + 10 * n_tasks)
    if th.cuda.is_available():
        th.cuda.synchronize()
    seconds = time_once(lambda: model.learn(vector_steps * n_tasks, reset_num_timesteps=False))
    return vector_steps * n_tasks / seconds


def bench_end_to_end(vector_steps: int, device: str) -> dict:
    """Wall time of learn() on MT10 after learning starts: env stepping, updates and the every-H work included."""
    from sb3_mtte import make_mt_env

    seconds = {}
    for label, cls in (("MTSAC-MT", MTSAC), ("MTSACTE", MTSACTE)):
        env = make_mt_env("MT10", seed=0)
        model = quiet(cls("MlpPolicy", env, learning_starts=2560, buffer_size=200_000, device=device, seed=0))
        seconds[label] = vector_steps * 10 / learn_rate(model, vector_steps)
    return {
        "vector_steps": vector_steps,
        "seconds": {k: round(v, 2) for k, v in seconds.items()},
        "env_steps_per_s": {k: round(vector_steps * 10 / v, 1) for k, v in seconds.items()},
        "mtsacte_over_mtsac": round(seconds["MTSACTE"] / seconds["MTSAC-MT"], 3),
    }


if __name__ == "__main__":
    main()
