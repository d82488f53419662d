"""rl-zoo3's ``ExperimentManager`` with one sub-env per task, multi-task evaluation, resumable checkpoints and
run metadata.

Everything else is rl-zoo's: hyperparameter files and ``-params`` overrides, run folders
``<log-folder>/<algo>/<env>_<id>/``, ``config.yml``/``args.yml``, optuna, ``-i`` continued training, ...
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import os
import re
from collections import OrderedDict, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from rl_zoo3.utils import ALGOS
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import ProgressBarCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_mtte.common.utils import get_task_names
from sb3_mtte.mtsac.checks import check_arguments
from sb3_mtte.envs import env_protocol, official_env_kwargs, reward_function_version
from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.env_ids import MultiTaskVecEnvFactory, benchmark_task_names, env_id_n_tasks, split_env_id
from sb3_mtte.experiments.zoo.adapter import ZooExperimentManager
from sb3_mtte.experiments.zoo.configs import LAUNCHER_YAML_KEYS, family_config_path, unknown_key_message
from sb3_mtte.experiments.zoo.env_backend import check_env_kwargs_flags, prepare_backend
from sb3_mtte.experiments.zoo.resume import RunFolderSettings
from sb3_mtte.experiments.zoo.run_checkpoints import (
    Checkpoint,
    atomic_save,
    final_checkpoint,
    find_latest_checkpoint,
    load_model,
    missing_folders,
    remove_made_folders,
    restart_envs,
)
from sb3_mtte.experiments.zoo.run_logs import make_run_logger, set_aside_monitor_files, trim_jsonl
from sb3_mtte.experiments.zoo.stopping import Stop, StopRequest, TrainingStopped, end_stopped_run
from sb3_mtte.experiments.zoo.training_callbacks import (
    MultiTaskCheckpointCallback,
    SuccessTrialEvalCallback,
    ZooEvalCallback,
)
from sb3_mtte.mtsacte.callbacks import NT_LOG_FILE


@dataclass
class LaunchOptions:
    """Options of the launcher that rl-zoo's argument parser does not know."""

    resume_dir: str | None = None
    exp_id: int | None = None
    flags_given: frozenset[str] = frozenset()
    """The settings the command line gives (:func:`~sb3_mtte.experiments.zoo.run_settings.given_settings`)."""
    keep_buffers: int = 1
    align_checkpoints: bool = True
    tensorboard: bool = True
    hyperparams: dict[str, dict[str, Any]] | None = None
    """Every env entry of the variant's hyperparameters (:mod:`~sb3_mtte.experiments.zoo.configs`); None: rl-zoo reads
    its ``-conf`` file."""


