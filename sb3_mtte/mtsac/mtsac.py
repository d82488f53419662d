"""MTSAC: multi-task SAC with per-task entropy coefficients and (clipped) per-task soft-Q losses.

The Table-1 baselines of the paper are MTSAC with a policy alias (SAC-MT, SAC-MT-MH, SAC-soft-modular,
SAC-Ind) and, for SAC-MT-with-clip, ``q_loss_clip=2000``.
"""

from __future__ import annotations

import math
import warnings
from collections import deque
from typing import Any, ClassVar, TypeVar

import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.vec_env import VecEnv

from sb3_mtte.common.buffers import MultiTaskReplayBuffer, MultiTaskReplayBufferSamples
from sb3_mtte.common.checkpoints import capture_rng_state, check_checkpoint, restore_rng_state
from sb3_mtte.common.gradient_surgery import check_gradient_surgery
from sb3_mtte.common.losses import clipped_sample_fraction, clipped_soft_q_loss, sac_task_objective
from sb3_mtte.common.update_hooks import GradientSurgery, UpdateHook, UpdateHooks
from sb3_mtte.common.utils import (
    caller_stacklevel,
    check_batch_size,
    check_buffer_size,
    check_learning_rate,
    check_multitask_env,
    check_not_gymnasium_vector_env,
    check_one_hot,
    get_task_names,
)
from sb3_mtte.mtsac.entropy import EntropyCoefMixin, check_ent_coef_arch
from sb3_mtte.mtsac.moore import MOOREPolicy
from sb3_mtte.mtsac.paco import PaCoPolicy
from sb3_mtte.mtsac.policies import IndependentPolicy, MTSACPolicy, MultiHeadPolicy, SoftModularPolicy
from sb3_mtte.mtsac.task_logs import PerTaskLogMixin
from sb3_mtte.mtsac.task_steps import TaskStepMixin
from sb3_mtte.mtsac.update_path import UpdatePathMixin, check_update_path
from sb3_mtte.openmp import warn_if_spinning

SelfMTSAC = TypeVar("SelfMTSAC", bound="MTSAC")


def check_q_loss_clip(q_loss_clip: float | None) -> None:
    if q_loss_clip is not None and not (q_loss_clip > 0 and math.isfinite(q_loss_clip)):
        raise ValueError(f"q_loss_clip (V_clip) must be a positive number or None, got {q_loss_clip}.")


