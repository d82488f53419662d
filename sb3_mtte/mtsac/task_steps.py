"""MTSAC's optimizer steps from ``(N,)`` per-task losses: on ``sum_i w_i L_i``, or, for parameters the tasks share
and an update hook that combines gradients (PCGrad, CAGrad, ...), along the hook's direction from the per-task
gradients (:mod:`sb3_mtte.common.update_hooks`)."""

from __future__ import annotations

import torch as th
from torch import nn

from sb3_mtte.common.gradient_surgery import (
    KeepsRows,
    assign_flat_gradient,
    per_task_gradients,
    per_task_gradients_of_rows,
)
from sb3_mtte.common.policies import MultiTaskActor
from sb3_mtte.common.update_hooks import UpdateHook
from sb3_mtte.common.update_monitor import UpdateMonitor


class TaskStepMixin:
    """Steps an optimizer on per-task losses (:meth:`_task_step`), asking :attr:`update_hook` to combine the
    per-task gradients of shared parameters when it does.

    The per-task gradients of a module whose network all tasks share and that maps rows independently
    (:attr:`~sb3_mtte.common.gradient_surgery.KeepsRows.shared_rows_network`: SAC-MT's actor, a shared critic) cost
    one more forward and backward pass of that network
    (:func:`~sb3_mtte.common.gradient_surgery.per_task_gradients_of_rows`); any other parameters take N backward
    passes (:func:`~sb3_mtte.common.gradient_surgery.per_task_gradients`).
    """

    update_hook: UpdateHook
    update_monitor: UpdateMonitor
    actor: MultiTaskActor
    critic: nn.Module

    def _enable_kept_rows(self) -> None:
        """Let the actor and the critic keep their forward passes for the per-task gradients, when that pays."""
        for module in (self.actor, self.critic):
            if isinstance(module, KeepsRows) and module.shared_rows_network is not None:
                module.keep_rows = self.update_hook.combines_gradients

    @staticmethod
    def _take_kept_rows(module: nn.Module | None) -> tuple[th.Tensor, th.Tensor, int] | None:
        return module.take_kept_rows() if isinstance(module, KeepsRows) else None

    @staticmethod
    def _per_task_gradients(
        module: nn.Module | None, kept: tuple | None, task_losses: th.Tensor, params: list[th.Tensor]
    ) -> th.Tensor:
        """``(N, P)`` per-task gradients of ``params``: from ``module``'s kept pass when there is one (one more pass
        of its shared network), else by the generic batched backward pass (N of them)."""
        if kept is None:
            return per_task_gradients(task_losses, params)
        network = module.shared_rows_network
        if [id(p) for p in network.parameters()] != [id(p) for p in params]:
            raise RuntimeError("An optimizer's parameters must be those of its module's shared network, in order.")
        inputs, outputs, task_dim = kept
        return per_task_gradients_of_rows(network, inputs, outputs, task_losses, task_dim)

    def _task_step(
        self,
        optimizer: th.optim.Optimizer,
        name: str,
        task_losses: th.Tensor,
        task_weights: th.Tensor,
        shared: bool,
        module: nn.Module | None = None,
    ) -> th.Tensor:
        """One step of ``optimizer`` on the per-task losses: along the hook's combination of the per-task gradients
        when it combines them and the tasks share the parameters, else on ``sum_i w_i L_i`` (disjoint per-task
        parameters have nothing to combine). ``module``: the module whose parameters ``optimizer`` steps, when it may
        have kept its forward pass (:meth:`_enable_kept_rows`). Returns ``sum_i w_i L_i``."""
        if self.update_hook.combines_gradients and shared:
            return self._combined_step(optimizer, name, task_losses, task_weights, module)
        return self._weighted_step(optimizer, name, task_losses, task_weights)

    def _weighted_step(
        self, optimizer: th.optim.Optimizer, name: str, task_losses: th.Tensor, task_weights: th.Tensor
    ) -> th.Tensor:
        """Minimise ``sum_i w_i L_i`` by one step of ``optimizer``; a non-finite loss stops training (before the
        step, or at the next read of :attr:`update_monitor` on the CUDA-graph path)."""
        loss = (task_weights * task_losses).sum()
        self.update_monitor.check_finite(name, loss)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return loss

    def _combined_step(
        self,
        optimizer: th.optim.Optimizer,
        name: str,
        task_losses: th.Tensor,
        task_weights: th.Tensor,
        module: nn.Module | None = None,
    ) -> th.Tensor:
        """One step of ``optimizer`` along the hook's direction; returns ``sum_i w_i L_i`` (for the logs).

        :param optimizer: the optimizer of the parameters the tasks share.
        :param name: name of the loss (for the error of a non-finite loss).
        :param task_losses: ``(N,)`` per-task losses with their graph.
        :param task_weights: ``(N,)`` weights of the tasks.
        :param module: the module of the parameters, if it may have kept its forward pass (then the per-task
            gradients take one more pass of its network instead of N backward passes).
        """
        kept = self._take_kept_rows(module)  # taken first: a non-finite loss leaves no graph behind
        loss = (task_weights * task_losses).sum()
        self.update_monitor.check_finite(name, loss)
        params = [p for group in optimizer.param_groups for p in group["params"] if p.requires_grad]
        grads = self._per_task_gradients(module, kept, task_losses, params)
        direction = self.update_hook.combine_gradients(grads, task_weights)
        optimizer.zero_grad()
        assign_flat_gradient(params, direction)
        optimizer.step()
        return loss.detach()
