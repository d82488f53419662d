"""MTSACTE: multi-task SAC with a task embedding network (the paper's method, Algorithm 1)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback, ConvertCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule

from sb3_mtte.common.update_hooks import NegativeTransferWeights, UpdateHook
from sb3_mtte.common.utils import check_finite, task_log_key
from sb3_mtte.mtsac.mtsac import MTSAC
from sb3_mtte.mtsacte.callbacks import NegativeTransferLogCallback
from sb3_mtte.mtsac.checks import ArgumentSpec, check_arguments
from sb3_mtte.mtsacte.checks import MTSACTE_ARGUMENTS, check_n_select
from sb3_mtte.mtsacte.objectives import TaskSelection, select_tasks
from sb3_mtte.mtsacte.policies import MTSACTEPolicy
from sb3_mtte.mtsacte.probe import task_probe_accuracy
from sb3_mtte.mtsacte.transfer import (
    RepresentationBatch,
    TaskObjectives,
    TransferStatistics,
    representation_gradients,
    transfer_matrix,
)

# Attributes holding the last recomputation's TaskSelection: tensors on the model's device, numpy in a checkpoint.
SELECTION_ATTRIBUTES = ("transfer_matrix", "mu", "selected_tasks", "task_weights")

SelfMTSACTE = TypeVar("SelfMTSACTE", bound="MTSACTE")


class MTSACTE(MTSAC):
    """Multi-task SAC with a task embedding network, negative-transfer task weights, clipped per-task soft-Q
    losses and top-K trajectory replay ("Multi-task RL with a task representation method").

    Every ``iteration_length`` vector steps, ``rep_gradient_steps`` updates of the encoder E_phi and decoder D by
    J^rep (Eq. 14) on top-K batches, each recomputing mu (Eq. 6), C_s (Eq. 7) and w (Eq. 8); the last C_s and w
    hold for the iteration. Every vector step: clipped per-task critic losses (Eq. 15-16), the weighted policy loss
    (Eq. 9) with z detached from phi, per-task beta_i, Polyak targets.

    ``mu``, ``selected_tasks`` (C_s), ``task_weights`` (w) and ``transfer_matrix`` hold the last recomputation as
    tensors on the model's device (numpy in a checkpoint). ``learn`` adds a :class:`NegativeTransferLogCallback`,
    which writes one line per iteration to ``negative_transfer.jsonl`` in the logger's folder.

    Ablations of Fig. 7: ``use_vae=False`` (Ours-VAE), ``q_loss_clip=None`` (Ours-clip), ``use_topk=False``
    (Ours-bestbatch).

    :param policy: ``"MlpPolicy"`` or :class:`MTSACTEPolicy`.
    :param env: multi-task VecEnv, sub-env i is task i.
    :param n_select: M, the size of the benign set C_s (default N // 2: 5 on MT10, 10 on MT20); 1 <= M < N.
    :param top_k: K, best episodes kept per task for the representation batches (30).
    :param q_loss_clip: V_clip of Eq. 16 (2000); None disables clipping.
    :param nt_step_size: alpha of Eq. 4, the virtual gradient-ascent step. Default 1e-3: small enough for the
        first-order picture (J_i(theta^k) - J_i(theta) ~ alpha g_i . g_k) to hold. The transfer matrix is computed
        in float64, so its signs stay exact at Q up to 1e4 (docs/paper_silent.md).
    :param c_vae: c_vae of Eq. 14, weight of the VAE term (1e-4). Adam moves E_phi's log-std along the KL's
        consistently signed gradient whatever its size, while J^NT's pull on it is second order in the std: at 1e-2
        the std returned to the prior within about 20 J^rep steps on the development benchmark and z lost the task
        (docs/embedding_study.md).
    :param rep_learning_rate: learning rate delta of phi and the decoder (3e-4).
    :param iteration_length: H, vector steps per iteration (500, Meta-World's horizon).
    :param rep_gradient_steps: J^rep updates at the start of every iteration (10).
    :param nt_estimator: ``"virtual_step"``: mu and J^NT exactly by Eq. 4-6 and 11 (O(N^2) evaluations), or
        ``"gradient_dot"``: both to first order in alpha (mu from the task-gradient Gram matrix, J^NT from the
        mean task gradients; linear in N).
    :param use_vae: include the VAE term of Eq. 14.
    :param use_topk: draw representation batches from the top-K episodes (else from the main buffer).
    :param nt_chunk_size: how many virtual parameter sets theta^k one batched pass over all tasks evaluates: None
        all at once, 1 one at a time; ``"auto"``: 1 on CPU (the least memory, as fast there), None on GPUs.
    :param nt_measure: how mu is read from the transfer matrices, beyond the paper when not the default.
        ``"per_batch"`` (the paper, Eq. 6): each recomputation counts the signs of its own batch's matrix.
        ``"mean"``: the j-th recomputation of an iteration counts the signs of the mean of the iteration's first j
        matrices. ``"significant"``: as ``"mean"``, counting only entries below zero by more than two standard
        errors over those batches. C_s and w at the end of an iteration then rest on all ``rep_gradient_steps``
        batches.
    :param critic_arch: ``"per_task"`` only: mu (Eq. 6) reads each task's own critics (a shared critic is MTSAC's).
    :param kwargs: every other argument of :class:`sb3_mtte.MTSAC` (learning_rate, batch_size = L per task, ...).
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MTSACTEPolicy}
    min_tasks: ClassVar[int] = 2  # Eq. 7 needs 1 <= M < N
    argument_specs: ClassVar[Mapping[str, ArgumentSpec]] = MTSACTE_ARGUMENTS
    policy: MTSACTEPolicy

    def __init__(
        self,
        policy: str | type[MTSACTEPolicy],
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
        n_select: int | None = None,
        top_k: int = 30,
        q_loss_clip: float | None = 2000.0,
        nt_step_size: float = 1e-3,
        c_vae: float = 1e-4,
        rep_learning_rate: float = 3e-4,
        iteration_length: int = 500,
        rep_gradient_steps: int = 10,
        nt_estimator: str = "virtual_step",
        use_vae: bool = True,
        use_topk: bool = True,
        nt_chunk_size: int | str | None = "auto",
        nt_measure: str = "per_batch",
        critic_arch: str = "per_task",
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
        replay_buffer_kwargs = {**(replay_buffer_kwargs or {}), "top_k": top_k if use_topk else 0}
        super().__init__(
            policy,
            env,
            learning_rate=learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            ent_coef=ent_coef,
            target_entropy=target_entropy,
            target_update_interval=target_update_interval,
            critic_arch="per_task",
            q_loss_clip=q_loss_clip,
            update_path=update_path,
            overlap_env_step=overlap_env_step,
            action_noise=action_noise,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
        )
        if self.env is not None:
            n_select = self.n_tasks // 2 if n_select is None else n_select
            check_n_select(n_select, self.n_tasks)
        self.n_select = n_select
        self.top_k, self.use_topk, self.use_vae = top_k, use_topk, use_vae
        self.nt_step_size, self.c_vae, self.rep_learning_rate = nt_step_size, c_vae, rep_learning_rate
        self.iteration_length, self.rep_gradient_steps = iteration_length, rep_gradient_steps
        self.nt_estimator, self.nt_chunk_size = nt_estimator, nt_chunk_size
        self.nt_measure = nt_measure
        self._last_iteration: int | None = None
        self.negative_transfer_records: list[dict[str, Any]] = []
        """Records of ``negative_transfer.jsonl`` (one per iteration) until :class:`NegativeTransferLogCallback`
        writes them."""
        if _init_setup_model:
            self._setup_model()
            self._check_first_observations()

    def _setup_model(self) -> None:
        super()._setup_model()
        if getattr(self, "mu", None) is None:
            n, dtype = self.n_tasks, self._actor_dtype()
            mu = th.zeros(n, dtype=th.long, device=self.device)
            transfer = th.zeros(n, n, dtype=th.float64, device=self.device)
            weights = th.full((n,), 1.0 / n, dtype=dtype, device=self.device)
            self._set_selection(TaskSelection(transfer, mu, th.zeros_like(mu, dtype=th.bool), weights))
            self.task_probe_accuracy = self.task_probe_accuracy_of_mean = self.z_std = float("nan")
        else:  # numpy arrays restored from a checkpoint
            for name in SELECTION_ATTRIBUTES:
                setattr(self, name, th.as_tensor(getattr(self, name), device=self.device))

    def _actor_dtype(self) -> th.dtype:
        return next(self.policy.actor.parameters()).dtype

    def _policy_build_kwargs(self) -> dict[str, Any]:
        return {**super()._policy_build_kwargs(), "rep_learning_rate": self.rep_learning_rate}

    def _create_aliases(self) -> None:
        super()._create_aliases()
        self.encoder = self.policy.encoder
        self.decoder = self.policy.decoder

    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        """The user's callbacks, after a :class:`NegativeTransferLogCallback` that writes the records."""
        callbacks: list[BaseCallback] = [NegativeTransferLogCallback()]
        if isinstance(callback, list):
            callbacks += callback
        elif callback is not None:
            callbacks.append(callback if isinstance(callback, BaseCallback) else ConvertCallback(callback))
        return super()._init_callback(callbacks, progress_bar)

    # --------------------------------------------------------------------------------------------- training
    def update_hooks(self) -> list[UpdateHook]:
        """The actor's weights w of Eq. 8 from the last recomputation (uniform before the first)."""
        return [*super().update_hooks(), NegativeTransferWeights()]

    # Algorithm 1: iteration k opens with J^rep, then takes vector steps k H + 1, ..., (k + 1) H, each followed by its
    # update. Once learning has begun, the iteration of the next step opens before that step is taken (so never after
    # the run's last step); one not open yet at an update (the run's first, a sparser train_freq) opens before it.
    def collect_rollouts(self, *args, **kwargs):
        next_iteration = self._iteration_of_step(self.num_timesteps // self.n_tasks + 1)
        if self._last_iteration is not None and next_iteration != self._last_iteration:
            self._open_iteration(next_iteration, self.batch_size)
        return super().collect_rollouts(*args, **kwargs)

    def train(self, gradient_steps: int, batch_size: int = 128) -> None:
        iteration = self._iteration_of_step(self.num_timesteps // self.n_tasks)
        if iteration != self._last_iteration:
            self._open_iteration(iteration, batch_size)
        super().train(gradient_steps, batch_size)

    def _iteration_of_step(self, step: int) -> int:
        """The iteration of Algorithm 1 that vector step ``step`` (counted from 1) belongs to."""
        return (step - 1) // self.iteration_length

    def _open_iteration(self, iteration: int, batch_size: int) -> None:
        self._last_iteration = iteration
        self.update_representation(batch_size)

    def _representation_batch(self, batch_size: int) -> RepresentationBatch:
        buffer = self.replay_buffer
        data = buffer.sample_top_k(batch_size) if self.use_topk else buffer.sample(batch_size)  # type: ignore[union-attr]
        return RepresentationBatch.draw(data.observations, self.policy.z_dim, self.policy.action_dim)

    def update_representation(self, batch_size: int | None = None) -> None:
        """``rep_gradient_steps`` updates of phi and the decoder by J^rep (Alg. 1), each recomputing mu, C_s, w, on
        batches of ``batch_size`` per task (the model's ``batch_size`` when None)."""
        batch_size = self.batch_size if batch_size is None else batch_size
        self.policy.set_training_mode(True)
        losses, statistics = [], TransferStatistics()
        for _ in range(self.rep_gradient_steps):
            batch = self._representation_batch(batch_size)
            objectives = TaskObjectives(self.policy, batch, self.entropy_coefficients, self._chunk_size())
            encoder_params, _ = objectives.phi()
            with th.no_grad():
                z, z_mean, z_log_std = objectives.embedding(encoder_params)
                transfer = transfer_matrix(objectives, z, self.nt_step_size, self.nt_estimator)
            statistics.add(transfer)
            self._set_selection(self._select(transfer, statistics))
            harmful_tasks = th.nonzero(~self.selected_tasks).flatten()
            if harmful_tasks.numel() == 0 and not self._has_vae_term():
                continue  # J^rep has no term: no step, so Adam's momentum does not move phi on zero gradients
            loss, enc_grads, dec_grads = representation_gradients(
                objectives,
                harmful_tasks,
                step_size=self.nt_step_size,
                c_vae=self.c_vae,
                use_vae=self.use_vae,
                estimator=self.nt_estimator,
            )
            check_finite("representation loss (J^rep)", loss)
            self._apply_gradients(enc_grads, dec_grads)
            losses.append(loss.detach())
        self.task_probe_accuracy = task_probe_accuracy(z)
        self.task_probe_accuracy_of_mean = task_probe_accuracy(z_mean)
        self.z_std = float(z_log_std.exp().mean())
        if getattr(self, "_logger", None) is None:
            return  # no learn yet (a model just built or loaded): no logger to record to
        if losses:
            self.logger.record("train/rep_loss", float(th.stack(losses).mean()))
        self._log_negative_transfer()

    def _has_vae_term(self) -> bool:
        return self.use_vae and self.c_vae > 0

    def _select(self, transfer: th.Tensor, statistics: TransferStatistics) -> TaskSelection:
        """mu, C_s and w (Eq. 6-8) from this batch's matrix or from the iteration's mean (``nt_measure``)."""
        dtype = self._actor_dtype()
        if self.nt_measure == "per_batch":
            return select_tasks(transfer, self.n_select, dtype)  # type: ignore[arg-type]
        error = statistics.standard_error if self.nt_measure == "significant" else None
        return select_tasks(statistics.mean, self.n_select, dtype, error)  # type: ignore[arg-type]

    def _chunk_size(self) -> int | None:
        if self.nt_chunk_size == "auto":
            return 1 if self.device.type == "cpu" else None
        return self.nt_chunk_size  # type: ignore[return-value]

    def _apply_gradients(self, enc_grads: dict[str, th.Tensor], dec_grads: dict[str, th.Tensor]) -> None:
        optimizer = self.policy.rep_optimizer
        optimizer.zero_grad()
        for module, grads in ((self.encoder, enc_grads), (self.decoder, dec_grads)):
            for name, param in module.named_parameters():
                param.grad = grads[name]
        optimizer.step()

    def _set_selection(self, selection: TaskSelection) -> None:
        weights = getattr(self, "task_weights", None)
        self.transfer_matrix, self.mu, self.selected_tasks, self.task_weights = selection
        if isinstance(weights, th.Tensor) and weights.shape == self.task_weights.shape:
            self.task_weights = weights.copy_(self.task_weights)  # in place: a captured update reads w there

    def _log_negative_transfer(self) -> None:
        """Record the ``nt/*`` and ``rep/*`` keys and queue the record of ``negative_transfer.jsonl``."""
        mu, weights, selected = (getattr(self, name).cpu().numpy() for name in ("mu", "task_weights", "selected_tasks"))
        self.logger.record("nt/n_selected", int(selected.sum()))
        self.logger.record("nt/mu_mean", float(mu.mean()))
        self.logger.record("rep/task_probe_accuracy", self.task_probe_accuracy)
        self.logger.record("rep/task_probe_accuracy_of_mean", self.task_probe_accuracy_of_mean)
        self.logger.record("rep/z_std", self.z_std)
        for i in range(self.n_tasks):
            name = self._task_name(i)
            self.logger.record(task_log_key("nt/mu", i, name), int(mu[i]))
            self.logger.record(task_log_key("nt/weight", i, name), float(weights[i]))
        if self.logger.get_dir():
            record = {
                "timesteps": self.num_timesteps,
                "mu": mu.tolist(),
                "selected": selected.astype(int).tolist(),
                "weights": weights.tolist(),
                "transfer_matrix": self.transfer_matrix.cpu().numpy().astype(np.float64).tolist(),
                "transfer_matrix_dtype": str(self.transfer_matrix.dtype).removeprefix("torch."),
                "task_probe_accuracy": self.task_probe_accuracy,
                "task_probe_accuracy_of_mean": self.task_probe_accuracy_of_mean,
                "z_std": self.z_std,
            }
            self.negative_transfer_records.append(record)

    # ------------------------------------------------------------------------------------------ save / load
    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "encoder", "decoder", "negative_transfer_records"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "policy.rep_optimizer"], variables

    def save(self, path, exclude=None, include=None) -> None:
        """Save the model; mu, C_s, w and the transfer matrix go into the checkpoint as numpy arrays."""
        tensors = {name: getattr(self, name) for name in SELECTION_ATTRIBUTES}
        self.__dict__.update({name: value.cpu().numpy() for name, value in tensors.items()})
        try:
            super().save(path, exclude=exclude, include=include)
        finally:
            self.__dict__.update(tensors)

    def learn(
        self: SelfMTSACTE,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "MTSACTE",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfMTSACTE:
        if reset_num_timesteps:
            self._last_iteration = None  # the first update opens an iteration
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)