class MTSAC(EntropyCoefMixin, TaskStepMixin, UpdatePathMixin, PerTaskLogMixin, OffPolicyAlgorithm):
    """Multi-task Soft Actor-Critic for a VecEnv with one sub-env per task (observation = state + one-hot).

    Batches are balanced and task-major: every update draws ``batch_size`` (L) transitions per task. With a
    single task (N = 1, e.g. a gymnasium env wrapped in :class:`~sb3_mtte.envs.wrappers.OneHotTaskWrapper`) and
    ``"MlpPolicy"``, the update is SB3's SAC update.

    Every update hands the ``(N,)`` per-task losses and weights of the entropy coefficients, the critic and the actor
    to :meth:`_entropy_coef_step`, :meth:`_critic_step` and :meth:`_actor_step`, which minimise ``sum_i w_i L_i``.
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
    min_tasks: ClassVar[int] = 1
    """Smallest task count N the algorithm accepts (1: a single task with the one-hot ``[1.0]`` is SAC)."""
    policy: MTSACPolicy
    replay_buffer: MultiTaskReplayBuffer | None

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
        check_not_gymnasium_vector_env(env)
        check_batch_size(batch_size)
        check_buffer_size(buffer_size)
        check_learning_rate(learning_rate)
        check_q_loss_clip(q_loss_clip)
        check_gradient_surgery(gradient_surgery, cagrad_c)
        check_ent_coef_arch(ent_coef_arch)
        check_update_path(update_path)
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
        self.n_tasks = check_multitask_env(self.env, min_tasks=self.min_tasks) if self.env is not None else 0
        self.task_names: list[str] = get_task_names(self.env) if self.env is not None else []
        self.critic_arch = critic_arch
        self.ent_coef_arch = ent_coef_arch
        self.q_loss_clip = q_loss_clip
        self.gradient_surgery = gradient_surgery
        self.cagrad_c = cagrad_c
        self.update_path = update_path
        self.ent_coef = ent_coef
        self.target_entropy = target_entropy
        self.target_update_interval = target_update_interval
        self.log_ent_coef: th.Tensor | None = None
        self.ent_coef_optimizer: th.optim.Optimizer | None = None
        if _init_setup_model:
            self._setup_model()

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
        self._setup_update_hook()
        if self.env is not None:
            self._setup_replay_buffer()
        self._setup_entropy_coef()
        self._setup_update_path()

    def update_hooks(self) -> list[UpdateHook]:
        """The algorithm's extensions of the update (before the policy's): gradient surgery when set."""
        if self.gradient_surgery is None:
            return []
        return [GradientSurgery(self.gradient_surgery, self.cagrad_c)]

    def _setup_update_hook(self) -> None:
        self.update_hook = UpdateHooks([*self.update_hooks(), *self.policy.update_hooks()])
        self.update_hook.attach(self)
        self._enable_kept_rows()

    def _policy_build_kwargs(self) -> dict[str, Any]:
        """Policy arguments owned by the algorithm (not stored in ``policy_kwargs``)."""
        return {"n_tasks": self.n_tasks, "critic_arch": self.critic_arch}

    def _setup_replay_buffer(self) -> None:
        """Build the replay buffer (lazily, so ``load(path, env=None)`` allocates none)."""
        if self.replay_buffer is None:
            self.replay_buffer = self.replay_buffer_class(
                self.buffer_size,
                self.observation_space,
                self.action_space,
                device=self.device,
                n_envs=self.n_tasks,
                optimize_memory_usage=self.optimize_memory_usage,
                **self.replay_buffer_kwargs,
            )

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ):
        self._setup_replay_buffer()
        result = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        check_one_hot(self._last_obs, self.n_tasks)  # type: ignore[arg-type]
        if self.device.type == "cpu":
            warn_if_spinning(th.get_num_threads())
        if not hasattr(self, "_task_success") or reset_num_timesteps:
            self._task_success = [deque(maxlen=self._stats_window_size) for _ in range(self.n_tasks)]
        return result

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        check_not_gymnasium_vector_env(env)
        if isinstance(env, VecEnv):
            check_multitask_env(env, self.n_tasks, min_tasks=self.min_tasks)
        super().set_env(env, force_reset)
        self.task_names = get_task_names(self.env)  # type: ignore[arg-type]

    # --------------------------------------------------------------------------------------------- training
    def _sac_update(self, replay_data: MultiTaskReplayBufferSamples) -> dict[str, th.Tensor]:
        """One SAC update on a task-major batch: beta_i, then critics (Eq. 15-16), then actor (Eq. 9)."""
        actions_pi, log_prob = self.policy.action_log_prob(replay_data.observations)
        ent_coef, stats = self._entropy_step(log_prob)
        critic_losses, clipped = self._critic_losses(replay_data, ent_coef)
        kept = self.update_hook.loss_mask(critic_losses.detach())
        self._critic_step(critic_losses, kept)
        stats["critic_loss"] = critic_losses.detach()
        if clipped is not None:
            stats["q_loss_clip_fraction"] = clipped
        self.critic.requires_grad_(False)  # constants of the actor loss: no gradient for them in its backward pass
        min_q_pi = self.critic(replay_data.observations, actions_pi).min(dim=0).values
        self.critic.requires_grad_(True)
        actor_losses = -sac_task_objective(log_prob, min_q_pi, ent_coef)
        stats["actor_loss"] = self._actor_step(actor_losses, self._actor_weights() * kept).detach()
        self.update_hook.after_update()
        return stats

    def _actor_weights(self) -> th.Tensor:
        """w of Eq. 9: the update hook's, else uniform 1/N."""
        weights = self.update_hook.task_weights()
        if weights is None:
            return th.full((self.n_tasks,), 1.0 / self.n_tasks, device=self.device)
        return weights

    def _critic_losses(
        self, replay_data: MultiTaskReplayBufferSamples, ent_coef: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor | None]:
        """``(N,)`` clipped soft Bellman loss of every task (Eq. 15-16), twin critics summed, and the ``(N,)`` share
        of samples the clip dropped (None without ``q_loss_clip``)."""
        with th.no_grad():
            next_actions, next_log_prob = self.policy.action_log_prob(replay_data.next_observations)
            next_q = self.critic_target(replay_data.next_observations, next_actions).min(dim=0).values
            next_q = next_q - ent_coef[:, None] * next_log_prob
            target_q = replay_data.rewards + (1 - replay_data.dones) * self.gamma * next_q
        current_q = self.critic(replay_data.observations, replay_data.actions)
        losses = clipped_soft_q_loss(current_q, target_q, self.q_loss_clip)
        if self.q_loss_clip is None:
            return losses, None
        return losses, clipped_sample_fraction(current_q.detach(), target_q, self.q_loss_clip)

    def _critic_step(self, task_losses: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
        """Apply one critic update from the per-task losses.

        :param task_losses: ``(N,)`` per-task critic losses (with their graph).
        :param task_weights: ``(N,)`` weights of the tasks (the update hook's loss mask).
        :return: the loss that was minimised.
        """
        shared = self.critic_arch == "shared"
        return self._task_step(self.critic.optimizer, "critic loss", task_losses, task_weights, shared, self.critic)

    def _actor_step(self, task_losses: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
        """Apply one actor update from the per-task losses -J_SAC,i.

        :param task_losses: ``(N,)`` per-task policy losses (with their graph).
        :param task_weights: ``(N,)`` w of Eq. 9 (:meth:`_actor_weights`) times the loss mask.
        :return: the loss that was minimised.
        """
        return self._task_step(self.actor.optimizer, "actor loss", task_losses, task_weights, True, self.actor)

    # ------------------------------------------------------------------------------------------ save / load
    def _excluded_save_params(self) -> list[str]:
        excluded = ["actor", "critic", "critic_target", "_task_success", "_last_dump_timesteps", "update_hook"]
        excluded += ["update_monitor", "_update_runner"]
        return [*super()._excluded_save_params(), *excluded]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        if self.ent_coef_optimizer is not None:
            return [*state_dicts, "ent_coef_optimizer"], ["log_ent_coef"]
        return state_dicts, ["ent_coef_tensor"]

    def save(self, path, exclude=None, include=None) -> None:
        """Save the model; the RNG states are saved with it so that a resumed run continues exactly."""
        self.update_monitor.check()
        self.rng_state = capture_rng_state(self.action_space)
        try:
            super().save(path, exclude=exclude, include=include)
        finally:
            del self.rng_state

    @classmethod
    def load(cls, path, env: GymEnv | None = None, device: th.device | str = "auto", **kwargs):  # type: ignore[override]
        """Load a model saved by this class; a checkpoint of another algorithm or task count raises ValueError.

        ``env=None`` is enough for prediction and evaluation: no replay buffer is allocated. The RNG states saved
        with the model are restored, so training resumed from a model and its replay buffer continues as if it
        had never stopped (CPU).
        """
        n_tasks = env.num_envs if isinstance(env, VecEnv) else None
        check_checkpoint(path, cls.__name__, n_tasks)
        model = super().load(path, env=env, device=device, **kwargs)
        rng_state = model.__dict__.pop("rng_state", None)
        if rng_state is not None:
            restore_rng_state(rng_state, model.action_space)
        return model

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
