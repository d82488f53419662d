"""rl-baselines3-zoo launcher for the multi-task algorithms of this package.

Usage (every rl-zoo ``train`` / ``enjoy`` flag works as usual)::

    python -m sb3_mtte.zoo train --algo mtsacte --env MT10 [-conf zoo_configs/mtsacte.yml] [rl-zoo flags]
    python -m sb3_mtte.zoo train --algo mtsacte --env MT10 --resume      # latest run of mtsacte/MT10 in -f
    python -m sb3_mtte.zoo train --resume logs/mtsacte/MT10_1            # a given run folder
    python -m sb3_mtte.zoo enjoy --algo mtsacte --env MT10 -f logs --no-render -n 2000
    python -m sb3_mtte.zoo record_video --algo mtsacte --env MT10 -f logs [-o VIDEO_DIR] [--episodes 1] [--tile]

Launcher options of ``train`` (besides rl-zoo's): ``--resume [RUN_DIR]``, ``--exp-id N`` (run folder ``<env>_N``),
``--no-progress``, ``--no-tensorboard``, ``--keep-buffers K`` (replay-buffer checkpoints kept, default 1, 0 = all),
``--no-align-checkpoints`` (save at the step reached, not at the next end of episodes).

What the launcher adds to rl-zoo3 (everything else is rl-zoo's ``ExperimentManager``: hyperparameter files and
``-params`` overrides, run folders ``<log-folder>/<algo>/<env>_<id>/``, ``config.yml``/``args.yml``, optuna,
``-i`` continued training, ...):

* Algorithms in ``rl_zoo3.ALGOS``: ``mtsac`` and ``mtsacte`` plus one key per row of the paper's Table 1 and
  Fig. 7 (:data:`ALGO_KEYS`); ``-conf`` defaults to ``zoo_configs/<algo>.yml`` (current directory first, then
  the source checkout).
* Env ids ``MT10``, ``MT20``, ``MT50``, ``toy-conflict``, ``toy-agree`` (and ``toy-conflict-<N>``), each also with
  a budget suffix (``MT10-smoke``): the suffix picks another entry of the hyperparameter file and names the run
  folder, the benchmark is the same. Sub-env i is task i: rl-zoo builds every sub-env with the same constructor,
  the launcher's VecEnv class (``ExperimentManager.default_vec_env_cls``' role, with rl-zoo's ``--vec-env``
  choice inside) tells constructor i which task to build. ``n_envs`` is set to the task count.
* Evaluation with :class:`~sb3_mtte.common.evaluation.MultiTaskEvalCallback` (Meta-World's success protocol;
  ``--eval-freq`` in total env steps, ``--eval-episodes`` per task) writing ``evaluations.npz`` and
  ``best_model.zip``; the hyperparameter file may give ``eval_freq``, ``eval_episodes`` and ``save_freq``
  defaults, which the command line overrides.
* Logging into the run folder: ``progress.csv``, tensorboard events (``-tb DIR`` moves them to
  ``DIR/<env>/<algo>_<run>``), ``negative_transfer.jsonl`` (MTSACTE) and ``run_info.json`` (versions, seed,
  git commit; :mod:`sb3_mtte.run_info`). Progress bar on (``--no-progress`` turns it off).
* ``enjoy`` is rl-zoo's, with ``--n-envs`` set to the task count and every finished episode printed (task,
  return, success); ``record_video`` writes one video per task (``--tile``: also all tasks side by side).
* Checkpoints (``--save-freq`` in total env steps): model, replay buffer (with the top-K store) and a marker,
  taken after the update of a step and at the end of an episode; ``--resume`` continues the latest complete
  checkpoint of a run folder to the run's ``n_timesteps``, and trims the logs written after it. At every
  checkpoint the training and evaluation envs are reseeded from (seed, step) and reset, at the boundary between
  episodes, so an interrupted and resumed run repeats exactly what an uninterrupted one does (on CPU).
"""

from __future__ import annotations

import argparse
import contextlib
import contextvars
import csv
import json
import os
import re
import sys
import warnings
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, ProgressBarCallback
from stable_baselines3.common.logger import (
    CSVOutputFormat,
    HumanOutputFormat,
    KVWriter,
    Logger,
    TensorBoardOutputFormat,
)
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecEnvWrapper

from sb3_mtte import run_info as run_info_mod
from sb3_mtte.common.checkpoints import read_checkpoint_data
from sb3_mtte.common.evaluation import MultiTaskEvalCallback, SuccessResult
from sb3_mtte.mtsac import MTSAC
from sb3_mtte.mtsacte import MTSACTE

# --------------------------------------------------------------------------------------------------------------
# Algorithms
# --------------------------------------------------------------------------------------------------------------
ALGO_KEYS: dict[str, type[BaseAlgorithm]] = {
    "mtsac": MTSAC,
    "mtsac_ind": MTSAC,
    "mtsac_mt": MTSAC,
    "mtsac_mh": MTSAC,
    "mtsac_softmod": MTSAC,
    "mtsac_clip": MTSAC,
    "mtsacte": MTSACTE,
    "mtsacte_novae": MTSACTE,
    "mtsacte_noclip": MTSACTE,
    "mtsacte_nobestbatch": MTSACTE,
}
"""Zoo algorithm key -> class. Each row key has its hyperparameter file ``zoo_configs/<key>.yml``."""

ALGORITHM_CLASSES: dict[str, type[BaseAlgorithm]] = {"MTSAC": MTSAC, "MTSACTE": MTSACTE}
"""``algorithm_name`` stored in a checkpoint -> class."""

BUDGET_SUFFIXES = ("smoke", "cpu")
"""Env-id suffixes that select another hyperparameter entry (``MT10-smoke``) for the same benchmark."""

STANDARD_BENCHMARKS = ("MT10", "MT20", "MT50", "toy-conflict", "toy-agree")

CONFIG_DIR_NAME = "zoo_configs"

_ZOO_YAML_KEYS = ("eval_freq", "eval_episodes", "save_freq")
"""Hyperparameter-file keys read by the launcher (defaults of the command-line flags), not by the model."""


def _sample_mtsac_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Optuna search space of the MTSAC family (architecture fixed by the hyperparameter file)."""
    trial.suggest_float("learning_rate", 1e-4, 1e-3, log=True)
    trial.suggest_float("one_minus_gamma", 0.002, 0.03, log=True)
    trial.suggest_float("tau", 0.001, 0.02, log=True)
    trial.suggest_int("batch_size_pow", 6, 8)
    return _convert_mtsac_params(trial.params)


def _sample_mtsacte_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Optuna search space of MTSACTE: the MTSAC one plus alpha_nt, c_vae and the J^rep steps per iteration."""
    _sample_mtsac_params(trial, n_actions, n_envs, additional_args)
    trial.suggest_float("nt_step_size", 1e-4, 1e-2, log=True)
    trial.suggest_float("c_vae", 1e-3, 1.0, log=True)
    trial.suggest_categorical("rep_gradient_steps", [1, 5, 10, 20])
    return _convert_mtsac_params(trial.params)


def _convert_mtsac_params(params: dict[str, Any]) -> dict[str, Any]:
    """Optuna trial parameters -> model keyword arguments."""
    kwargs = dict(params)
    if "one_minus_gamma" in kwargs:
        kwargs["gamma"] = 1.0 - kwargs.pop("one_minus_gamma")
    if "batch_size_pow" in kwargs:
        kwargs["batch_size"] = 2 ** kwargs.pop("batch_size_pow")
    return kwargs


