"""The optimizer steps of gradient surgery (PCGrad, CAGrad) for MTSAC; the maths is in
:mod:`sb3_mtte.common.gradient_surgery`."""

from __future__ import annotations

import torch as th

from sb3_mtte.common.gradient_surgery import (
    assign_flat_gradient,
    per_task_gradients,
    per_task_gradients_of_rows,
    surgery_direction,
)
from sb3_mtte.common.policies import MultiTaskActor
from sb3_mtte.common.utils import check_finite


class GradientSurgeryMixin:
    """Steps an optimizer along the PCGrad / CAGrad combination of the per-task gradients of its parameters, for
    the parameters the tasks share (:meth:`_task_step`).

    The per-task gradients of an actor whose network all tasks share and that maps rows independently
    (:attr:`~sb3_mtte.common.policies.MultiTaskActor.shared_rows_network`, e.g. SAC-MT's) cost about one backward
    pass (:func:`~sb3_mtte.common.gradient_surgery.per_task_gradients_of_rows`); any other parameters take N
    (:func:`~sb3_mtte.common.gradient_surgery.per_task_gradients`).
    """

    gradient_surgery: str | None
    cagrad_c: float
    actor: MultiTaskActor

    def _setup_gradient_surgery(self) -> None:
        """Let the actor keep its forward pass for the per-task gradients, when that pays."""
        self.actor.keep_output = self.gradient_surgery is not None and self.actor.shared_rows_network is not None

    def _actor_per_task_gradients(self, task_losses: th.Tensor, params: list[th.Tensor]) -> th.Tensor:
        kept, self.actor.kept_output = self.actor.kept_output, None
        network = self.actor.shared_rows_network
        if kept is None or network is None:
            return per_task_gradients(task_losses, params)
        if [id(p) for p in network.parameters()] != [id(p) for p in params]:
            raise RuntimeError("The actor optimizer's parameters must be those of its shared network, in order.")
        return per_task_gradients_of_rows(network, *kept, task_losses)

    def _task_step(
        self,
        optimizer: th.optim.Optimizer,
        name: str,
        task_losses: th.Tensor,
        task_weights: th.Tensor,
        shared: bool,
        actor: bool = False,
    ) -> th.Tensor:
        """One step of ``optimizer`` on the per-task losses: along the surgered direction when a method is set and
        the tasks share the parameters, else on ``sum_i w_i L_i`` (disjoint per-task parameters have nothing to
        combine). Returns ``sum_i w_i L_i``."""
        if self.gradient_surgery is not None and shared:
            return self._surgery_step(optimizer, name, task_losses, task_weights, actor)
        return self._weighted_step(optimizer, name, task_losses, task_weights)

    @staticmethod
    def _weighted_step(
        optimizer: th.optim.Optimizer, name: str, task_losses: th.Tensor, task_weights: th.Tensor
    ) -> th.Tensor:
        """Minimise ``sum_i w_i L_i`` by one step of ``optimizer``; a non-finite loss stops training."""
        loss = (task_weights * task_losses).sum()
        check_finite(name, loss)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return loss

    def _surgery_step(
        self,
        optimizer: th.optim.Optimizer,
        name: str,
        task_losses: th.Tensor,
        task_weights: th.Tensor,
        actor: bool = False,
    ) -> th.Tensor:
        """One step of ``optimizer`` along the surgered direction; returns ``sum_i w_i L_i`` (for the logs).

        :param optimizer: the optimizer of the parameters the tasks share.
        :param name: name of the loss (for the error of a non-finite loss).
        :param task_losses: ``(N,)`` per-task losses with their graph.
        :param task_weights: ``(N,)`` weights of the tasks.
        :param actor: whether these are the actor's losses (which may take the one-backward-pass gradients).
        """
        loss = (task_weights * task_losses).sum()
        check_finite(name, loss)
        params = [p for group in optimizer.param_groups for p in group["params"] if p.requires_grad]
        if actor:
            grads = self._actor_per_task_gradients(task_losses, params)
        else:
            grads = per_task_gradients(task_losses, params)
        direction = surgery_direction(self.gradient_surgery, grads, task_weights, self.cagrad_c)  # type: ignore[arg-type]
        optimizer.zero_grad()
        assign_flat_gradient(params, direction)
        optimizer.step()
        return loss.detach()
