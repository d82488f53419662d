"""MTSAC's learned entropy coefficients beta_i (SAC's temperature, Eq. 3 of every task)."""

from __future__ import annotations

import math

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_mtte.common.losses import per_task_entropy_loss


def resolve_target_entropy(target_entropy: str | float, action_space: spaces.Box) -> float:
    """H-bar: ``"auto"`` is -dim(A), as SB3's SAC."""
    if target_entropy == "auto":
        return -float(np.prod(action_space.shape))
    return float(target_entropy)


def learned_initial_value(ent_coef: str | float) -> float | None:
    """The initial beta of a learned coefficient (``"auto"``: 1, ``"auto_0.1"``: 0.1), or None for a fixed one.

    :raises ValueError: for an initial value that is not positive.
    """
    if not (isinstance(ent_coef, str) and ent_coef.startswith("auto")):
        return None
    init_value = float(ent_coef.split("_")[1]) if "_" in ent_coef else 1.0
    if init_value <= 0:
        raise ValueError("The initial value of ent_coef must be greater than 0.")
    return init_value


class MultiTaskTemperature:
    """Learned beta_i: ``log_ent_coef`` holds one entry per task, or one for every task when ``shared``.

    The losses always see the ``(N,)`` coefficients of :attr:`ent_coef`. The ``(N,)`` temperature losses are
    minimised with :attr:`task_weights` 1 (each beta_i its own task's loss) or, for a shared beta, 1/N (the mean over
    every sample, as SB3's SAC).

    :param n_tasks: N.
    :param init_value: beta at the start.
    :param target_entropy: H-bar.
    :param shared: one beta for every task.
    :param learning_rate: Adam's learning rate.
    :param device: where the coefficients live.
    """

    def __init__(
        self,
        n_tasks: int,
        init_value: float,
        target_entropy: float,
        shared: bool,
        learning_rate: float,
        device: th.device,
    ) -> None:
        self.n_tasks, self.target_entropy, self.shared = n_tasks, target_entropy, shared
        n_coefs = 1 if shared else n_tasks
        self.log_ent_coef = th.full((n_coefs,), math.log(init_value), device=device, requires_grad=True)
        self.optimizer = th.optim.Adam([self.log_ent_coef], lr=learning_rate)
        self.task_weights = th.full((n_tasks,), 1.0 / n_tasks if shared else 1.0, device=device)

    @property
    def ent_coef(self) -> th.Tensor:
        """``(N,)`` beta_i, without gradient (one value N times when shared)."""
        return self.log_ent_coef.detach().exp().expand(self.n_tasks)

    def loss(self, log_prob: th.Tensor) -> th.Tensor:
        """``(N,)`` temperature loss of every task (Eq. 3).

        :param log_prob: ``(N, L)`` log-probabilities of the reparameterised actions.
        """
        return per_task_entropy_loss(self.log_ent_coef.expand(self.n_tasks), log_prob.detach(), self.target_entropy)