def register_algos() -> None:
    """Add :data:`ALGO_KEYS` to ``rl_zoo3.ALGOS`` and their optuna samplers to rl-zoo's tables (idempotent)."""
    import rl_zoo3
    from rl_zoo3 import hyperparams_opt

    for key, cls in ALGO_KEYS.items():
        rl_zoo3.ALGOS[key] = cls
        sampler = _sample_mtsacte_params if cls is MTSACTE else _sample_mtsac_params
        hyperparams_opt.HYPERPARAMS_SAMPLER[key] = sampler
        hyperparams_opt.HYPERPARAMS_CONVERTER[key] = _convert_mtsac_params


# --------------------------------------------------------------------------------------------------------------
# Env ids and the one-task-per-sub-env VecEnv
# --------------------------------------------------------------------------------------------------------------
def split_env_id(env_id: str) -> tuple[str, str | None]:
    """``"MT10-smoke"`` -> ``("MT10", "smoke")``; ``"MT10"`` -> ``("MT10", None)``."""
    for suffix in BUDGET_SUFFIXES:
        if env_id.endswith(f"-{suffix}"):
            return env_id[: -len(suffix) - 1], suffix
    return env_id, None


def benchmark_task_names(benchmark: str) -> list[str]:
    """Task names of a benchmark name (``"MT10"``, ``"toy-conflict-6"``, ...), without building any env.

    :raises ValueError: for an unknown benchmark.
    """
    from sb3_mtte.envs import METAWORLD_BENCHMARKS, TOY_BENCHMARKS
    from sb3_mtte.envs.toy import parse_toy_name

    toy = parse_toy_name(benchmark)
    if toy is not None:
        return TOY_BENCHMARKS[toy[0]](toy[1])[0]
    if benchmark.upper() in METAWORLD_BENCHMARKS:
        return list(METAWORLD_BENCHMARKS[benchmark.upper()])
    raise ValueError(
        f"Unknown benchmark {benchmark!r}: use MT10, MT20, MT50, toy-conflict, toy-agree or toy-<name>-<N>, "
        f"optionally followed by a budget suffix ({', '.join('-' + s for s in BUDGET_SUFFIXES)})."
    )


def env_id_n_tasks(env_id: str) -> int:
    """Number of tasks of the benchmark an env id names."""
    return len(benchmark_task_names(split_env_id(env_id)[0]))


_ENTRY_POINT = "sb3_mtte.zoo:make_task_env"
_TASK_CONTEXT: contextvars.ContextVar[tuple[int, int] | None] = contextvars.ContextVar("sb3_mtte_task", default=None)


def make_task_env(benchmark: str, task_index: int | None = None, seed: int | None = None, **kwargs: Any) -> gym.Env:
    """Gymnasium entry point of the registered ids: sub-env ``task_index`` of ``benchmark``.

    Inside :class:`MultiTaskVecEnvFactory` the task index and the benchmark seed come from the sub-env's position;
    elsewhere pass ``task_index`` (and ``seed``) explicitly.

    :param benchmark: benchmark name.
    :param task_index: the task this env runs.
    :param seed: benchmark seed (goal variations); default: the factory's seed, else 0.
    :param kwargs: env keyword arguments of :func:`sb3_mtte.envs.make_mt_env` (``max_episode_steps``,
        ``render_mode``, ...).
    """
    from sb3_mtte.envs import make_env_fns

    context = _TASK_CONTEXT.get()
    if task_index is None:
        if context is None:
            raise gym.error.Error(
                f"{benchmark!r} is a multi-task benchmark with one sub-env per task: build it with "
                "sb3_mtte.envs.make_mt_env, with the sb3_mtte.zoo launcher, or pass task_index=i."
            )
        task_index = context[0]
    if seed is None:
        seed = context[1] if context is not None else 0
    env_fns = make_env_fns(benchmark, seed=int(seed), **kwargs)
    return env_fns[task_index]()


def register_env_id(env_id: str) -> bool:
    """Register ``env_id`` (a benchmark name, optionally with a budget suffix) with gymnasium.

    :return: True when registered now or before, False when ``env_id`` is no benchmark of this package.
    """
    if env_id in gym.envs.registry:
        return gym.envs.registry[env_id].entry_point == _ENTRY_POINT
    benchmark = split_env_id(env_id)[0]
    try:
        benchmark_task_names(benchmark)
    except ValueError:
        return False
    gym.register(
        id=env_id,
        entry_point=_ENTRY_POINT,
        kwargs={"benchmark": benchmark},
        disable_env_checker=True,
    )
    return True


def register_standard_env_ids() -> None:
    """Register :data:`STANDARD_BENCHMARKS`, each with and without every budget suffix."""
    for benchmark in STANDARD_BENCHMARKS:
        register_env_id(benchmark)
        for suffix in BUDGET_SUFFIXES:
            register_env_id(f"{benchmark}-{suffix}")


class _TaskEnvFn:
    """Picklable constructor that builds sub-env ``task_index`` by calling a zoo env constructor in context."""

    def __init__(self, env_fn: Callable[[], gym.Env], task_index: int, seed: int) -> None:
        self.env_fn, self.task_index, self.seed = env_fn, task_index, seed

    def __call__(self) -> gym.Env:
        token = _TASK_CONTEXT.set((self.task_index, self.seed))
        try:
            return self.env_fn()
        finally:
            _TASK_CONTEXT.reset(token)


class EpisodeReporter(VecEnvWrapper):
    """Print every finished episode (task, return, success) and, on close, the success rate of each task."""

    def __init__(self, venv: VecEnv) -> None:
        super().__init__(venv)
        from sb3_mtte.common.utils import get_task_names

        self.task_names = get_task_names(venv)
        self.successes: list[list[bool]] = [[] for _ in range(venv.num_envs)]

    def reset(self) -> Any:
        return self.venv.reset()

    def step_wait(self) -> Any:
        obs, rewards, dones, infos = self.venv.step_wait()
        for i in np.flatnonzero(dones):
            success = bool(infos[i].get("is_success", False))
            self.successes[i].append(success)
            episode = infos[i].get("episode", {})
            print(
                f"task {i:2d} {self.task_names[i]:<28} return {episode.get('r', float('nan')):9.2f}  "
                f"length {episode.get('l', '-')!s:>4}  success {success}"
            )
        return obs, rewards, dones, infos

    def close(self) -> None:
        if any(self.successes):
            print("Success rate per task (episodes finished):")
            for name, results in zip(self.task_names, self.successes):
                if results:
                    print(f"  {name:<28} {100 * np.mean(results):5.1f}% ({len(results)})")
        self.venv.close()


class MultiTaskVecEnvFactory:
    """A VecEnv "class" for rl-zoo: given N constructors of the same registered env, sub-env i builds task i.

    :param n_tasks: number of tasks N; the zoo must ask for N sub-envs.
    :param seed: benchmark seed handed to every sub-env (goal variations).
    :param vec_env_cls: the VecEnv class that runs the sub-envs (rl-zoo's ``--vec-env`` choice).
    :param report_episodes: wrap the env in :class:`EpisodeReporter` (``enjoy``).
    """

    def __init__(
        self, n_tasks: int, seed: int = 0, vec_env_cls: type[VecEnv] = DummyVecEnv, report_episodes: bool = False
    ) -> None:
        self.n_tasks, self.seed, self.vec_env_cls = n_tasks, int(seed), vec_env_cls
        self.report_episodes = report_episodes

    def __call__(self, env_fns: Sequence[Callable[[], gym.Env]], **vec_env_kwargs: Any) -> VecEnv:
        if len(env_fns) != self.n_tasks:
            raise ValueError(
                f"This benchmark has {self.n_tasks} tasks and needs one sub-env per task; got {len(env_fns)} "
                f"sub-envs (use n_envs={self.n_tasks}, or --n-envs {self.n_tasks} for enjoy)."
            )
        fns = [_TaskEnvFn(fn, i, self.seed) for i, fn in enumerate(env_fns)]
        env = self.vec_env_cls(fns, **vec_env_kwargs)  # type: ignore[arg-type]
        return EpisodeReporter(env) if self.report_episodes else env


