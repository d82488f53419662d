"""MTSAC: multi-task SAC with per-task entropy coefficients and (clipped) per-task soft-Q losses.

The Table-1 baselines of the paper are MTSAC with a policy alias (SAC-MT, SAC-MT-MH, SAC-soft-modular,
SAC-Ind) and, for SAC-MT-with-clip, ``q_loss_clip=2000``.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule

from sb3_mtte.common.buffers import MultiTaskReplayBuffer, MultiTaskReplayBufferSamples
from sb3_mtte.common.captured_update import set_learning_rate
from sb3_mtte.common.losses import clipped_sample_fraction, clipped_soft_q_loss, sac_task_objective
from sb3_mtte.common.multitask_algorithm import MultiTaskOffPolicyAlgorithm
from sb3_mtte.common.update_hooks import GradientSurgery, UpdateHook, UpdateHooks
from sb3_mtte.common.update_monitor import Stats, UpdateMonitor
from sb3_mtte.common.utils import caller_stacklevel, check_not_gymnasium_vector_env, polyak_update
from sb3_mtte.mtsac.checks import MTSAC_ARGUMENTS, ArgumentSpec, check_arguments, check_buffer_holds_a_batch
from sb3_mtte.mtsac.moore import MOOREPolicy
from sb3_mtte.mtsac.paco import PaCoPolicy
from sb3_mtte.mtsac.policies import IndependentPolicy, MTSACPolicy, MultiHeadPolicy, SoftModularPolicy
from sb3_mtte.mtsac.task_logs import MEAN_STATS, record_train_stats
from sb3_mtte.mtsac.task_steps import enable_kept_rows, task_step
from sb3_mtte.mtsac.temperature import MultiTaskTemperature, learned_initial_value, resolve_target_entropy
from sb3_mtte.mtsac.update_path import resolve_update_path, update_runner

SelfMTSAC = TypeVar("SelfMTSAC", bound="MTSAC")


class MTSAC(MultiTaskOffPolicyAlgorithm):
    """Multi-task Soft Actor-Critic for a VecEnv with one sub-env per task (observation = state + one-hot).

    Batches are balanced and task-major: every update draws ``batch_size`` (L) transitions per task. With a
    single task (N = 1, e.g. a gymnasium env wrapped in :class:`~sb3_mtte.envs.wrappers.OneHotTaskWrapper`) and
    ``"MlpPolicy"``, the update is SB3's SAC update.

    :meth:`train` runs :meth:`_update` once per gradient step, eagerly or as its CUDA graph. The update computes the
    ``(N,)`` per-task losses of the entropy coefficients, the critic and the actor, in that order, and hands each to
    :meth:`_entropy_coef_step`, :meth:`_critic_step` or :meth:`_actor_step`, which minimise ``sum_i w_i L_i``.
    What else happens to the per-task losses and gradients (the actor's weights, a mask of tasks, a combination of
    the task gradients, a reset after the update) is :attr:`update_hook`'s, built from :meth:`update_hooks` and the
    policy's (:mod:`sb3_mtte.common.update_hooks`).

    :param policy: ``"MlpPolicy"`` (SAC-MT), ``"MultiHeadPolicy"`` (SAC-MT-MH), ``"SoftModularPolicy"``
        (SAC-soft-modular), ``"IndependentPolicy"`` (SAC-Ind), ``"MOOREPolicy"`` (MOORE) or ``"PaCoPolicy"`` (PaCo),
        or a policy class.
    :param env: multi-task VecEnv, sub-env i is task i (see :func:`sb3_mtte.make_mt_env`).
    :param learning_rate: Adam learning rate (delta), a float or schedule.
    :param buffer_size: replay capacity in transitions over all tasks.
    :param learning_starts: transitions (over all tasks) collected with random actions before learning.
    :param batch_size: L, transitions per task in every mini-batch (total N * L).
    :param tau: Polyak coefficient of the target critics.
    :param gamma: discount factor.
    :param train_freq: update every ``train_freq`` vector steps (one env step of every task).
    :param gradient_steps: gradient updates per ``train_freq``.
    :param ent_coef: ``"auto"`` / ``"auto_<init>"`` (learned beta_i) or a fixed float.
    :param target_entropy: target entropy H-bar, ``"auto"`` = -dim(A).
    :param target_update_interval: gradient steps between target updates.
    :param critic_arch: ``"per_task"`` (one twin Q per task, the paper's setting) or ``"shared"``.
    :param ent_coef_arch: ``"per_task"`` (a learned beta_i per task, the paper's setting) or ``"shared"`` (one learned
        beta for every task, minimising the mean of the tasks' temperature losses as SB3's SAC does).
    :param q_loss_clip: V_clip of Eq. 16; None = plain soft Bellman loss (Eq. 15).
    :param gradient_surgery: None (minimise sum_i w_i L_i), ``"pcgrad"`` (Yu et al. 2020) or ``"cagrad"``
        (Liu et al. 2021): the update of the shared actor, of the critic when ``critic_arch="shared"`` and of the
        entropy coefficient when ``ent_coef_arch="shared"`` follows the method's combination of the per-task
        gradients.
    :param cagrad_c: CAGrad's c in (0, 1), radius of the ball ||d - g0|| <= c ||g0||.
    :param update_path: ``"auto"`` (a CUDA graph of the update on CUDA where the update allows it, else eager),
        ``"eager"`` or ``"cuda_graph"`` (:mod:`sb3_mtte.mtsac.update_path`). The same numbers on the CPU; on CUDA
        the graph's agree within float tolerance (its learning rates are float32 tensors).
    :param overlap_env_step: run each step's updates while the envs take the step, between sending the actions and
        receiving the observations; each update then samples the transitions before its step
        (:mod:`sb3_mtte.common.overlapped_rollout`). Off by default: it changes the algorithm.
    :param action_noise: optional exploration noise.
    :param replay_buffer_class: replay buffer class (a :class:`MultiTaskReplayBuffer` by default).
    :param replay_buffer_kwargs: its keyword arguments.
    :param policy_kwargs: policy keyword arguments (``net_arch``, ``actor_kwargs``, ...).
    :param stats_window_size: episodes averaged in rollout logs.
    :param tensorboard_log: tensorboard log folder.
    :param verbose: 0, 1 or 2.
    :param seed: random seed.
    :param device: ``"auto"`` (CUDA when present), ``"cpu"`` or ``"cuda"``.
    :param _init_setup_model: whether to build the networks now.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MTSACPolicy,
        "MultiHeadPolicy": MultiHeadPolicy,
        "SoftModularPolicy": SoftModularPolicy,
        "IndependentPolicy": IndependentPolicy,
        "MOOREPolicy": MOOREPolicy,
        "PaCoPolicy": PaCoPolicy,
    }
    argument_specs: ClassVar[Mapping[str, ArgumentSpec]] = MTSAC_ARGUMENTS
    """Type and range of every argument but ``policy`` and ``env`` (:mod:`sb3_mtte.mtsac.checks`)."""
    policy: MTSACPolicy

    def __init__(
        self,
        policy: str | type[MTSACPolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 5_000,
        batch_size: int = 128,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        ent_coef: str | float = "auto",
        target_entropy: str | float = "auto",
        target_update_interval: int = 1,
        critic_arch: str = "per_task",
        ent_coef_arch: str = "per_task",
        q_loss_clip: float | None = None,
        gradient_surgery: str | None = None,
        cagrad_c: float = 0.5,
        update_path: str = "auto",
        overlap_env_step: bool = False,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        check_arguments(type(self), locals())
        check_not_gymnasium_vector_env(env)
        super().__init__(
            policy,
            env,  # type: ignore[arg-type]
            learning_rate,
            buffer_size,
            learning_starts,
            batch_size,
            tau,
            gamma,
            train_freq,
            gradient_steps,
            action_noise,
            replay_buffer_class=replay_buffer_class or MultiTaskReplayBuffer,
            replay_buffer_kwargs=replay_buffer_kwargs,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            supported_action_spaces=(spaces.Box,),
            support_multi_env=True,
            sde_support=False,
        )
        self.algorithm_name = type(self).__name__
        self._setup_tasks()
        if self.env is not None:
            check_buffer_holds_a_batch(buffer_size, batch_size, self.n_tasks)
        self.critic_arch, self.ent_coef_arch, self.q_loss_clip = critic_arch, ent_coef_arch, q_loss_clip
        self.gradient_surgery, self.cagrad_c, self.update_path = gradient_surgery, cagrad_c, update_path
        self.overlap_env_step = overlap_env_step
        self.ent_coef, self.target_entropy = ent_coef, target_entropy
        self.target_update_interval = target_update_interval
        self.temperature: MultiTaskTemperature | None = None
        if _init_setup_model:
            self._setup_model()
            self._check_first_observations()

    # ----------------------------------------------------------------------------------------------- set-up
    def _setup_model(self) -> None:
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        self.policy = self.policy_class(
            self.observation_space,
            self.action_space,
            self.lr_schedule,
            **self._policy_build_kwargs(),
            **self.policy_kwargs,
        ).to(self.device)
        self._convert_train_freq()
        self._create_aliases()
        self.update_hook = UpdateHooks([*self.update_hooks(), *self.policy.update_hooks()])
        self.update_hook.attach(self)
        enable_kept_rows((self.actor, self.critic), self.update_hook.combines_gradients)
        if self.env is not None:
            self._setup_replay_buffer()
        self._setup_temperature()
        self._setup_update_path()

    def update_hooks(self) -> list[UpdateHook]:
        """The algorithm's extensions of the update (before the policy's): gradient surgery when set."""
        if self.gradient_surgery is None:
            return []
        return [GradientSurgery(self.gradient_surgery, self.cagrad_c)]

    def _policy_build_kwargs(self) -> dict[str, Any]:
        """Policy arguments owned by the algorithm (not stored in ``policy_kwargs``)."""
        return {"n_tasks": self.n_tasks, "critic_arch": self.critic_arch}

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target

    def _setup_temperature(self) -> None:
        """beta_i: a learned :class:`MultiTaskTemperature`, or the fixed ``ent_coef_tensor``."""
        self.target_entropy = resolve_target_entropy(self.target_entropy, self.action_space)
        init_value = learned_initial_value(self.ent_coef)
        self.temperature = None
        if init_value is None:
            self.ent_coef_tensor = th.full((self.n_tasks,), float(self.ent_coef), device=self.device)
            return
        shared, learning_rate = self.ent_coef_arch == "shared", self.lr_schedule(1)
        self.temperature = MultiTaskTemperature(
            self.n_tasks, init_value, self.target_entropy, shared, learning_rate, self.device
        )

    @property
    def log_ent_coef(self) -> th.Tensor | None:
        """The learned log beta (the temperature's; SB3's name, saved in checkpoints), None for a fixed beta."""
        return None if self.temperature is None else self.temperature.log_ent_coef

    @property
    def ent_coef_optimizer(self) -> th.optim.Optimizer | None:
        """The optimizer of the learned log beta (the temperature's; SB3's name), None for a fixed beta."""
        return None if self.temperature is None else self.temperature.optimizer

    @property
    def entropy_coefficients(self) -> th.Tensor:
        """Current per-task beta_i, shape (N,) (one value N times when shared)."""
        return self.ent_coef_tensor if self.temperature is None else self.temperature.ent_coef

    def resolved_update_path(self) -> str:
        """``"eager"`` or ``"cuda_graph"`` (:func:`~sb3_mtte.mtsac.update_path.resolve_update_path`)."""
        return resolve_update_path(self.update_path, self.device, self.update_hook.capturable)

    def _setup_update_path(self, capture: bool = True) -> None:
        """Build the monitor and the runner of the resolved path (``capture=False``: the graph path's static
        inputs and deferred reads without the graph, which the CPU can run). What the old monitor kept is read
        first (its statistics recorded, a non-finite loss raised)."""
        if getattr(self, "update_monitor", None) is not None:
            self.update_monitor.read()
        path = self.resolved_update_path() if capture else "cuda_graph"
        deferred = path != "eager"
        record = self._record_train_stats
        self.update_monitor = UpdateMonitor(self.device, deferred, record, MEAN_STATS, self._n_updates)
        self._update_runner = update_runner(path, self._update, self._optimizers, self.device, capture)

    def _optimizers(self) -> list[th.optim.Optimizer]:
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        return optimizers if self.ent_coef_optimizer is None else [*optimizers, self.ent_coef_optimizer]

    # --------------------------------------------------------------------------------------------- training
    def train(self, gradient_steps: int, batch_size: int = 128) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate(self._optimizers())
        self.update_monitor.set_env_step(self.num_timesteps)
        stats: dict[str, list[th.Tensor]] = {}
        for gradient_step in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            polyak = gradient_step % self.target_update_interval == 0
            for key, value in self._update_runner(replay_data, polyak).items():  # _update, or its CUDA graph
                stats.setdefault(key, []).append(value)
        self._n_updates += gradient_steps
        self.update_monitor.add_train_stats({key: th.stack(values).mean(0) for key, values in stats.items()})

    def _update(self, replay_data: MultiTaskReplayBufferSamples, polyak: bool) -> Stats:
        """One SAC update on a task-major batch: beta_i (Eq. 3), the critics (Eq. 15-16), the actor (Eq. 9), then
        the Polyak step of the target critics when ``polyak``. It reads no device tensor on the host, so that the
        CUDA graph can record it."""
        actions_pi, log_prob = self.policy.action_log_prob(replay_data.observations)

        # Entropy coefficients (Eq. 3): the losses below use beta_i from before this step, as SB3's SAC
        if self.temperature is None:
            ent_coef = self.ent_coef_tensor
            stats = {"ent_coef": ent_coef}
        else:
            ent_coef = self.temperature.ent_coef
            ent_coef_loss = self._entropy_coef_step(self.temperature.loss(log_prob), self.temperature.task_weights)
            stats = {"ent_coef_loss": ent_coef_loss.detach(), "ent_coef": ent_coef}

        # Critics (Eq. 15-16): every task's clipped soft Bellman loss, twin critics summed
        with th.no_grad():
            next_actions, next_log_prob = self.policy.action_log_prob(replay_data.next_observations)
            next_q = self.critic_target(replay_data.next_observations, next_actions).min(dim=0).values
            next_q = next_q - ent_coef[:, None] * next_log_prob
            target_q = replay_data.rewards + (1 - replay_data.dones) * self.gamma * next_q
        current_q = self.critic(replay_data.observations, replay_data.actions)
        critic_losses = clipped_soft_q_loss(current_q, target_q, self.q_loss_clip)
        if self.q_loss_clip is not None:
            stats["q_loss_clip_fraction"] = clipped_sample_fraction(current_q.detach(), target_q, self.q_loss_clip)
        loss_mask = self.update_hook.loss_mask(critic_losses.detach())
        self._critic_step(critic_losses, loss_mask)
        stats["critic_loss"] = critic_losses.detach()

        # Actor (Eq. 9): the per-task losses -J_SAC,i weighted by w; the critics are constants of its backward pass
        self.critic.requires_grad_(False)
        min_q_pi = self.critic(replay_data.observations, actions_pi).min(dim=0).values
        self.critic.requires_grad_(True)
        actor_losses = -sac_task_objective(log_prob, min_q_pi, ent_coef)
        stats["actor_loss"] = self._actor_step(actor_losses, self._actor_weights() * loss_mask).detach()
        self.update_hook.after_update()

        if polyak:
            polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
        self.update_monitor.count_update()
        return stats

    def _actor_weights(self) -> th.Tensor:
        """w of Eq. 9: the update hook's, else uniform 1/N."""
        weights = self.update_hook.task_weights()
        if weights is None:
            return th.full((self.n_tasks,), 1.0 / self.n_tasks, device=self.device)
        return weights

    def _entropy_coef_step(self, task_losses: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
        """One step of the learned beta_i on the ``(N,)`` temperature losses; returns the loss minimised."""
        combining_hook = self._combining_hook(self.ent_coef_arch == "shared")
        optimizer, name = self.ent_coef_optimizer, "entropy coefficient loss"
        return task_step(optimizer, name, task_losses, task_weights, self.update_monitor, combining_hook)  # type: ignore[arg-type]

    def _critic_step(self, task_losses: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
        """One critic step on the ``(N,)`` critic losses, weighted by the update hook's loss mask."""
        combining_hook = self._combining_hook(self.critic_arch == "shared")
        optimizer, monitor = self.critic.optimizer, self.update_monitor
        return task_step(optimizer, "critic loss", task_losses, task_weights, monitor, combining_hook, self.critic)

    def _actor_step(self, task_losses: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
        """One actor step on the ``(N,)`` losses -J_SAC,i, weighted by w of Eq. 9 times the loss mask."""
        combining_hook = self._combining_hook(shared=True)
        optimizer, monitor = self.actor.optimizer, self.update_monitor
        return task_step(optimizer, "actor loss", task_losses, task_weights, monitor, combining_hook, self.actor)

    def _combining_hook(self, shared: bool) -> UpdateHook | None:
        """The update hook when it combines the task gradients and the tasks share the parameters, else None
        (disjoint per-task parameters have nothing to combine)."""
        return self.update_hook if shared and self.update_hook.combines_gradients else None

    def _update_learning_rate(self, optimizers: list[th.optim.Optimizer] | th.optim.Optimizer) -> None:
        """SB3's, writing a learning rate held in a tensor in place (the CUDA graph reads it there)."""
        learning_rate = self.lr_schedule(self._current_progress_remaining)
        self.logger.record("train/learning_rate", learning_rate)
        set_learning_rate(optimizers if isinstance(optimizers, list) else [optimizers], learning_rate)

    # ------------------------------------------------------------------------------------------------- logs
    def _record_train_stats(self, stats: dict[str, np.ndarray]) -> None:
        record_train_stats(self.logger, stats, self._n_updates, self.task_names)

    # ------------------------------------------------------------------------------------------ save / load
    def _excluded_save_params(self) -> list[str]:
        aliases = ["actor", "critic", "critic_target", "temperature"]
        runtime = ["update_hook", "update_monitor", "_update_runner"]
        return [*super()._excluded_save_params(), *self.unsaved_attributes, *aliases, *runtime]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        if self.ent_coef_optimizer is not None:
            return [*state_dicts, "ent_coef_optimizer"], ["log_ent_coef"]
        return state_dicts, ["ent_coef_tensor"]

    def set_parameters(self, load_path_or_dict, exact_match: bool = True, device: th.device | str = "auto") -> None:
        """SB3's, then a new runner: a loaded optimizer state replaces the tensors a captured graph would read."""
        super().set_parameters(load_path_or_dict, exact_match, device)
        self._setup_update_path()

    def learn(
        self: SelfMTSAC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "MTSAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfMTSAC:
        super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)
        self.update_monitor.check()
        if self.num_timesteps <= self.learning_starts:  # SB3 updates once num_timesteps > learning_starts
            warnings.warn(
                f"learn ended at {self.num_timesteps} env steps, not past learning_starts={self.learning_starts}: "
                "no gradient update was made; learn for more steps or lower learning_starts.",
                stacklevel=caller_stacklevel(),
            )
        return self
