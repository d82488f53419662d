"""Every extension of an MTSAC update: what happens to the ``(N,)`` per-task losses and gradients.

An update (:meth:`sb3_mtte.MTSAC._update`) asks its algorithm's :class:`UpdateHook`, in this order:

1. :meth:`~UpdateHook.loss_mask` on the ``(N,)`` critic losses: a factor per task for this update's losses;
2. :meth:`~UpdateHook.task_weights`: the ``(N,)`` weights w of the actor loss ``sum_i w_i L_i`` (Eq. 9);
3. :meth:`~UpdateHook.combine_gradients`, for every optimizer whose parameters the tasks share, when the hook
   :attr:`~UpdateHook.combines_gradients`: one update direction from the ``(N, P)`` per-task gradients;
4. :meth:`~UpdateHook.after_update`, once the optimizers have stepped.

A hook does one of these things; :class:`UpdateHooks` runs several as one (masks multiply, the last hook that
gives weights gives them, at most one combines gradients). The algorithm's hooks come from
:meth:`sb3_mtte.MTSAC.update_hooks` (gradient surgery from ``gradient_surgery``, MTSACTE's weights) followed by its
policy's :meth:`~sb3_mtte.common.policies.MultiTaskPolicy.update_hooks` (PaCo's mask and reset).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch as th

from sb3_mtte.common.gradient_surgery import surgery_direction


class UpdateHook:
    """The plain update: every task's losses count, uniform weights 1/N, the gradient of ``sum_i w_i L_i``."""

    combines_gradients: bool = False
    """Whether :meth:`combine_gradients` replaces the gradient of ``sum_i w_i L_i`` for the shared parameters."""
    capturable: bool = True
    """Whether the hook's part of an update runs on the device alone (no read on the host): a CUDA graph can hold it."""

    def attach(self, model: Any) -> None:
        """Called once the algorithm's networks exist (and again after ``load``)."""

    def loss_mask(self, task_losses: th.Tensor) -> th.Tensor:
        """``(N,)`` factor of every task's losses in this update, from its ``(N,)`` critic losses (detached)."""
        return th.ones_like(task_losses)

    def task_weights(self) -> th.Tensor | None:
        """``(N,)`` weights of the actor loss (w of Eq. 9), or None for uniform 1/N."""
        return None

    def combine_gradients(self, task_gradients: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
        """The ``(P,)`` update direction of shared parameters from their ``(N, P)`` per-task gradients."""
        return task_weights @ task_gradients

    def after_update(self) -> None:
        """Called after the update's optimizer steps."""


class UpdateHooks(UpdateHook):
    """Several hooks as one, in order. :raises ValueError: when more than one combines gradients."""

    def __init__(self, hooks: Sequence[UpdateHook]) -> None:
        self.hooks = list(hooks)
        combining = [hook for hook in self.hooks if hook.combines_gradients]
        if len(combining) > 1:
            names = ", ".join(type(hook).__name__ for hook in combining)
            raise ValueError(f"At most one update hook may combine the task gradients, got {names}.")
        self.combining = combining[0] if combining else None
        self.combines_gradients = self.combining is not None

    @property
    def capturable(self) -> bool:  # type: ignore[override]
        return all(hook.capturable for hook in self.hooks)

    def attach(self, model: Any) -> None:
        for hook in self.hooks:
            hook.attach(model)

    def loss_mask(self, task_losses: th.Tensor) -> th.Tensor:
        mask = th.ones_like(task_losses)
        for hook in self.hooks:
            mask = mask * hook.loss_mask(task_losses)
        return mask

    def task_weights(self) -> th.Tensor | None:
        weights = [hook.task_weights() for hook in self.hooks]
        return next((w for w in reversed(weights) if w is not None), None)

    def combine_gradients(self, task_gradients: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
        if self.combining is None:
            return super().combine_gradients(task_gradients, task_weights)
        return self.combining.combine_gradients(task_gradients, task_weights)

    def after_update(self) -> None:
        for hook in self.hooks:
            hook.after_update()


class GradientSurgery(UpdateHook):
    """PCGrad (Yu et al. 2020) or CAGrad (Liu et al. 2021) on every loss whose parameters the tasks share.

    :param method: ``"pcgrad"`` or ``"cagrad"``.
    :param cagrad_c: CAGrad's c in (0, 1).
    """

    combines_gradients = True
    capturable = False  # the combination is solved on the host from the Gram matrix

    def __init__(self, method: str, cagrad_c: float = 0.5) -> None:
        self.method, self.cagrad_c = method, cagrad_c

    def combine_gradients(self, task_gradients: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
        return surgery_direction(self.method, task_gradients, task_weights, self.cagrad_c)


class NegativeTransferWeights(UpdateHook):
    """MTSACTE's actor weights: w of Eq. 8 from the model's last recomputation (``model.task_weights``)."""

    def attach(self, model: Any) -> None:
        self.model = model

    def task_weights(self) -> th.Tensor:
        return self.model.task_weights


class CollapseReset(UpdateHook):
    """PaCo's reset of collapsed tasks (Sun et al. 2022): a task whose critic loss exceeds the policy's
    ``task_loss_threshold`` takes no part in the update, and its task weights are reset after it.

    :param policy: the policy, with ``task_loss_threshold`` and ``reset_task_weights(collapsed)``.
    """

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        self.collapsed: th.Tensor | None = None
        """``(N,)`` bool, the tasks masked in the running update (None when none)."""

    @property
    def capturable(self) -> bool:  # type: ignore[override]
        return self.policy.task_loss_threshold is None  # else the reset's shapes follow the collapsed tasks

    def loss_mask(self, task_losses: th.Tensor) -> th.Tensor:
        threshold = self.policy.task_loss_threshold
        if threshold is None:
            return th.ones_like(task_losses)
        collapsed = task_losses > threshold
        self.collapsed = collapsed if bool(collapsed.any()) else None
        return (~collapsed).to(task_losses.dtype)

    def after_update(self) -> None:
        if self.collapsed is not None:
            self.policy.reset_task_weights(self.collapsed)
            self.collapsed = None


__all__ = ["CollapseReset", "GradientSurgery", "NegativeTransferWeights", "UpdateHook", "UpdateHooks"]