# --------------------------------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------------------------------
CHECKPOINT_PREFIX = "rl_model"
_CHECKPOINT_RE = re.compile(rf"^{CHECKPOINT_PREFIX}_(\d+)_steps\.zip$")


@dataclass
class Checkpoint:
    """A complete checkpoint of a run folder."""

    timesteps: int
    model: Path
    replay_buffer: Path | None
    meta: dict[str, Any] = field(default_factory=dict)


def checkpoint_paths(run_dir: str | os.PathLike, timesteps: int, prefix: str = CHECKPOINT_PREFIX) -> dict[str, Path]:
    """Model, replay-buffer and marker paths of the checkpoint at ``timesteps`` (SB3's CheckpointCallback names)."""
    run_dir = Path(run_dir)
    return {
        "model": run_dir / f"{prefix}_{timesteps}_steps.zip",
        "replay_buffer": run_dir / f"{prefix}_replay_buffer_{timesteps}_steps.pkl",
        "meta": run_dir / f"{prefix}_{timesteps}_steps.json",
    }


def find_checkpoints(run_dir: str | os.PathLike, require_buffer: bool = True) -> list[Checkpoint]:
    """Complete checkpoints of a run folder, oldest first.

    A checkpoint is complete when its model exists and, with ``require_buffer``, its replay buffer too. The
    marker (``rl_model_<t>_steps.json``, written last) is read when present.
    """
    found = []
    for path in Path(run_dir).glob(f"{CHECKPOINT_PREFIX}_*_steps.zip"):
        match = _CHECKPOINT_RE.match(path.name)
        if match is None:
            continue
        steps = int(match.group(1))
        paths = checkpoint_paths(run_dir, steps)
        buffer = paths["replay_buffer"] if paths["replay_buffer"].is_file() else None
        if require_buffer and buffer is None:
            continue
        meta = json.loads(paths["meta"].read_text()) if paths["meta"].is_file() else {}
        found.append(Checkpoint(steps, path, buffer, meta))
    return sorted(found, key=lambda c: c.timesteps)


def find_latest_checkpoint(run_dir: str | os.PathLike, require_buffer: bool = True) -> Checkpoint | None:
    """The most recent complete checkpoint of a run folder (see :func:`find_checkpoints`), or None."""
    found = find_checkpoints(run_dir, require_buffer)
    return found[-1] if found else None


def restart_seed(seed: int, timesteps: int, stream: int = 0) -> int:
    """Seed of the envs restarted at a checkpoint: a function of the run seed, the step and the env (0: train)."""
    state = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(seed) >> 32, int(timesteps), stream])
    return int(state.generate_state(1)[0] % (2**31 - 2**16))


def restart_envs(model: BaseAlgorithm, eval_env: VecEnv | None, seed: int, timesteps: int) -> None:
    """Reseed from (seed, step) and reset the training env, and reseed the evaluation env for its next reset.

    Called at every checkpoint taken at the boundary between episodes, and on resuming from any checkpoint,
    so that both runs continue from the same env states.
    """
    env = model.get_env()
    assert env is not None
    buffer = getattr(model, "replay_buffer", None)
    if hasattr(buffer, "reset_running_episodes"):
        buffer.reset_running_episodes()  # episodes cut by the restart are not offered to the top-K store
    env.seed(restart_seed(seed, timesteps, 0))
    model._last_obs = env.reset()  # type: ignore[assignment]
    model._last_episode_starts = np.ones((env.num_envs,), dtype=bool)
    if eval_env is not None:
        eval_env.seed(restart_seed(seed, timesteps, 1))


def _atomic_save(save: Callable[[str], None], path: Path) -> None:
    tmp = path.with_name(f".tmp_{path.name}")
    save(str(tmp))
    os.replace(tmp, path)