class MultiTaskExperimentManager(RunFolderSettings, ZooExperimentManager):
    """rl-zoo's ExperimentManager with one sub-env per task, multi-task evaluation, resumable checkpoints
    and run metadata (see the module docstring).

    It overrides public methods of rl-zoo's only; its private steps go through
    :class:`~sb3_mtte.experiments.zoo.adapter.ZooExperimentManager`.
    """

    trial_eval_callback_class = SuccessTrialEvalCallback  # an optuna trial is scored by success, not return

    def __init__(self, args: argparse.Namespace, algo: str, env_id: str, *pos: Any, **kwargs: Any) -> None:
        self.launch: LaunchOptions = kwargs.pop("launch", None) or LaunchOptions()
        super().__init__(args, algo, env_id, *pos, **kwargs)
        if self.launch.hyperparams is not None:
            self.config = str(family_config_path(algo))
        self.env_id = env_id
        self.benchmark = split_env_id(env_id)[0]
        self.n_tasks = env_id_n_tasks(env_id)
        self.vec_env_class = MultiTaskVecEnvFactory(self.n_tasks, seed=self.seed, vec_env_cls=self.vec_env_class)
        # tensorboard events go through the run logger (make_run_logger), not the model's own
        self.tensorboard_dir = self.tensorboard_log
        self.tensorboard_log = None
        if self.launch.resume_dir is not None:
            self.save_path = os.path.normpath(self.launch.resume_dir)
            self.params_path = f"{self.save_path}/{self.env_name}"
            self.restore_run_settings()
            self.refuse_a_finished_resume()
        elif self.launch.exp_id is not None:
            self.save_path = os.path.join(self.log_path, f"{self.env_name}_{self.launch.exp_id}")
            self.params_path = f"{self.save_path}/{self.env_name}"
            self.check_the_run_folder()
        self.checkpoint: Checkpoint | None = None
        self.resumed = False  # from a checkpoint
        self.resume_step: int | None = None  # step the logs are trimmed to (0: resumed without checkpoint)
        self.checkpoint_callback: MultiTaskCheckpointCallback | None = None
        self.eval_callback: ZooEvalCallback | None = None
        self._eval_env: VecEnv | None = None
        self.stop_request = StopRequest()
        self.stopped: Stop | None = None
        check_env_kwargs_flags(self.benchmark, self.env_kwargs, self.eval_env_kwargs, self.eval_env_kwargs_given)
        prepare_backend(self.env_kwargs, self.vec_env_class)

    # ---- hyperparameters
    def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
        if self.launch.resume_dir is not None:
            hyperparams = self._read_run_hyperparameters()
        elif self.launch.hyperparams is not None:
            hyperparams = self._read_variant_hyperparameters(self.launch.hyperparams)
        else:
            hyperparams, _ = super().read_hyperparameters()
        unknown = unknown_key_message(self.algo, hyperparams, self._source_of)
        if unknown:
            raise SystemExit(unknown)
        n_envs = hyperparams.get("n_envs")
        if n_envs is not None and int(n_envs) != self.n_tasks:
            raise ValueError(f"n_envs={n_envs} in the hyperparameters, but {self.env_id} has {self.n_tasks} tasks.")
        hyperparams["n_envs"] = self.n_tasks
        for key in LAUNCHER_YAML_KEYS:
            value = hyperparams.pop(key, None)
            if value is None or key in self.launch.flags_given:
                continue
            if key == "eval_freq":
                self.eval_freq = int(value)
            elif key == "eval_episodes":
                self.n_eval_episodes = int(value)
            else:
                self.save_freq = int(value)
        if self.eval_env_kwargs_given is None:  # evaluated on Meta-World's own envs, also when trained on EnvPool
            self.eval_env_kwargs = official_env_kwargs(self.env_kwargs)
        self._check_arguments(hyperparams)
        saved = OrderedDict((key, hyperparams[key]) for key in sorted(hyperparams))
        saved.update({key: value for key, value in self._zoo_yaml_values().items()})
        saved = OrderedDict((key, saved[key]) for key in sorted(saved))
        return hyperparams, saved

    def _check_arguments(self, hyperparams: dict[str, Any]) -> None:
        """The constructor's type and range checks (one table per class) on the hyperparameters as rl-zoo will pass
        them, before any folder exists."""
        rate = hyperparams.get("learning_rate")
        if isinstance(rate, str) and not re.fullmatch(r"lin_[0-9.eE+-]+", rate):  # rl-zoo's one schedule string
            raise ValueError(
                f"learning_rate must be a positive number such as 3e-4, or 'lin_<initial>' for rl-zoo's linear "
                f"schedule, got learning_rate={rate!r}."
            )
        verbose, self.verbose = self.verbose, 0  # the dry pass prints nothing
        try:
            processed = self.preprocess_hyperparams(copy.deepcopy(dict(hyperparams)))[0]
        finally:
            self.verbose = verbose
        check_arguments(ALGOS[self.algo], {**processed, "seed": self.seed}, n_tasks=self.n_tasks)

    def _source_of(self, key: str) -> str:
        """Where a hyperparameter was given: ``-params``, else the file read."""
        if key in (self.custom_hyperparams or {}):
            return "-params"
        return str(Path(self.params_path) / "config.yml") if self.launch.resume_dir is not None else str(self.config)

    def _read_run_hyperparameters(self) -> dict[str, Any]:
        """Resuming: the run's own ``config.yml`` (and ``-params`` given now)."""
        config = Path(self.params_path) / "config.yml"
        if not config.is_file():
            raise SystemExit(f"Cannot resume: {config} not found (not a run folder of the zoo?).")
        print(f"Loading hyperparameters from: {config}")
        with open(config) as file:
            hyperparams = dict(yaml.load(file, Loader=yaml.UnsafeLoader))
        self.hyperparameter_overrides(hyperparams)
        if self.custom_hyperparams is not None:
            hyperparams.update(self.custom_hyperparams)
        return hyperparams

    def _read_variant_hyperparameters(self, entries: dict[str, dict[str, Any]]) -> dict[str, Any]:
        """The env entry of the variant's composed hyperparameters, as rl-zoo reads an entry of a file."""
        env_key = self.env_name.gym_id
        if env_key not in entries:
            raise ValueError(f"Hyperparameters not found for {self.algo}-{env_key} in {self.config}")
        print(f"Loading hyperparameters from: {self.config} + the overrides of {self.algo}")
        hyperparams = dict(entries[env_key])
        if self.storage and self.study_name and self.trial_id:
            hyperparams.update(self.load_trial(self.storage, self.study_name, self.trial_id))
        if self.custom_hyperparams is not None:
            hyperparams.update(self.custom_hyperparams)
        if "env_kwargs" in hyperparams and self.env_kwargs:
            hyperparams["env_kwargs"] = self.env_kwargs
            if self.eval_env_kwargs_given is None:
                self.eval_env_kwargs = hyperparams["env_kwargs"]
        return hyperparams

    def _zoo_yaml_values(self) -> dict[str, int]:
        return {"eval_freq": self.eval_freq, "eval_episodes": self.n_eval_episodes, "save_freq": self.save_freq}

    # ---- envs and callbacks
    def create_envs(self, n_envs: int, eval_env: bool = False, no_log: bool = False) -> VecEnv:
        return super().create_envs(self.n_tasks, eval_env=eval_env, no_log=no_log)

    def create_callbacks(self) -> None:
        if self.show_progress:
            self.callbacks.append(ProgressBarCallback())
        if self.eval_freq > 0 and not self.optimize_hyperparameters:
            if self.n_eval_episodes < 1:
                raise ValueError(
                    f"--eval-episodes {self.n_eval_episodes}: give at least 1 episode per task, or --eval-freq -1 "
                    "to turn the evaluation off."
                )
            self._eval_env = self.create_envs(self.n_tasks, eval_env=True)
            self.eval_callback = ZooEvalCallback(
                self._eval_env,
                eval_freq=max(self.eval_freq // self.n_tasks, 1),
                episodes_per_task=self.n_eval_episodes,
                deterministic=self.deterministic_eval,
                log_path=self.save_path,
                best_model_save_path=self.save_path,
                verbose=self.verbose,
            )
        if not self.optimize_hyperparameters:  # also without --save-freq: a Ctrl-C saves a checkpoint
            self.checkpoint_callback = MultiTaskCheckpointCallback(
                save_freq=self.save_freq if self.save_freq > 0 else None,
                save_path=self.save_path,
                seed=self.seed,
                eval_env=self._eval_env,
                keep_buffers=self.launch.keep_buffers,
                align_to_episodes=self.launch.align_checkpoints,
                stop_request=self.stop_request,
                verbose=self.verbose,
            )
            self.callbacks.append(self.checkpoint_callback)
        if self.eval_callback is not None:
            self.callbacks.append(self.eval_callback)

    # ---- set-up
    def setup_experiment(self) -> tuple[BaseAlgorithm, dict[str, Any]] | None:
        """rl-zoo's set-up, or a resumed run's; a ``ValueError`` that this package or rl-zoo raises on the
        hyperparameters, env or model (a value out of range) ends with its one line, any other keeps its traceback.
        A new run whose set-up fails leaves no folder behind, the folders above it that it made included (later
        commands would take a run folder for the latest run)."""
        made = [] if self.launch.resume_dir is not None else missing_folders(Path(self.save_path))
        try:
            return self._setup_experiment()
        except BaseException:
            remove_made_folders(made)
            raise

    def _setup_experiment(self) -> tuple[BaseAlgorithm, dict[str, Any]] | None:
        try:
            if self.launch.resume_dir is not None:
                return self._setup_resume()
            result = super().setup_experiment()
        except ValueError as error:
            if not _raised_by(error, ("sb3_mtte", "rl_zoo3")):
                raise
            raise SystemExit(f"{self.algo} on {self.env_id}: {error}") from None
        if result is not None:
            self._write_run_info(*result)
        return result

    def _setup_resume(self) -> tuple[BaseAlgorithm, dict[str, Any]]:
        run_dir = Path(self.save_path)
        self.checkpoint = find_latest_checkpoint(run_dir)
        final = final_checkpoint(run_dir, str(self.env_name))
        if final is not None and (self.checkpoint is None or final.timesteps > self.checkpoint.timesteps):
            self.checkpoint = final
        step = self.checkpoint.timesteps if self.checkpoint is not None else 0
        self.resume_step = step
        if self.checkpoint is None:
            print(f"Resuming {run_dir} from scratch: it has no checkpoint")
        else:
            print(f"Resumed {run_dir} at {step:,} env steps, from {self.checkpoint.model.name}")
        if self.checkpoint is not None:  # before the folder changes: a run without config.yml is left as it was
            unprocessed, saved = self.read_hyperparameters()
        set_aside_monitor_files(run_dir)
        trim_jsonl(run_dir / NT_LOG_FILE, step)
        if self.checkpoint is None:
            result = super().setup_experiment()
            assert result is not None
            run_info.append_resume(run_dir, checkpoint=None, timesteps=0)
            return result
        hyperparams, self.env_wrapper, self.callbacks, self.vec_env_wrapper = self.preprocess_hyperparams(unprocessed)
        self.create_log_folder()
        self.create_callbacks()
        env = self.create_envs(self.n_tasks, no_log=False)
        hyperparams = self.preprocess_action_noise(hyperparams, saved, env)
        overrides = {k: v for k, v in hyperparams.items() if k in (self.custom_hyperparams or {})}
        overrides.pop("policy", None)
        overrides.pop("policy_kwargs", None)
        model = load_model(self.checkpoint.model, device=self.device, env=env, verbose=self.verbose, **overrides)
        if self.checkpoint.replay_buffer is not None:
            model.load_replay_buffer(self.checkpoint.replay_buffer)
        restart_envs(model, self._eval_env, self.seed, step)
        if "task_success" in self.checkpoint.meta:
            window = getattr(model, "_stats_window_size", 100)
            model._task_success = [deque(v, maxlen=window) for v in self.checkpoint.meta["task_success"]]
        self.resumed = True
        run_info.append_resume(
            run_dir, checkpoint=self.checkpoint.model.name, timesteps=step, meta=self.checkpoint.meta
        )
        return model, saved

    def saves_config(self) -> bool:
        return self.launch.resume_dir is None  # a resumed run keeps its own config.yml, args.yml and command

    def _write_run_info(self, model: BaseAlgorithm, saved: dict[str, Any]) -> None:
        env = model.get_env()
        episode_length = None
        with contextlib.suppress(Exception):
            episode_length = int(env.get_attr("_max_episode_steps", [0])[0])  # type: ignore[union-attr]
        info = run_info.collect_run_info(
            algo=self.algo,
            env_id=self.env_id,
            seed=self.seed,
            benchmark=self.benchmark,
            hyperparams=saved,
            algorithm_class=type(model).__name__,
            n_tasks=self.n_tasks,
            task_names=get_task_names(env) if env is not None else benchmark_task_names(self.benchmark),
            benchmark_seed=self.seed,
            reward_function_version=reward_function_version(self.benchmark, self.env_kwargs),
            env_protocol=env_protocol(self.benchmark, self.env_kwargs),
            episode_length=episode_length,
            n_timesteps=self.n_timesteps,
            run_dir=os.path.abspath(self.save_path),
            zoo_args={k: run_info.to_jsonable(v) for k, v in sorted(vars(self.args).items())},
            launcher={
                "tensorboard": self.launch.tensorboard,
                "keep_buffers": self.launch.keep_buffers,
                "align_checkpoints": self.launch.align_checkpoints,
            },
        )
        run_info.write_run_info(self.save_path, info)

    # ---- training
    def learn(self, model: BaseAlgorithm) -> None:
        """Train to ``n_timesteps`` (a resumed run: from its checkpoint); Ctrl-C stops the run
        (:mod:`~sb3_mtte.experiments.zoo.stopping`) and :meth:`save_trained_model` ends it."""
        step = self.resume_step
        tb_dir = None
        if self.tensorboard_dir is not None:
            tb_dir = os.path.join(self.tensorboard_dir, f"{self.algo}_{os.path.basename(self.save_path)}")
        model.set_logger(make_run_logger(self.save_path, self.verbose, tb_dir, step, self.launch.tensorboard))
        if step is not None and self.eval_callback is not None:
            self.eval_callback.load_history(step)
            self.eval_callback.n_calls = step // self.n_tasks
        budget = self.n_timesteps - model.num_timesteps if self.resumed else self.n_timesteps
        try:
            if budget > 0:
                with self.stop_request:
                    model.learn(budget, reset_num_timesteps=not self.resumed, **self._learn_kwargs())
            else:
                print(f"Nothing to do: the run is at {model.num_timesteps} of {self.n_timesteps} steps.")
        except TrainingStopped as stop:
            self.stopped = Stop(stop.checkpoint.timesteps, stop.checkpoint)
        except KeyboardInterrupt:  # a second Ctrl-C: at once, without a checkpoint
            self.stopped = Stop(int(model.num_timesteps), None)
        finally:
            if self.callbacks and budget > 0:
                self.callbacks[0].on_training_end()  # the progress bar, as rl-zoo does
            with contextlib.suppress(EOFError):
                model.get_env().close()  # type: ignore[union-attr]

    def _learn_kwargs(self) -> dict[str, Any]:
        """rl-zoo's arguments of ``learn``: its log interval (-1: the model's, below -1: none) and callbacks."""
        kwargs: dict[str, Any] = {}
        if self.log_interval > -1:
            kwargs["log_interval"] = self.log_interval
        elif self.log_interval < -1:
            kwargs["log_interval"] = None
        if self.callbacks:
            kwargs["callback"] = self.callbacks
        return kwargs

    def save_trained_model(self, model: BaseAlgorithm) -> None:
        """Save the final model (and the replay buffer with ``--save-replay-buffer``), each whole or not at all; a
        stopped run saves no final model (:func:`~sb3_mtte.experiments.zoo.stopping.end_stopped_run`)."""
        if self._eval_env is not None:
            self._eval_env.close()
        if self.stopped is not None:
            end_stopped_run(model, self.stopped, self.save_path, self.n_timesteps)
        print(f"Saving to {self.save_path}")
        atomic_save(model.save, Path(self.save_path) / f"{self.env_name}.zip")
        if hasattr(model, "save_replay_buffer") and self.save_replay_buffer:
            print("Saving replay buffer")
            atomic_save(model.save_replay_buffer, Path(self.save_path) / "replay_buffer.pkl")
        if self.normalize:
            vec_normalize = model.get_vec_normalize_env()
            assert vec_normalize is not None
            atomic_save(vec_normalize.save, Path(self.params_path) / "vecnormalize.pkl")
        run_info.update_run_info(
            self.save_path,
            timesteps=int(model.num_timesteps),
            n_updates=int(getattr(model, "_n_updates", 0)),
            finished=bool(model.num_timesteps >= self.n_timesteps),
            ended=run_info.now(),
            final_model=f"{self.env_name}.zip",
            stopped=None,
        )


def _raised_by(error: BaseException, packages: tuple[str, ...]) -> bool:
    """Whether the frame that raised ``error`` is code of one of ``packages``."""
    traceback = error.__traceback__
    while traceback is not None and traceback.tb_next is not None:
        traceback = traceback.tb_next
    module = traceback.tb_frame.f_globals.get("__name__", "") if traceback is not None else ""
    return module.split(".")[0] in packages
