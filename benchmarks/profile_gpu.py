"""Where the fast path's time goes in ``learn()`` on a GPU: the wall time of a vector step split into acting, env
stepping, storing and the update (each timed with the device synchronised around it), the device's busy share, the
top ops by device and by host time (torch.profiler), and the env stepping alone under each VecEnv class. Writes
``--out`` (JSON) and prints the tables.

    python benchmarks/profile_gpu.py --benchmarks MT10 MT50 --out profile_gpu.json
    python benchmarks/profile_gpu.py --benchmarks MT10 --vector-steps 10 --device cpu   # a dry run
"""

from __future__ import annotations

import sb3_mtte

sb3_mtte.tune_process()  # before torch loads, as the package's commands do

# isort: split

import argparse
import json
import os
import time
from collections import defaultdict
from contextlib import contextmanager

import numpy as np
import torch as th
from bench_updates import quiet, time_once
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

from sb3_mtte import MTSAC, MTSACTE, make_mt_env
from sb3_mtte.common import gpu_defaults
from sb3_mtte.experiments.env_ids import default_vec_env

STAGES = {"act": "_sample_action", "store": "_store_transition", "update": "train"}
"""The model's methods timed as stages of a vector step; the env's ``step`` is the fourth."""


def synchronize(device: str) -> None:
    if device == "cuda":
        th.cuda.synchronize()


@contextmanager
def timed_stages(model, device: str):
    """Wrap the stages' methods on this instance so each call adds its synchronised wall time to the yielded dict;
    the wrappers are removed on exit."""
    seconds: dict[str, float] = defaultdict(float)
    wrapped = [(model, name, stage) for stage, name in STAGES.items()] + [(model.env, "step", "env")]
    own = [name in vars(owner) for owner, name, _ in wrapped]  # an instance attribute already: put it back on exit
    originals = [getattr(owner, name) for owner, name, _ in wrapped]
    for (owner, name, stage), original in zip(wrapped, originals, strict=True):

        def wrapper(*args, original=original, stage=stage, **kwargs):
            synchronize(device)
            start = time.perf_counter()
            result = original(*args, **kwargs)
            synchronize(device)
            seconds[stage] += time.perf_counter() - start
            return result

        setattr(owner, name, wrapper)
    try:
        yield seconds
    finally:
        for (owner, name, _), original, was_own in zip(wrapped, originals, own, strict=True):
            if was_own:
                setattr(owner, name, original)
            else:
                delattr(owner, name)


def learn_seconds(model, device: str, vector_steps: int) -> float:
    synchronize(device)
    return time_once(lambda: model.learn(vector_steps * model.n_tasks, reset_num_timesteps=False))


def split_vector_step(model, device: str, vector_steps: int) -> dict:
    """Milliseconds per vector step of each stage and of the rest, over ``vector_steps`` steps of ``learn()``, and
    the env steps/s of the same number of steps untimed before them."""
    untimed = learn_seconds(model, device, vector_steps)
    with timed_stages(model, device) as seconds:
        wall = learn_seconds(model, device, vector_steps)
    per_step = {stage: 1e3 * s / vector_steps for stage, s in seconds.items()}
    per_step["rest"] = 1e3 * wall / vector_steps - sum(per_step.values())
    return {
        "ms_per_vector_step": {k: round(v, 3) for k, v in per_step.items()},
        "env_steps_per_s": round(vector_steps * model.n_tasks / wall, 1),
        "untimed_env_steps_per_s": round(vector_steps * model.n_tasks / untimed, 1),
    }


def profile_learn(model, device: str, vector_steps: int, rows: int) -> dict:
    """torch.profiler over ``vector_steps`` steps of ``learn()``: the share of that time the device ran kernels, and
    the top kernels (device time) and host ops (self time)."""
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    with profile(activities=activities) as prof:
        wall_us = 1e6 * learn_seconds(model, device, vector_steps)
    kernel_us: dict[str, float] = defaultdict(float)
    for event in prof.key_averages():
        if event.device_type == DeviceType.CUDA:
            kernel_us[event.key[:60]] += event.self_device_time_total
    host = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)[:rows]
    kernels = sorted(kernel_us.items(), key=lambda item: item[1], reverse=True)[:rows]
    return {
        "device_busy_share": round(sum(kernel_us.values()) / wall_us, 3),
        "profiled_env_steps_per_s": round(vector_steps * model.n_tasks / (wall_us / 1e6), 1),
        "top_by_device_us_per_vector_step": {key: round(us / vector_steps, 1) for key, us in kernels},
        "top_by_host_us_per_vector_step": {e.key[:60]: round(e.self_cpu_time_total / vector_steps, 1) for e in host},
    }


def env_rate(benchmark: str, vec_env_cls, vector_steps: int) -> float:
    """Env steps/s of the VecEnv alone, random actions, after one untimed step."""
    env = make_mt_env(benchmark, seed=0, vec_env_cls=vec_env_cls)
    env.reset()
    actions = lambda: np.stack([env.action_space.sample() for _ in range(env.num_envs)])  # noqa: E731
    env.step(actions())
    start = time.perf_counter()
    for _ in range(vector_steps):
        env.step(actions())
    rate = vector_steps * env.num_envs / (time.perf_counter() - start)
    env.close()
    return round(rate, 1)


def profile_benchmark(benchmark: str, device: str, vector_steps: int, rows: int) -> dict:
    fast_cls = SubprocVecEnv if default_vec_env(benchmark) == "subproc" else DummyVecEnv
    result: dict = {"vec_env": fast_cls.__name__, "env_alone_env_steps_per_s": {}}
    for cls in (DummyVecEnv, SubprocVecEnv):
        result["env_alone_env_steps_per_s"][cls.__name__] = env_rate(benchmark, cls, vector_steps)
    env = make_mt_env(benchmark, seed=0, vec_env_cls=fast_cls)
    for label, algorithm in (("MTSAC", MTSAC), ("MTSACTE", MTSACTE)):
        n_tasks = env.num_envs
        model = quiet(algorithm("MlpPolicy", env, learning_starts=64 * n_tasks, buffer_size=2000 * n_tasks,
                                device=device, seed=0))  # fmt: skip
        model.learn(model.learning_starts + 10 * n_tasks)  # the warm-up, the graph's capture, a first recomputation
        result[label] = profile_learn(model, device, vector_steps, rows)
        result[label].update(split_vector_step(model, device, vector_steps))
    env.close()
    return result


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--benchmarks", nargs="+", default=["MT10", "MT50"], choices=["MT10", "MT50"])
    parser.add_argument("--vector-steps", type=int, default=100, help="vector steps of each timed learn()")
    parser.add_argument("--rows", type=int, default=12, help="ops in each top table")
    parser.add_argument("--device", default="auto", help="cuda, cpu or auto (default)")
    parser.add_argument("--out", default=None, help="also write the JSON here, after every benchmark")
    args = parser.parse_args(argv)
    gpu_defaults.FAST_PATH_BY_DEFAULT = True
    device = ("cuda" if th.cuda.is_available() else "cpu") if args.device == "auto" else args.device
    name = th.cuda.get_device_name(0) if device == "cuda" else "cpu"
    report: dict = {"device": device, "device_name": name, "torch": th.__version__, "cpu_count": os.cpu_count(),
                    "vector_steps": args.vector_steps}  # fmt: skip
    for benchmark in args.benchmarks:
        report[benchmark] = profile_benchmark(benchmark, device, args.vector_steps, args.rows)
        if args.out:
            with open(args.out, "w") as file:
                json.dump(report, file, indent=1)
    print(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
