"""Callbacks of the launcher: resumable checkpoints, evaluation with ``best_model.zip``, the score of an optuna
trial."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from rl_zoo3.callbacks import TrialEvalCallback
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_mtte.evaluation import MultiTaskEvalCallback, SuccessResult, evaluate_success
from sb3_mtte.common.update_monitor import record_train_stats
from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.zoo.run_checkpoints import (
    Checkpoint,
    atomic_save,
    checkpoint_paths,
    find_checkpoints,
    restart_envs,
)
from sb3_mtte.experiments.zoo.stopping import StopRequest, TrainingStopped


class MultiTaskCheckpointCallback(BaseCallback):
    """Save model, replay buffer (with the top-K store) and a marker every ``save_freq`` env steps (over all tasks).

    A checkpoint is taken at the start of a rollout, i.e. after the transition of the last step is stored and
    its update is done (SB3's ``CheckpointCallback`` saves before both). Once ``save_freq`` steps have passed,
    it waits for the end of an episode in every sub-env (at most ``save_freq`` more steps), then restarts the
    envs with seeds drawn from (seed, step) (:func:`restart_envs`) and saves. Files are written under a
    temporary name and renamed; the marker ``rl_model_<t>_steps.json`` comes last. A checkpoint whose write fails
    (a full disk) leaves none of its files behind.

    With a ``stop_request`` (:class:`~sb3_mtte.experiments.zoo.stopping.StopRequest`), the first rollout start after
    a Ctrl-C saves a checkpoint there and raises :class:`~sb3_mtte.experiments.zoo.stopping.TrainingStopped`.

    :param save_freq: env steps (all tasks) between checkpoints; None: checkpoints only on a stop request.
    :param save_path: the run folder.
    :param seed: the run seed (env restarts).
    :param eval_env: the evaluation env, reseeded with the training env.
    :param save_replay_buffer: save the replay buffer too.
    :param keep_buffers: replay-buffer files kept (the newest ones); 0 keeps all.
    :param align_to_episodes: wait for the end of an episode before saving.
    :param stop_request: the Ctrl-C of the command, if any.
    :param verbose: 1 prints a line per checkpoint.
    """

    def __init__(
        self,
        save_freq: int | None,
        save_path: str | os.PathLike,
        seed: int = 0,
        eval_env: VecEnv | None = None,
        save_replay_buffer: bool = True,
        keep_buffers: int = 1,
        align_to_episodes: bool = True,
        stop_request: StopRequest | None = None,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        if save_freq is not None and save_freq < 1:
            raise ValueError(f"save_freq must be >= 1, got {save_freq}.")
        self.save_freq, self.save_path, self.seed = save_freq, Path(save_path), int(seed)
        self.eval_env, self.save_replay_buffer = eval_env, save_replay_buffer
        self.keep_buffers, self.align_to_episodes = keep_buffers, align_to_episodes
        self.stop_request = stop_request
        self._next_save: int | None = None

    def _init_callback(self) -> None:
        self.save_path.mkdir(parents=True, exist_ok=True)
        if self.save_freq is not None:
            self._next_save = (self.num_timesteps // self.save_freq + 1) * self.save_freq

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        boundary = bool(np.all(self.model._last_episode_starts))
        if self.stop_request is not None and self.stop_request.requested:
            raise TrainingStopped(self.save(episode_boundary=boundary))
        if self.save_freq is None or self._next_save is None:
            return
        steps = self.num_timesteps
        if steps < self._next_save:
            return
        if self.align_to_episodes and not boundary and steps < self._next_save + self.save_freq:
            return
        self.save(episode_boundary=boundary)
        self._next_save = (steps // self.save_freq + 1) * self.save_freq

    def save(self, episode_boundary: bool) -> Checkpoint:
        """Take a checkpoint now (restarting the envs first when at an episode boundary)."""
        steps = self.num_timesteps
        record_train_stats(self.model)
        if self.model.logger.name_to_value:  # records waiting for the next dump would die with a killed process
            self.model.logger.dump(steps)
        if episode_boundary:
            restart_envs(self.model, self.eval_env, self.seed, steps)
        paths = checkpoint_paths(self.save_path, steps)
        buffer_path = self._save_files(paths)
        meta = self._marker(steps, episode_boundary, buffer_path is not None)
        atomic_save(lambda tmp: Path(tmp).write_text(json.dumps(meta, indent=2) + "\n"), paths["meta"])
        self._prune_buffers()
        if self.verbose >= 1:
            print(f"Saved a checkpoint at {steps:,} env steps: {paths['model']}")
        return Checkpoint(steps, paths["model"], buffer_path, meta)

    def _save_files(self, paths: dict[str, Path]) -> Path | None:
        """Write the replay buffer (when saved) and the model of a checkpoint; return the buffer's path."""
        buffer_path = None
        if self.save_replay_buffer and getattr(self.model, "replay_buffer", None) is not None:
            atomic_save(self.model.save_replay_buffer, paths["replay_buffer"])  # type: ignore[attr-defined]
            buffer_path = paths["replay_buffer"]
        try:
            atomic_save(self.model.save, paths["model"])
        except BaseException:  # no buffer without its model: a checkpoint is whole or absent
            if buffer_path is not None:
                buffer_path.unlink(missing_ok=True)
            raise
        return buffer_path

    def _marker(self, steps: int, episode_boundary: bool, with_buffer: bool) -> dict[str, Any]:
        meta: dict[str, Any] = {
            "timesteps": steps,
            "n_updates": int(getattr(self.model, "_n_updates", 0)),
            "episode_boundary": episode_boundary,
            "envs_restarted": episode_boundary,
            "replay_buffer": with_buffer,
            "time": run_info.now(),
        }
        task_success = getattr(self.model, "_task_success", None)
        if task_success is not None:  # per-task rollout success window (logging), not saved with the model
            meta["task_success"] = [[float(v) for v in window] for window in task_success]
        return meta

    def _prune_buffers(self) -> None:
        if self.keep_buffers <= 0:
            return
        buffers = [c.replay_buffer for c in find_checkpoints(self.save_path) if c.replay_buffer is not None]
        for path in buffers[: -self.keep_buffers]:
            path.unlink(missing_ok=True)


class ZooEvalCallback(MultiTaskEvalCallback):
    """:class:`MultiTaskEvalCallback` that also saves ``best_model.zip`` (highest mean success) like rl-zoo's.

    A tie goes to the later model (as much success, more training): while every evaluation scores 0,
    ``best_model.zip`` is the latest evaluated model, not the one of the first evaluation.
    """

    def __init__(self, *args: Any, best_model_save_path: str | os.PathLike | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.best_model_save_path = best_model_save_path
        self.best_mean_success = -np.inf

    def evaluate(self) -> SuccessResult:
        result = super().evaluate()
        if result.mean >= self.best_mean_success:
            self.best_mean_success = result.mean
            if self.best_model_save_path is not None:
                atomic_save(self.model.save, Path(self.best_model_save_path) / "best_model.zip")
        return result

    def load_history(self, up_to_timesteps: int) -> None:
        """Continue the ``evaluations.npz`` of a resumed run: keep its evaluations up to ``up_to_timesteps``."""
        if self.log_path is None:
            return
        path = Path(self.log_path) / "evaluations.npz"
        if not path.is_file():
            return
        with np.load(path) as data:
            keep = data["timesteps"] <= up_to_timesteps
            self.evaluations_timesteps = [int(t) for t in data["timesteps"][keep]]
            self.evaluations_success = list(np.asarray(data["success_rate"])[keep])
        if self.evaluations_success:
            self.best_mean_success = max(float(np.mean(s)) for s in self.evaluations_success)
            self.save_evaluations()
        else:
            path.unlink()


class SuccessTrialEvalCallback(TrialEvalCallback):
    """rl-zoo's optuna trial callback scoring by the mean success over tasks (Meta-World's protocol,
    ``n_eval_episodes`` per task) instead of the mean return; rl-zoo reports and returns ``last_mean_reward``."""

    def _on_step(self) -> bool:
        if self.eval_freq <= 0 or self.n_calls % self.eval_freq != 0:
            return True
        result = evaluate_success(self.model, self.eval_env, self.n_eval_episodes, self.deterministic)
        self.last_mean_reward = result.mean
        self.eval_idx += 1
        self.trial.report(self.last_mean_reward, self.eval_idx)
        self.is_pruned = self.trial.should_prune()
        return not self.is_pruned
