"""Optimizer steps from ``(N,)`` per-task losses: on ``sum_i w_i L_i``, or, for parameters the tasks share and an
update hook that combines gradients (PCGrad, CAGrad, ...), along the hook's direction from the per-task gradients
(:mod:`sb3_mtte.common.update_hooks`).

The per-task gradients of a module whose network all tasks share and that maps rows independently
(:attr:`~sb3_mtte.common.gradient_surgery.KeepsRows.shared_rows_network`: SAC-MT's actor, a shared critic) cost one
more forward and backward pass of that network (:func:`~sb3_mtte.common.gradient_surgery.per_task_gradients_of_rows`);
any other parameters take N backward passes (:func:`~sb3_mtte.common.gradient_surgery.per_task_gradients`).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch as th
from torch import nn

from sb3_mtte.common.gradient_surgery import (
    KeepsRows,
    assign_flat_gradient,
    per_task_gradients,
    per_task_gradients_of_rows,
)
from sb3_mtte.common.update_hooks import UpdateHook
from sb3_mtte.common.update_monitor import UpdateMonitor


def task_step(
    optimizer: th.optim.Optimizer,
    name: str,
    task_losses: th.Tensor,
    task_weights: th.Tensor,
    monitor: UpdateMonitor,
    combining_hook: UpdateHook | None = None,
    module: nn.Module | None = None,
) -> th.Tensor:
    """One step of ``optimizer`` on the per-task losses; returns ``sum_i w_i L_i``.

    :param optimizer: the optimizer of the parameters.
    :param name: name of the loss (for the error of a non-finite loss).
    :param task_losses: ``(N,)`` per-task losses with their graph.
    :param task_weights: ``(N,)`` weights of the tasks.
    :param monitor: checks that the loss is finite (at once, or deferred on the CUDA-graph path).
    :param combining_hook: the hook whose combination of the per-task gradients the step follows (for parameters
        the tasks share); None: the gradient of ``sum_i w_i L_i``.
    :param module: the module of the parameters, if it may have kept its forward pass (:func:`enable_kept_rows`).
    """
    if combining_hook is None:
        return weighted_step(optimizer, name, task_losses, task_weights, monitor)
    return combined_step(optimizer, name, task_losses, task_weights, monitor, combining_hook, module)


def weighted_step(
    optimizer: th.optim.Optimizer, name: str, task_losses: th.Tensor, task_weights: th.Tensor, monitor: UpdateMonitor
) -> th.Tensor:
    """Minimise ``sum_i w_i L_i`` by one step of ``optimizer``; a non-finite loss stops training (before the step,
    or at the next read of ``monitor`` on the CUDA-graph path)."""
    loss = (task_weights * task_losses).sum()
    monitor.check_finite(name, loss)
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return loss


def combined_step(
    optimizer: th.optim.Optimizer,
    name: str,
    task_losses: th.Tensor,
    task_weights: th.Tensor,
    monitor: UpdateMonitor,
    combining_hook: UpdateHook,
    module: nn.Module | None = None,
) -> th.Tensor:
    """One step of ``optimizer`` along ``combining_hook``'s direction (arguments of :func:`task_step`); returns
    ``sum_i w_i L_i``, detached."""
    kept = take_kept_rows(module)  # taken first: a non-finite loss leaves no graph behind
    loss = (task_weights * task_losses).sum()
    monitor.check_finite(name, loss)
    params = [p for group in optimizer.param_groups for p in group["params"] if p.requires_grad]
    grads = module_task_gradients(module, kept, task_losses, params)
    direction = combining_hook.combine_gradients(grads, task_weights)
    optimizer.zero_grad()
    assign_flat_gradient(params, direction)
    optimizer.step()
    return loss.detach()


def enable_kept_rows(modules: Iterable[nn.Module], combines_gradients: bool) -> None:
    """Let the modules keep their forward passes for the per-task gradients, when that pays."""
    for module in modules:
        if isinstance(module, KeepsRows) and module.shared_rows_network is not None:
            module.keep_rows = combines_gradients


def take_kept_rows(module: nn.Module | None) -> tuple[th.Tensor, th.Tensor, int] | None:
    """The forward pass ``module`` kept (and forgets now), or None."""
    return module.take_kept_rows() if isinstance(module, KeepsRows) else None


def module_task_gradients(
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