class MultiTaskCheckpointCallback(BaseCallback):
    """Save model, replay buffer (with the top-K store) and a marker every ``save_freq`` env steps (over all tasks).

    A checkpoint is taken at the start of a rollout, i.e. after the transition of the last step is stored and
    its update is done (SB3's ``CheckpointCallback`` saves before both). Once ``save_freq`` steps have passed,
    it waits for the end of an episode in every sub-env (at most ``save_freq`` more steps), then restarts the
    envs with seeds drawn from (seed, step) (:func:`restart_envs`) and saves. Files are written under a
    temporary name and renamed; the marker ``rl_model_<t>_steps.json`` comes last.

    :param save_freq: env steps (all tasks) between checkpoints.
    :param save_path: the run folder.
    :param seed: the run seed (env restarts).
    :param eval_env: the evaluation env, reseeded with the training env.
    :param save_replay_buffer: save the replay buffer too.
    :param keep_buffers: replay-buffer files kept (the newest ones); 0 keeps all.
    :param align_to_episodes: wait for the end of an episode before saving.
    :param verbose: 1 prints a line per checkpoint.
    """

    def __init__(
        self,
        save_freq: int,
        save_path: str | os.PathLike,
        seed: int = 0,
        eval_env: VecEnv | None = None,
        save_replay_buffer: bool = True,
        keep_buffers: int = 1,
        align_to_episodes: bool = True,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        if save_freq < 1:
            raise ValueError(f"save_freq must be >= 1, got {save_freq}.")
        self.save_freq, self.save_path, self.seed = int(save_freq), Path(save_path), int(seed)
        self.eval_env, self.save_replay_buffer = eval_env, save_replay_buffer
        self.keep_buffers, self.align_to_episodes = keep_buffers, align_to_episodes
        self._next_save: int | None = None

    def _init_callback(self) -> None:
        self.save_path.mkdir(parents=True, exist_ok=True)
        self._next_save = (self.num_timesteps // self.save_freq + 1) * self.save_freq

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        assert self._next_save is not None
        steps = self.num_timesteps
        if steps < self._next_save:
            return
        boundary = bool(np.all(self.model._last_episode_starts))
        if self.align_to_episodes and not boundary and steps < self._next_save + self.save_freq:
            return
        self.save(episode_boundary=boundary)
        self._next_save = (steps // self.save_freq + 1) * self.save_freq

    def save(self, episode_boundary: bool) -> Checkpoint:
        """Take a checkpoint now (restarting the envs first when at an episode boundary)."""
        steps = self.num_timesteps
        if self.model.logger.name_to_value:  # records waiting for the next dump would die with a killed process
            self.model.logger.dump(steps)
        if episode_boundary:
            restart_envs(self.model, self.eval_env, self.seed, steps)
        paths = checkpoint_paths(self.save_path, steps)
        buffer_path = None
        if self.save_replay_buffer and getattr(self.model, "replay_buffer", None) is not None:
            _atomic_save(self.model.save_replay_buffer, paths["replay_buffer"])  # type: ignore[attr-defined]
            buffer_path = paths["replay_buffer"]
        _atomic_save(self.model.save, paths["model"])
        meta = {
            "timesteps": steps,
            "n_updates": int(getattr(self.model, "_n_updates", 0)),
            "episode_boundary": episode_boundary,
            "envs_restarted": episode_boundary,
            "replay_buffer": buffer_path is not None,
            "time": run_info_mod.now(),
        }
        task_success = getattr(self.model, "_task_success", None)
        if task_success is not None:  # per-task rollout success window (logging), not saved with the model
            meta["task_success"] = [[float(v) for v in window] for window in task_success]
        tmp = paths["meta"].with_name(f".tmp_{paths['meta'].name}")
        tmp.write_text(json.dumps(meta, indent=2) + "\n")
        os.replace(tmp, paths["meta"])
        self._prune_buffers()
        if self.verbose >= 1:
            print(f"Checkpoint at {steps} steps: {paths['model']}")
        return Checkpoint(steps, paths["model"], buffer_path, meta)

    def _prune_buffers(self) -> None:
        if self.keep_buffers <= 0:
            return
        buffers = [c.replay_buffer for c in find_checkpoints(self.save_path) if c.replay_buffer is not None]
        for path in buffers[: -self.keep_buffers]:
            path.unlink(missing_ok=True)


class ZooEvalCallback(MultiTaskEvalCallback):
    """:class:`MultiTaskEvalCallback` that also saves ``best_model.zip`` (highest mean success) like rl-zoo's."""

    def __init__(self, *args: Any, best_model_save_path: str | os.PathLike | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.best_model_save_path = best_model_save_path
        self.best_mean_success = -np.inf

    def evaluate(self) -> SuccessResult:
        result = super().evaluate()
        if result.mean > self.best_mean_success:
            self.best_mean_success = result.mean
            if self.best_model_save_path is not None:
                _atomic_save(self.model.save, Path(self.best_model_save_path) / "best_model.zip")
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
            np.savez(
                path,
                timesteps=np.asarray(self.evaluations_timesteps),
                success_rate=np.stack(self.evaluations_success),
                task_names=np.asarray(self.task_names),
            )
        else:
            path.unlink()


# --------------------------------------------------------------------------------------------------------------
# Logs of a run folder
# --------------------------------------------------------------------------------------------------------------
PROGRESS_FILE = "progress.csv"
NT_FILE = "negative_transfer.jsonl"
STEP_KEY = "time/total_timesteps"


class _TensorBoardFormat(TensorBoardOutputFormat):
    """SB3's tensorboard writer with a purge step: events of a killed run after the resumed step are hidden."""

    def __init__(self, folder: str, purge_step: int | None = None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(log_dir=folder, purge_step=purge_step)
        self._is_closed = False


def _trim_progress_csv(path: Path, up_to_timesteps: int) -> tuple[list[str], list[str]]:
    """Header and raw data lines of an SB3 ``progress.csv`` whose step is at most ``up_to_timesteps``."""
    if not path.is_file():
        return [], []
    lines = path.read_text().splitlines()
    if not lines:
        return [], []
    header = lines[0].split(",")
    column = header.index(STEP_KEY) if STEP_KEY in header else None
    kept = []
    for line in lines[1:]:
        if column is not None:
            row = next(csv.reader([line]), [])
            try:
                if float(row[column]) > up_to_timesteps:
                    continue
            except (IndexError, ValueError):
                pass
        kept.append(line)
    return header, kept


def make_run_logger(
    run_dir: str | os.PathLike,
    verbose: int = 1,
    tensorboard_dir: str | None = None,
    resume_step: int | None = None,
    tensorboard: bool = True,
) -> Logger:
    """SB3 logger of a run folder: stdout (verbose >= 1), ``progress.csv`` and tensorboard events.

    :param run_dir: the run folder (``logger.get_dir()``, where MTSACTE writes ``negative_transfer.jsonl``).
    :param verbose: 1 adds stdout.
    :param tensorboard_dir: folder of the events (the run folder when None).
    :param resume_step: for a resumed run, the checkpoint step: ``progress.csv`` keeps its rows up to this step
        and continues, tensorboard hides the events logged after it.
    :param tensorboard: write tensorboard events.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    formats: list[KVWriter] = []
    if verbose >= 1:
        formats.append(HumanOutputFormat(sys.stdout))
    path = run_dir / PROGRESS_FILE
    header, lines = _trim_progress_csv(path, resume_step) if resume_step is not None else ([], [])
    csv_format = CSVOutputFormat(str(path))
    if header:
        csv_format.keys = header
        csv_format.file.write(",".join(header) + "\n")
        for line in lines:
            csv_format.file.write(line + "\n")
        csv_format.file.flush()
    formats.append(csv_format)
    if tensorboard:
        purge = None if resume_step is None else resume_step + 1
        formats.append(_TensorBoardFormat(str(tensorboard_dir or run_dir), purge_step=purge))
    return Logger(folder=str(run_dir), output_formats=formats)


def trim_jsonl(path: Path, up_to_timesteps: int, key: str = "timesteps") -> None:
    """Drop the records of a JSON-lines log whose ``key`` exceeds ``up_to_timesteps``."""
    if not path.is_file():
        return
    kept = []
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            if json.loads(line).get(key, 0) > up_to_timesteps:
                continue
        except json.JSONDecodeError:
            continue  # a line cut by the kill
        kept.append(line + "\n")
    tmp = path.with_name(f".tmp_{path.name}")
    tmp.write_text("".join(kept))
    os.replace(tmp, path)


def _set_aside_monitor_files(run_dir: Path) -> None:
    """Rename the Monitor files of the previous segments (``0.monitor.csv`` -> ``0.seg<k>.monitor.csv``)."""
    files = sorted(run_dir.glob("[0-9]*.monitor.csv"))
    files = [f for f in files if re.fullmatch(r"\d+\.monitor\.csv", f.name)]
    if not files:
        return
    segment = 1 + len({m.group(1) for f in run_dir.glob("*.seg*.monitor.csv") if (m := re.search(r"seg(\d+)", f.name))})
    for path in files:
        path.rename(path.with_name(path.name.replace(".monitor.csv", f".seg{segment}.monitor.csv")))


# --------------------------------------------------------------------------------------------------------------
# Experiment manager
# --------------------------------------------------------------------------------------------------------------
@dataclass
class LaunchOptions:
    """Options of the launcher that rl-zoo's argument parser does not know."""

    resume_dir: str | None = None
    exp_id: int | None = None
    flags_given: frozenset[str] = frozenset()
    keep_buffers: int = 1
    align_checkpoints: bool = True
    tensorboard: bool = True


_MANAGER_CLASS: type | None = None


def _exp_manager_class() -> type:
    """The ExperimentManager subclass (built on first use: importing rl-zoo is slow)."""
    global _MANAGER_CLASS
    if _MANAGER_CLASS is None:
        _MANAGER_CLASS = _build_exp_manager_class()
    return _MANAGER_CLASS


def _build_exp_manager_class() -> type:
    from rl_zoo3.exp_manager import ExperimentManager

    class MultiTaskExperimentManager(ExperimentManager):
        """rl-zoo's ExperimentManager with one sub-env per task, multi-task evaluation, resumable checkpoints
        and run metadata (see the module docstring)."""

        def __init__(self, args: argparse.Namespace, algo: str, env_id: str, *pos: Any, **kwargs: Any) -> None:
            self.launch: LaunchOptions = kwargs.pop("launch", None) or LaunchOptions()
            super().__init__(args, algo, env_id, *pos, **kwargs)
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
                self._restore_run_args()
            elif self.launch.exp_id is not None:
                self.save_path = os.path.join(self.log_path, f"{self.env_name}_{self.launch.exp_id}")
                self.params_path = f"{self.save_path}/{self.env_name}"
                if (Path(self.save_path) / run_info_mod.RUN_INFO_FILE).is_file():
                    raise FileExistsError(f"{self.save_path} already holds a run: use --resume {self.save_path}.")
            self.checkpoint: Checkpoint | None = None
            self.resumed = False  # from a checkpoint
            self.resume_step: int | None = None  # step the logs are trimmed to (0: resumed without checkpoint)
            self.checkpoint_callback: MultiTaskCheckpointCallback | None = None
            self.eval_callback: ZooEvalCallback | None = None
            self._eval_env: VecEnv | None = None

        def _restore_run_args(self) -> None:
            """Resuming: take the run's own command-line settings (its ``args.yml``) unless given again now."""
            import yaml

            path = Path(self.params_path) / "args.yml"
            if not path.is_file():
                return
            with open(path) as file:
                saved = dict(yaml.load(file, Loader=yaml.UnsafeLoader))
            given = self.launch.flags_given
            if "n_timesteps" not in given:
                info = run_info_mod.read_run_info(self.save_path) or {}
                self.n_timesteps = int(info.get("n_timesteps", saved.get("n_timesteps", -1)))
            if "env_kwargs" not in given:
                self.env_kwargs = dict(saved.get("env_kwargs") or {})
            if "eval_env_kwargs" not in given:
                self._eval_env_kwargs_args = saved.get("eval_env_kwargs")
                self.eval_env_kwargs = dict(self._eval_env_kwargs_args or self.env_kwargs)
            if "vec_env" not in given and saved.get("vec_env") == "subproc":
                from stable_baselines3.common.vec_env import SubprocVecEnv

                self.vec_env_class.vec_env_cls = SubprocVecEnv
            if "log_interval" not in given and "log_interval" in saved:
                self.log_interval = int(saved["log_interval"])
            if "save_replay_buffer" not in given and saved.get("save_replay_buffer"):
                self.save_replay_buffer = True
            if "tensorboard_log" not in given and saved.get("tensorboard_log"):
                self.tensorboard_dir = os.path.join(saved["tensorboard_log"], self.env_name)

        # ---- hyperparameters
        def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
            if self.launch.resume_dir is not None:
                config = Path(self.params_path) / "config.yml"
                if not config.is_file():
                    raise FileNotFoundError(f"Cannot resume: {config} not found (not a run folder of the zoo?).")
                import yaml

                print(f"Loading hyperparameters from: {config}")
                with open(config) as file:
                    hyperparams = dict(yaml.load(file, Loader=yaml.UnsafeLoader))
                if self.custom_hyperparams is not None:
                    hyperparams.update(self.custom_hyperparams)
            else:
                hyperparams, _ = super().read_hyperparameters()
            n_envs = hyperparams.get("n_envs")
            if n_envs is not None and int(n_envs) != self.n_tasks:
                raise ValueError(f"n_envs={n_envs} in the hyperparameters, but {self.env_id} has {self.n_tasks} tasks.")
            hyperparams["n_envs"] = self.n_tasks
            for key in _ZOO_YAML_KEYS:
                value = hyperparams.pop(key, None)
                if value is None or key in self.launch.flags_given:
                    continue
                if key == "eval_freq":
                    self.eval_freq = int(value)
                elif key == "eval_episodes":
                    self.n_eval_episodes = int(value)
                else:
                    self.save_freq = int(value)
            saved = OrderedDict((key, hyperparams[key]) for key in sorted(hyperparams))
            saved.update({key: value for key, value in self._zoo_yaml_values().items()})
            saved = OrderedDict((key, saved[key]) for key in sorted(saved))
            return hyperparams, saved

        def _zoo_yaml_values(self) -> dict[str, int]:
            return {"eval_freq": self.eval_freq, "eval_episodes": self.n_eval_episodes, "save_freq": self.save_freq}

        # ---- envs and callbacks
        def create_envs(self, n_envs: int, eval_env: bool = False, no_log: bool = False) -> VecEnv:
            return super().create_envs(self.n_tasks, eval_env=eval_env, no_log=no_log)

        def create_callbacks(self) -> None:
            if self.show_progress:
                self.callbacks.append(ProgressBarCallback())
            if self.eval_freq > 0 and not self.optimize_hyperparameters:
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
            if self.save_freq > 0 and not self.optimize_hyperparameters:
                self.checkpoint_callback = MultiTaskCheckpointCallback(
                    save_freq=self.save_freq,
                    save_path=self.save_path,
                    seed=self.seed,
                    eval_env=self._eval_env,
                    keep_buffers=self.launch.keep_buffers,
                    align_to_episodes=self.launch.align_checkpoints,
                    verbose=self.verbose,
                )
                self.callbacks.append(self.checkpoint_callback)
            if self.eval_callback is not None:
                self.callbacks.append(self.eval_callback)

        # ---- set-up
        def setup_experiment(self) -> tuple[BaseAlgorithm, dict[str, Any]] | None:
            if self.launch.resume_dir is not None:
                return self._setup_resume()
            result = super().setup_experiment()
            if result is not None:
                self._write_run_info(*result)
            return result

        def _setup_resume(self) -> tuple[BaseAlgorithm, dict[str, Any]]:
            run_dir = Path(self.save_path)
            self.checkpoint = find_latest_checkpoint(run_dir)
            final = self._final_checkpoint(run_dir)
            if final is not None and (self.checkpoint is None or final.timesteps > self.checkpoint.timesteps):
                self.checkpoint = final
            step = self.checkpoint.timesteps if self.checkpoint is not None else 0
            self.resume_step = step
            print(f"Resuming {run_dir} from " + (f"{self.checkpoint.model.name}" if self.checkpoint else "scratch"))
            _set_aside_monitor_files(run_dir)
            trim_jsonl(run_dir / NT_FILE, step)
            if self.checkpoint is None:
                result = super().setup_experiment()
                assert result is not None
                run_info_mod.append_resume(run_dir, checkpoint=None, timesteps=0)
                return result
            unprocessed, saved = self.read_hyperparameters()
            hyperparams, self.env_wrapper, self.callbacks, self.vec_env_wrapper = self._preprocess_hyperparams(
                unprocessed
            )
            self.create_log_folder()
            self.create_callbacks()
            env = self.create_envs(self.n_tasks, no_log=False)
            hyperparams = self._preprocess_action_noise(hyperparams, saved, env)
            overrides = {k: v for k, v in hyperparams.items() if k in (self.custom_hyperparams or {})}
            overrides.pop("policy", None)
            overrides.pop("policy_kwargs", None)
            cls = ALGORITHM_CLASSES[read_checkpoint_data(self.checkpoint.model)["algorithm_name"]]
            model = cls.load(self.checkpoint.model, env=env, device=self.device, verbose=self.verbose, **overrides)
            if self.checkpoint.replay_buffer is not None:
                model.load_replay_buffer(self.checkpoint.replay_buffer)
            restart_envs(model, self._eval_env, self.seed, step)
            if "task_success" in self.checkpoint.meta:
                from collections import deque

                window = getattr(model, "_stats_window_size", 100)
                model._task_success = [deque(v, maxlen=window) for v in self.checkpoint.meta["task_success"]]
            self.resumed = True
            run_info_mod.append_resume(
                run_dir, checkpoint=self.checkpoint.model.name, timesteps=step, meta=self.checkpoint.meta
            )
            return model, saved

        def _save_config(self, saved_hyperparams: dict[str, Any]) -> None:
            if self.launch.resume_dir is None:  # a resumed run keeps its own config.yml, args.yml and command
                super()._save_config(saved_hyperparams)

        def _final_checkpoint(self, run_dir: Path) -> Checkpoint | None:
            """The final model and replay buffer of a run that finished (``--save-replay-buffer``), if any."""
            info = run_info_mod.read_run_info(run_dir) or {}
            model, buffer = run_dir / f"{self.env_name}.zip", run_dir / "replay_buffer.pkl"
            if not (info.get("finished") and model.is_file() and buffer.is_file()):
                return None
            steps = int(read_checkpoint_data(model).get("num_timesteps", 0))
            return Checkpoint(steps, model, buffer, {"timesteps": steps, "final_model": True})

        def _write_run_info(self, model: BaseAlgorithm, saved: dict[str, Any]) -> None:
            from sb3_mtte.common.utils import get_task_names

            env = model.get_env()
            episode_length = None
            with contextlib.suppress(Exception):
                episode_length = int(env.get_attr("_max_episode_steps", [0])[0])  # type: ignore[union-attr]
            info = run_info_mod.collect_run_info(
                algo=self.algo,
                env_id=self.env_id,
                seed=self.seed,
                benchmark=self.benchmark,
                hyperparams=saved,
                algorithm_class=type(model).__name__,
                n_tasks=self.n_tasks,
                task_names=get_task_names(env) if env is not None else benchmark_task_names(self.benchmark),
                benchmark_seed=self.seed,
                episode_length=episode_length,
                n_timesteps=self.n_timesteps,
                run_dir=os.path.abspath(self.save_path),
                zoo_args={k: run_info_mod.to_jsonable(v) for k, v in sorted(vars(self.args).items())},
                launcher={
                    "tensorboard": self.launch.tensorboard,
                    "keep_buffers": self.launch.keep_buffers,
                    "align_checkpoints": self.launch.align_checkpoints,
                },
            )
            run_info_mod.write_run_info(self.save_path, info)

        # ---- training
        def learn(self, model: BaseAlgorithm) -> None:
            step = self.resume_step
            tb_dir = None
            if self.tensorboard_dir is not None:
                tb_dir = os.path.join(self.tensorboard_dir, f"{self.algo}_{os.path.basename(self.save_path)}")
            model.set_logger(make_run_logger(self.save_path, self.verbose, tb_dir, step, self.launch.tensorboard))
            if step is not None and self.eval_callback is not None:
                self.eval_callback.load_history(step)
                self.eval_callback.n_calls = step // self.n_tasks
            if not self.resumed:
                super().learn(model)
                return
            kwargs: dict[str, Any] = {}
            if self.log_interval > -1:
                kwargs["log_interval"] = self.log_interval
            elif self.log_interval < -1:
                kwargs["log_interval"] = None
            if self.callbacks:
                kwargs["callback"] = self.callbacks
            remaining = self.n_timesteps - model.num_timesteps
            try:
                if remaining > 0:
                    model.learn(remaining, reset_num_timesteps=False, **kwargs)
                else:
                    print(f"Nothing to do: the run is at {model.num_timesteps} of {self.n_timesteps} steps.")
            except KeyboardInterrupt:
                pass
            finally:
                if self.callbacks and remaining > 0:
                    self.callbacks[0].on_training_end()
                with contextlib.suppress(EOFError):
                    model.get_env().close()  # type: ignore[union-attr]

        def save_trained_model(self, model: BaseAlgorithm) -> None:
            super().save_trained_model(model)
            run_info_mod.update_run_info(
                self.save_path,
                timesteps=int(model.num_timesteps),
                n_updates=int(getattr(model, "_n_updates", 0)),
                finished=bool(model.num_timesteps >= self.n_timesteps),
                ended=run_info_mod.now(),
                final_model=f"{self.env_name}.zip",
            )
            if self._eval_env is not None:
                self._eval_env.close()

    return MultiTaskExperimentManager


# --------------------------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------------------------
def find_config_dir() -> Path | None:
    """``zoo_configs/`` of the current directory, else of the source checkout holding this package."""
    for base in (Path.cwd(), Path(__file__).resolve().parent.parent):
        if (base / CONFIG_DIR_NAME).is_dir():
            return base / CONFIG_DIR_NAME
    return None


def default_config(algo: str) -> Path | None:
    """``zoo_configs/<algo>.yml`` (see :func:`find_config_dir`), or None."""
    directory = find_config_dir()
    if directory is None:
        return None
    path = directory / f"{algo}.yml"
    return path if path.is_file() else None


@contextlib.contextmanager
def _patched(obj: Any, name: str, value: Any) -> Iterator[None]:
    old = getattr(obj, name)
    setattr(obj, name, value)
    try:
        yield
    finally:
        setattr(obj, name, old)


def _flag_value(argv: Sequence[str], *names: str) -> str | None:
    """Value of the last occurrence of an option (``--x v`` or ``--x=v``) in ``argv``."""
    value = None
    for i, arg in enumerate(argv):
        for name in names:
            if arg == name and i + 1 < len(argv):
                value = argv[i + 1]
            elif arg.startswith(name + "="):
                value = arg.split("=", 1)[1]
    return value


def _has_flag(argv: Sequence[str], *names: str) -> bool:
    return any(arg in names or any(arg.startswith(n + "=") for n in names) for arg in argv)


def _run_dir_of(log_folder: str, algo: str, env_id: str, exp_id: int = 0) -> Path:
    """Run folder ``<log_folder>/<algo>/<env>_<id>`` (``exp_id=0``: the latest)."""
    from huggingface_sb3 import EnvironmentName
    from rl_zoo3.utils import get_latest_run_id

    env_name = EnvironmentName(env_id)
    if exp_id == 0:
        exp_id = get_latest_run_id(os.path.join(log_folder, algo), env_name)
        if exp_id == 0:
            raise FileNotFoundError(f"No run of {algo} on {env_id} in {log_folder}/{algo}/.")
    return Path(log_folder) / algo / f"{env_name}_{exp_id}"


_TRACKED_FLAGS: dict[str, tuple[str, ...]] = {
    "eval_freq": ("--eval-freq",),
    "eval_episodes": ("--eval-episodes",),
    "save_freq": ("--save-freq",),
    "n_timesteps": ("-n", "--n-timesteps"),
    "env_kwargs": ("--env-kwargs",),
    "eval_env_kwargs": ("--eval-env-kwargs",),
    "vec_env": ("--vec-env",),
    "log_interval": ("--log-interval",),
    "save_replay_buffer": ("--save-replay-buffer",),
    "tensorboard_log": ("-tb", "--tensorboard-log"),
}
"""rl-zoo flags whose presence on the command line matters (file defaults, resumed runs' own settings)."""


def train(argv: Sequence[str]) -> None:
    """``train``: rl-zoo's train with the launcher's additions (see the module docstring)."""
    import rl_zoo3.train

    parser = argparse.ArgumentParser(prog="python -m sb3_mtte.zoo train", add_help=False)
    parser.add_argument("--resume", nargs="?", const="", default=None, metavar="RUN_DIR")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--no-tensorboard", action="store_true", default=None)
    parser.add_argument("--keep-buffers", type=int, default=None)
    parser.add_argument("--no-align-checkpoints", action="store_true", default=None)
    parser.add_argument("--exp-id", type=int, default=None)
    ours, zoo_argv = parser.parse_known_args(list(argv))
    saved_launcher: dict[str, Any] = {}
    if _has_flag(zoo_argv, "-h", "--help"):
        print(
            "sb3_mtte options: --resume [RUN_DIR] (continue the latest checkpoint of RUN_DIR, default the latest "
            "run of --algo/--env in -f), --exp-id N (run folder <env>_N instead of the next free one), "
            "--no-progress, --no-tensorboard, --keep-buffers K (replay-buffer checkpoints kept, 0 = all; "
            "default 1), --no-align-checkpoints.\nrl-zoo options:"
        )
    if ours.resume:  # --resume RUN_DIR: the run's own algorithm and env unless given
        info = run_info_mod.read_run_info(ours.resume) or {}
        for flag, key in (("--algo", "algo"), ("--env", "env_id")):
            if not _has_flag(zoo_argv, flag) and key in info:
                zoo_argv += [flag, str(info[key])]
    algo = _flag_value(zoo_argv, "--algo") or "ppo"
    env_id = _flag_value(zoo_argv, "--env")
    if env_id is None and not _has_flag(zoo_argv, "-h", "--help"):
        raise SystemExit(f"--env is required: {benchmark_help()}")
    if env_id is not None and not register_env_id(env_id):
        raise SystemExit(f"{env_id!r} is not a benchmark of sb3_mtte: {benchmark_help()}")
    register_algos()
    log_folder = _flag_value(zoo_argv, "-f", "--log-folder") or "logs"
    resume_dir = None
    if ours.resume is not None:
        if env_id is None:
            raise SystemExit("--resume needs --algo and --env (or a run folder: --resume RUN_DIR).")
        resume_dir = Path(ours.resume) if ours.resume else _run_dir_of(log_folder, algo, env_id)
        info = run_info_mod.read_run_info(resume_dir) or {}
        if info and (info.get("algo"), info.get("env_id")) != (algo, env_id):
            raise SystemExit(
                f"{resume_dir} is a run of --algo {info.get('algo')} --env {info.get('env_id')}, "
                f"not --algo {algo} --env {env_id}."
            )
        if not _has_flag(zoo_argv, "--seed") and "seed" in info:
            zoo_argv += ["--seed", str(info["seed"])]
        saved_launcher = dict(info.get("launcher") or {})
        if ours.resume and not _has_flag(zoo_argv, "-f", "--log-folder"):
            zoo_argv += ["-f", str(resume_dir.parent.parent)]
        resume_dir = str(resume_dir)
    if not _has_flag(zoo_argv, "-conf", "--conf-file") and not _has_flag(zoo_argv, "-h", "--help"):
        config = default_config(algo)
        if config is None and algo in ALGO_KEYS:
            raise SystemExit(f"No zoo_configs/{algo}.yml found: pass -conf <file>.yml.")
        if config is not None:
            zoo_argv += ["-conf", str(config)]
    if not ours.no_progress and not _has_flag(zoo_argv, "-P", "--progress"):
        zoo_argv.append("-P")
    flags = {dest: _has_flag(zoo_argv, *names) for dest, names in _TRACKED_FLAGS.items()}
    launch = LaunchOptions(
        resume_dir=resume_dir,
        exp_id=ours.exp_id,
        flags_given=frozenset(k for k, given in flags.items() if given),
        keep_buffers=ours.keep_buffers if ours.keep_buffers is not None else saved_launcher.get("keep_buffers", 1),
        align_checkpoints=(
            not ours.no_align_checkpoints
            if ours.no_align_checkpoints is not None
            else saved_launcher.get("align_checkpoints", True)
        ),
        tensorboard=not ours.no_tensorboard
        if ours.no_tensorboard is not None
        else saved_launcher.get("tensorboard", True),
    )
    manager_cls = _exp_manager_class()

    def make_manager(*args: Any, **kwargs: Any) -> Any:
        return manager_cls(*args, launch=launch, **kwargs)

    with (
        _patched(sys, "argv", [f"{sys.argv[0]} train", *zoo_argv]),
        _patched(rl_zoo3.train, "ExperimentManager", make_manager),
    ):
        rl_zoo3.train.train()


def benchmark_help() -> str:
    return (
        "MT10, MT20, MT50, toy-conflict, toy-agree or toy-<conflict|agree>-<N>, optionally with a budget suffix "
        f"({', '.join('-' + s for s in BUDGET_SUFFIXES)})."
    )


def _locate_model(argv: Sequence[str], default_folder: str = "logs") -> tuple[str, str, str, str, str]:
    """(algo, env_id, name_prefix, model_path, log_path) of an enjoy/record_video command line (rl-zoo's rules)."""
    from huggingface_sb3 import EnvironmentName
    from rl_zoo3.utils import get_model_path

    algo = _flag_value(argv, "--algo") or "mtsacte"
    env_id = _flag_value(argv, "--env")
    if env_id is None:
        raise SystemExit("--env is required.")
    folder = _flag_value(argv, "-f", "--folder") or default_folder
    exp_id = int(_flag_value(argv, "--exp-id") or 0)
    checkpoint = _flag_value(argv, "--load-checkpoint")
    name_prefix, model_path, log_path = get_model_path(
        exp_id,
        folder,
        algo,
        EnvironmentName(env_id),
        _has_flag(argv, "--load-best"),
        checkpoint,
        _has_flag(argv, "--load-last-checkpoint"),
    )
    return algo, env_id, name_prefix, model_path, log_path


def enjoy(argv: Sequence[str]) -> None:
    """``enjoy``: rl-zoo's enjoy with one sub-env per task (``--n-envs`` is set to the task count)."""
    import rl_zoo3.enjoy
    from rl_zoo3.exp_manager import ExperimentManager

    argv = list(argv)
    env_id = _flag_value(argv, "--env")
    if env_id is None or not register_env_id(env_id):
        raise SystemExit(f"--env must be a benchmark of sb3_mtte: {benchmark_help()}")
    register_algos()
    if not _has_flag(argv, "-f", "--folder"):
        argv += ["-f", "logs"]
    n_tasks = env_id_n_tasks(env_id)
    n_envs = _flag_value(argv, "--n-envs")
    if n_envs is not None and int(n_envs) != n_tasks:
        raise SystemExit(f"{env_id} has {n_tasks} tasks: --n-envs must be {n_tasks} (one sub-env per task).")
    if n_envs is None:
        argv += ["--n-envs", str(n_tasks)]
    _, _, _, _, log_path = _locate_model(argv)
    info = run_info_mod.read_run_info(log_path) or {}
    factory = MultiTaskVecEnvFactory(n_tasks, seed=int(info.get("benchmark_seed", 0)), report_episodes=True)
    with (
        _patched(sys, "argv", [f"{sys.argv[0]} enjoy", *argv]),
        _patched(ExperimentManager, "default_vec_env_cls", factory),
    ):
        rl_zoo3.enjoy.enjoy()


def load_model(path: str | os.PathLike, device: str = "auto", env: VecEnv | None = None) -> BaseAlgorithm:
    """Load an MTSAC or MTSACTE checkpoint, picking the class from the zip."""
    name = read_checkpoint_data(path).get("algorithm_name")
    if name not in ALGORITHM_CLASSES:
        raise ValueError(f"{path} was not saved by MTSAC or MTSACTE (algorithm_name={name!r}).")
    return ALGORITHM_CLASSES[name].load(path, env=env, device=device)


def _write_video(frames: list[np.ndarray], path: Path, fps: int) -> None:
    from moviepy.video.io.ImageSequenceClip import ImageSequenceClip

    clip = ImageSequenceClip(list(frames), fps=fps)
    clip.write_videofile(str(path), logger=None)
    clip.close()


def record_video(argv: Sequence[str]) -> list[Path]:
    """``record_video``: one video per task (and optionally a tiled one) of a trained model.

    Meta-World renders with MuJoCo: headless machines need ``MUJOCO_GL=egl`` (set by default when there is no
    display) or ``osmesa``.

    :return: the written video paths.
    """
    parser = argparse.ArgumentParser(prog="python -m sb3_mtte.zoo record_video")
    parser.add_argument("--env", required=True, help="env id of the run (MT10, MT10-smoke, toy-conflict, ...)")
    parser.add_argument("-f", "--folder", default="logs", help="log folder")
    parser.add_argument("-o", "--output-folder", default=None, help="video folder (default: <run>/videos)")
    parser.add_argument("--algo", default="mtsacte", help="zoo algorithm key")
    parser.add_argument("-n", "--n-timesteps", type=int, default=None, help="max vector steps (default: as needed)")
    parser.add_argument("--episodes", type=int, default=1, help="episodes recorded per task")
    parser.add_argument("--stochastic", action="store_true", help="sample actions (default: deterministic)")
    parser.add_argument("--seed", type=int, default=None, help="benchmark seed (default: the run's)")
    parser.add_argument("--exp-id", type=int, default=0, help="run id (0: latest)")
    parser.add_argument("--load-best", action="store_true")
    parser.add_argument("--load-checkpoint", type=int, default=None)
    parser.add_argument("--load-last-checkpoint", action="store_true")
    parser.add_argument("--env-kwargs", type=str, nargs="+", default=None, help="key:value env keyword arguments")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--fps", type=int, default=None)
    parser.add_argument("--tile", action="store_true", help="also write one video of all tasks side by side")
    parser.add_argument("--flip", action="store_true", help="flip frames vertically (Meta-World's corner cameras)")
    args = parser.parse_args(list(argv))
    if not os.environ.get("DISPLAY") and "MUJOCO_GL" not in os.environ:
        os.environ["MUJOCO_GL"] = "egl"
    if not register_env_id(args.env):
        raise SystemExit(f"--env must be a benchmark of sb3_mtte: {benchmark_help()}")
    register_algos()
    locate = ["--algo", args.algo, "--env", args.env, "-f", args.folder, "--exp-id", str(args.exp_id)]
    if args.load_best:
        locate.append("--load-best")
    if args.load_checkpoint is not None:
        locate += ["--load-checkpoint", str(args.load_checkpoint)]
    if args.load_last_checkpoint:
        locate.append("--load-last-checkpoint")
    _, env_id, name_prefix, model_path, log_path = _locate_model(locate, args.folder)
    info = run_info_mod.read_run_info(log_path) or {}
    seed = args.seed if args.seed is not None else int(info.get("benchmark_seed", 0))
    env_kwargs = _saved_env_kwargs(log_path, env_id)
    if args.env_kwargs:
        from rl_zoo3.utils import StoreDict

        namespace = argparse.Namespace()
        StoreDict(["--env-kwargs"], "env_kwargs")(parser, namespace, args.env_kwargs)
        env_kwargs.update(namespace.env_kwargs)
    env_kwargs["render_mode"] = "rgb_array"

    from stable_baselines3.common.vec_env.base_vec_env import tile_images

    from sb3_mtte.common.utils import get_task_names, short_task_name
    from sb3_mtte.envs import make_mt_env

    env = make_mt_env(split_env_id(env_id)[0], seed=seed, **env_kwargs)
    try:
        model = load_model(model_path, device=args.device)
        task_names = get_task_names(env)
        n_tasks = env.num_envs
        if env.has_attr("set_eval_mode"):
            env.env_method("set_eval_mode", True)
        fps = args.fps or int((env.metadata or {}).get("render_fps", 0) or 30)
        frames: list[list[np.ndarray]] = [[] for _ in range(n_tasks)]
        tiled: list[np.ndarray] = []
        episodes = np.zeros(n_tasks, dtype=int)
        obs = env.reset()
        steps = 0
        while (episodes < args.episodes).any() and (args.n_timesteps is None or steps < args.n_timesteps):
            images = env.get_images()
            if any(image is None for image in images):
                raise RuntimeError("The env returned no image: it cannot render in rgb_array mode here.")
            if args.flip:
                images = [image[::-1] for image in images]
            for i in np.flatnonzero(episodes < args.episodes):
                frames[i].append(images[i])
            if args.tile:
                tiled.append(tile_images(images))
            actions, _ = model.predict(obs, deterministic=not args.stochastic)
            obs, _, dones, _ = env.step(actions)
            episodes += dones.astype(int)
            steps += 1
        out_dir = Path(args.output_folder or os.path.join(log_path, "videos"))
        out_dir.mkdir(parents=True, exist_ok=True)
        written = []
        for i, task_frames in enumerate(frames):
            if task_frames:
                path = out_dir / f"{name_prefix}-{i:02d}_{short_task_name(task_names[i])}.mp4"
                _write_video(task_frames, path, fps)
                written.append(path)
        if args.tile and tiled:
            path = out_dir / f"{name_prefix}-all_tasks.mp4"
            _write_video(tiled, path, fps)
            written.append(path)
        for path in written:
            print(f"Saved {path}")
        return written
    finally:
        env.close()


def _saved_env_kwargs(log_path: str, env_id: str) -> dict[str, Any]:
    """``env_kwargs`` a run was trained with (its ``args.yml``), as rl-zoo's enjoy reads them."""
    import yaml
    from huggingface_sb3 import EnvironmentName

    path = Path(log_path) / EnvironmentName(env_id) / "args.yml"
    if not path.is_file():
        return {}
    with open(path) as file:
        loaded = yaml.load(file, Loader=yaml.UnsafeLoader)
    return dict(loaded.get("env_kwargs") or {})


COMMANDS = {"train": train, "enjoy": enjoy, "record_video": record_video}


def main(argv: Sequence[str] | None = None) -> Any:
    """``python -m sb3_mtte.zoo {train,enjoy,record_video} ...``"""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        print(f"usage: python -m sb3_mtte.zoo {{{','.join(COMMANDS)}}} [options]\n\n{__doc__}")
        raise SystemExit(0 if argv and argv[0] in ("-h", "--help") else 2)
    register_standard_env_ids()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*render_mode.*")
        return COMMANDS[argv[0]](argv[1:])


__all__ = [
    "ALGO_KEYS",
    "BUDGET_SUFFIXES",
    "Checkpoint",
    "LaunchOptions",
    "MultiTaskCheckpointCallback",
    "MultiTaskVecEnvFactory",
    "ZooEvalCallback",
    "benchmark_task_names",
    "default_config",
    "enjoy",
    "env_id_n_tasks",
    "find_checkpoints",
    "find_latest_checkpoint",
    "load_model",
    "main",
    "make_run_logger",
    "make_task_env",
    "record_video",
    "register_algos",
    "register_env_id",
    "register_standard_env_ids",
    "restart_envs",
    "split_env_id",
    "train",
]

if __name__ == "__main__":
    # run the imported module, not this __main__ copy: env constructors must pickle by reference (subprocesses)
    from sb3_mtte.zoo import main as _main

    _main()
