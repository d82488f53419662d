"""MTSAC's entropy coefficients: a learned beta_i per task (the paper's setting), one learned beta shared by every
task, or a fixed value (SAC's Eq. 3 per task)."""

from __future__ import annotations

import math

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_mtte.common.losses import per_task_entropy_loss

ENT_COEF_ARCHS = ("per_task", "shared")


def check_ent_coef_arch(ent_coef_arch: str) -> None:
    """:raises ValueError: for an ``ent_coef_arch`` other than ``"per_task"`` and ``"shared"``."""
    if ent_coef_arch not in ENT_COEF_ARCHS:
        raise ValueError(f"ent_coef_arch must be one of {ENT_COEF_ARCHS}, got {ent_coef_arch!r}.")


class EntropyCoefMixin:
    """The temperature of MTSAC: ``log_ent_coef`` has one entry per task (``ent_coef_arch="per_task"``) or one for
    every task (``"shared"``); the losses always see the ``(N,)`` coefficients of :attr:`entropy_coefficients`.

    Each update hands the ``(N,)`` per-task temperature losses to :meth:`_entropy_coef_step` with weights 1 (each
    beta_i minimises its own task's loss) or, for a shared beta, 1/N (the mean over every sample, as SB3's SAC).
    """

    n_tasks: int
    device: th.device
    action_space: spaces.Box
    ent_coef: str | float
    ent_coef_arch: str
    target_entropy: str | float
    log_ent_coef: th.Tensor | None
    ent_coef_optimizer: th.optim.Optimizer | None
    ent_coef_tensor: th.Tensor

    def _setup_entropy_coef(self) -> None:
        if self.target_entropy == "auto":
            self.target_entropy = -float(np.prod(self.action_space.shape))  # type: ignore[arg-type]
        self.target_entropy = float(self.target_entropy)
        if isinstance(self.ent_coef, str) and self.ent_coef.startswith("auto"):
            init_value = float(self.ent_coef.split("_")[1]) if "_" in self.ent_coef else 1.0
            if init_value <= 0:
                raise ValueError("The initial value of ent_coef must be greater than 0.")
            n_coefs = 1 if self.ent_coef_arch == "shared" else self.n_tasks
            self.log_ent_coef = th.full((n_coefs,), math.log(init_value), device=self.device, requires_grad=True)
            self.ent_coef_optimizer = th.optim.Adam([self.log_ent_coef], lr=self.lr_schedule(1))  # type: ignore[attr-defined]
        else:
            self.ent_coef_tensor = th.full((self.n_tasks,), float(self.ent_coef), device=self.device)

    @property
    def entropy_coefficients(self) -> th.Tensor:
        """Current per-task beta_i, shape (N,) (one value N times when shared)."""
        if self.log_ent_coef is None:
            return self.ent_coef_tensor
        return self.log_ent_coef.detach().exp().expand(self.n_tasks)

    def _entropy_step(self, log_prob: th.Tensor) -> tuple[th.Tensor, dict[str, th.Tensor]]:
        """Update the learned beta_i (Eq. 3) and return the coefficients the losses use, with their stats.

        :param log_prob: ``(N, L)`` log-probabilities of the reparameterised actions.
        """
        if self.ent_coef_optimizer is None or self.log_ent_coef is None:
            return self.ent_coef_tensor, {"ent_coef": self.ent_coef_tensor}
        ent_coef = self.entropy_coefficients
        task_losses = per_task_entropy_loss(
            self.log_ent_coef.expand(self.n_tasks), log_prob.detach(), self.target_entropy
        )
        ent_coef_loss = self._entropy_coef_step(task_losses, self._entropy_task_weights())
        return ent_coef, {"ent_coef_loss": ent_coef_loss.detach(), "ent_coef": ent_coef}

    def _entropy_task_weights(self) -> th.Tensor:
        weight = 1.0 / self.n_tasks if self.ent_coef_arch == "shared" else 1.0
        return th.full((self.n_tasks,), weight, device=self.device)

    def _entropy_coef_step(self, task_losses: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
        """Apply one update of the learned entropy coefficients from the per-task temperature losses (a shared beta
        follows the update hook's combination of the task gradients, e.g. PCGrad's or CAGrad's).

        :param task_losses: ``(N,)`` per-task temperature losses (with their graph).
        :param task_weights: ``(N,)`` weights of the tasks.
        :return: the loss that was minimised.
        """
        shared = self.ent_coef_arch == "shared"
        optimizer = self.ent_coef_optimizer
        return self._task_step(optimizer, "entropy coefficient loss", task_losses, task_weights, shared)  # type: ignore[attr-defined]
