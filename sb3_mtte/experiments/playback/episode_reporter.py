"""The episode report of ``enjoy``: a VecEnv wrapper that prints every finished episode and the success rates.

``enjoy`` hands it to :class:`~sb3_mtte.experiments.env_ids.MultiTaskVecEnvFactory` as the wrapper of its envs.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from sb3_mtte.common.utils import get_task_names


class EpisodeReporter(VecEnvWrapper):
    """Print every finished episode (task, return, success) and, on close, the success rate of each task; a task
    with no finished episode gets its unfinished one (return, length and success so far)."""

    def __init__(self, venv: VecEnv) -> None:
        super().__init__(venv)
        self.task_names = get_task_names(venv)
        self.successes: list[list[bool]] = [[] for _ in range(venv.num_envs)]
        self.returns = np.zeros(venv.num_envs)
        self.lengths = np.zeros(venv.num_envs, dtype=int)
        self.success_so_far = np.zeros(venv.num_envs, dtype=bool)

    def reset(self) -> Any:
        return self.venv.reset()

    def step_wait(self) -> Any:
        obs, rewards, dones, infos = self.venv.step_wait()
        self.returns += rewards
        self.lengths += 1
        self.success_so_far = np.array([bool(info.get("is_success", False)) for info in infos])
        for i in np.flatnonzero(dones):
            self.successes[i].append(bool(self.success_so_far[i]))
            episode = infos[i].get("episode", {})
            print(
                f"task {i:2d} {self.task_names[i]:<28} return {episode.get('r', float('nan')):9.2f}  "
                f"length {episode.get('l', '-')!s:>4}  success {self.success_so_far[i]}"
            )
            self.returns[i], self.lengths[i] = 0.0, 0
        return obs, rewards, dones, infos

    def close(self) -> None:
        if any(self.successes):
            print("Success rate per task (episodes finished):")
            for name, results in zip(self.task_names, self.successes, strict=True):
                if results:
                    print(f"  {name:<28} {100 * np.mean(results):5.1f}% ({len(results)})")
        unfinished = [i for i, results in enumerate(self.successes) if not results and self.lengths[i] > 0]
        if unfinished:
            print(f"No episode finished for {len(unfinished)} task(s) (pass a larger -n); the unfinished episodes:")
            for i in unfinished:
                print(
                    f"  task {i:2d} {self.task_names[i]:<28} return {self.returns[i]:9.2f}  "
                    f"length {self.lengths[i]:>4}  success so far {self.success_so_far[i]}"
                )
        self.venv.close()
