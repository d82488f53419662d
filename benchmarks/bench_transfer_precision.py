"""Cost of one J^rep step of MTSACTE with the transfer matrix in float32 (the old computation) and in float64.

One step draws a batch, computes the N x N transfer matrix (Eq. 4-5) in the given dtype, reads mu, C_s and w
(Eq. 6-8), takes the gradient of J^rep (Eq. 14) and steps Adam. Both dtypes alternate in one run, on the
package's default networks (2 x 400) and N tasks of Meta-World's shapes. Prints one JSON object.

    python benchmarks/bench_transfer_precision.py --rounds 7 --repeats 5
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

import numpy as np
import torch as th
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_mtte import MTSACTE, __version__
from sb3_mtte.envs.wrappers import OneHotTaskWrapper
from sb3_mtte.mtsacte.objectives import select_tasks
from sb3_mtte.mtsacte.transfer import RepresentationBatch, TaskObjectives, representation_gradients, transfer_matrix

STATE_DIM, ACTION_DIM = 39, 4


def make_model(n_tasks: int) -> MTSACTE:
    """An MTSACTE with the default networks on N Pendulum-shaped sub-envs widened to Meta-World's 39-d state."""
    import gymnasium as gym

    class Task(gym.Env):
        observation_space = gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32)
        action_space = gym.spaces.Box(-1, 1, (ACTION_DIM,), np.float32)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            return self.observation_space.sample(), {}

        def step(self, action):
            return self.observation_space.sample(), 0.0, False, False, {}

    envs = [lambda i=i: OneHotTaskWrapper(Task(), i, n_tasks, f"task{i}") for i in range(n_tasks)]
    return MTSACTE("MlpPolicy", DummyVecEnv(envs), seed=0, device="cpu", learning_starts=0)


def rep_step(model: MTSACTE, obs: th.Tensor, dtype: th.dtype, harmful: th.Tensor) -> None:
    """One J^rep step as MTSACTE.update_representation takes it, the transfer matrix in ``dtype``."""
    batch = RepresentationBatch.draw(obs, model.policy.z_dim, model.policy.action_dim)
    objectives = TaskObjectives(model.policy, batch, model.entropy_coefficients, chunk_size=1)
    with th.no_grad():
        z = objectives.embedding(objectives.phi()[0])[0]
        matrix = transfer_matrix(objectives, z, model.nt_step_size, dtype=dtype)
    select_tasks(matrix, model.n_select, th.float32)
    _, enc_grads, dec_grads = representation_gradients(
        objectives, harmful, step_size=model.nt_step_size, c_vae=model.c_vae
    )
    model._apply_gradients(enc_grads, dec_grads)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-tasks", type=int, default=10)
    parser.add_argument("--batch-size", type=int, default=128, help="L, per task")
    parser.add_argument("--rounds", type=int, default=7, help="alternating rounds of both dtypes")
    parser.add_argument("--repeats", type=int, default=5, help="J^rep steps timed per round and dtype")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None, help="also write the JSON here")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    th.manual_seed(0)
    model = make_model(args.n_tasks)
    n, dim = args.n_tasks, STATE_DIM + args.n_tasks
    obs = th.cat([th.randn(n, args.batch_size, STATE_DIM), th.eye(n)[:, None].expand(n, args.batch_size, n)], -1)
    assert obs.shape[-1] == dim
    harmful = th.arange(n - model.n_select)  # |C \ C_s| = N - M, the same for both dtypes
    names = {"float32": th.float32, "float64": th.float64}
    times: dict[str, list[float]] = {name: [] for name in names}
    for dtype in names.values():  # warm-up
        rep_step(model, obs, dtype, harmful)
    for _ in range(args.rounds):
        for name, dtype in names.items():
            start = time.perf_counter()
            for _ in range(args.repeats):
                rep_step(model, obs, dtype, harmful)
            times[name].append((time.perf_counter() - start) / args.repeats)
    medians = {name: statistics.median(values) for name, values in times.items()}
    result = {
        "command": "python benchmarks/bench_transfer_precision.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if v is not None and k != "out"),
        "sb3_mtte": __version__,
        "torch": th.__version__,
        "processor": platform.processor() or platform.machine(),
        "seconds_per_rep_step": {name: {"median": medians[name], "rounds": times[name]} for name in names},
        "ratio_float64_to_float32": medians["float64"] / medians["float32"],
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        with open(args.out, "w") as file:
            file.write(text + "\n")


if __name__ == "__main__":
    main()
