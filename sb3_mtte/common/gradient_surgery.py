"""Gradient surgery for the parameters the tasks share: PCGrad (Yu et al. 2020) and CAGrad (Liu et al. 2021).

Both methods turn the per-task gradients G (N x P, row i = grad of task i's loss) into one update direction that is a
linear combination of the rows, d = a^T G. Everything they decide is decided on the N x N Gram matrix G G^T, so the
pure functions below work on the Gram matrix and return the coefficients a (N,); :func:`surgery_direction` applies
d = a^T G to the G of :func:`per_task_gradients_of_rows` (a shared network, one more forward and backward pass) or
:func:`per_task_gradients` (any parameters, N backward passes).
"""

from __future__ import annotations

import math

import numpy as np
import torch as th
from torch import nn
from torch.func import functional_call, grad, vmap

GRADIENT_SURGERY_METHODS = ("pcgrad", "cagrad")


# ------------------------------------------------------------------------------------------------------ PCGrad
def pcgrad_orders(n_tasks: int, generator: th.Generator | None = None) -> np.ndarray:
    """A random order of the other tasks for every task (Algorithm 1: "for g_j in G \\ g_i in random order").

    :param n_tasks: N.
    :param generator: torch CPU generator (the global one by default, so that saved RNG states replay the orders).
    :return: ``(N, N - 1)`` integer array, row i a permutation of the tasks other than i.
    """
    keys = th.rand(n_tasks, n_tasks, generator=generator, dtype=th.float64)
    keys.fill_diagonal_(2.0)  # task i last, then dropped
    return keys.argsort(dim=1)[:, : n_tasks - 1].numpy()


def pcgrad_coefficients(gram: np.ndarray, orders: np.ndarray) -> np.ndarray:
    """PCGrad's projected gradients as combinations of the original ones (Yu et al. 2020, Algorithm 1).

    For every task i, in the order ``orders[i]``: if g_i^PC . g_j < 0, then g_i^PC -= (g_i^PC . g_j / ||g_j||^2) g_j,
    with g_j task j's original gradient. Every task is processed at once, one position of the orders at a time.

    :param gram: ``(N, N)`` Gram matrix G G^T of the original gradients.
    :param orders: ``(N, N - 1)`` order of the other tasks for every task (:func:`pcgrad_orders`).
    :return: ``(N, N)`` matrix C with g_i^PC = sum_k C[i, k] g_k.
    """
    n_tasks = gram.shape[0]
    coefficients = np.eye(n_tasks, dtype=gram.dtype)
    rows = np.arange(n_tasks)
    for position in range(orders.shape[1]):
        others = orders[:, position]
        dots = np.einsum("ik,ki->i", coefficients, gram[:, others])  # g_i^PC . g_j
        squared_norms = gram[others, others]
        conflict = (dots < 0) & (squared_norms > 0)
        coefficients[rows, others] -= np.where(conflict, dots / np.where(conflict, squared_norms, 1.0), 0.0)
    return coefficients


# ------------------------------------------------------------------------------------------------------ CAGrad
def project_to_simplex(x: np.ndarray) -> np.ndarray:
    """Euclidean projection of x (N,) onto the probability simplex (sort-based, Held et al. 1974)."""
    u = np.sort(x)[::-1]
    cumulative = np.cumsum(u) - 1.0
    index = np.arange(1, x.size + 1)
    rho = np.nonzero(u - cumulative / index > 0)[0][-1]
    return np.maximum(x - cumulative[rho] / (rho + 1.0), 0.0)


def cagrad_dual_objective(p: np.ndarray, gram: np.ndarray, weights: np.ndarray, c: float) -> float:
    """CAGrad's dual objective F(p) = g_p . g0 + c ||g0|| ||g_p|| with g_p = p^T G and g0 = weights^T G
    (Liu et al. 2021, Eq. 7 / Algorithm 1), from the Gram matrix."""
    g0_norm = math.sqrt(max(float(weights @ gram @ weights), 0.0))
    return float(p @ gram @ weights) + c * g0_norm * math.sqrt(max(float(p @ gram @ p), 0.0))


def cagrad_solve_dual(
    gram: np.ndarray, weights: np.ndarray, c: float, max_iter: int = 500, tol: float = 1e-12
) -> np.ndarray:
    """Minimise :func:`cagrad_dual_objective` over the simplex by projected gradient descent with backtracking.

    :param gram: ``(N, N)`` Gram matrix of the task gradients.
    :param weights: ``(N,)`` weights of the average gradient g0.
    :param c: the radius factor of CAGrad's ball, ||d - g0|| <= c ||g0||.
    :param max_iter: iterations at most.
    :param tol: stop when an accepted step lowers the objective by less than ``tol`` (relative to F's scale).
    :return: ``(N,)`` the minimiser p on the simplex.
    """
    scale = float(np.mean(np.diag(gram)))
    if scale <= 0:
        return np.full(gram.shape[0], 1.0 / gram.shape[0])
    a = gram / scale  # the minimiser does not depend on the scale of G
    b = a @ weights
    k = c * math.sqrt(max(float(weights @ b), 0.0))
    eps = 1e-12

    def objective(p: np.ndarray) -> float:
        return float(p @ b) + k * math.sqrt(max(float(p @ a @ p), 0.0) + eps)

    p = np.full(a.shape[0], 1.0 / a.shape[0])
    value, step = objective(p), 1.0
    for _ in range(max_iter):
        gradient = b + k * (a @ p) / math.sqrt(max(float(p @ a @ p), 0.0) + eps)
        while True:
            candidate = project_to_simplex(p - step * gradient)
            candidate_value = objective(candidate)
            if candidate_value <= value - 1e-4 * float(gradient @ (p - candidate)) or step < 1e-12:
                break
            step *= 0.5
        improvement = value - candidate_value
        if improvement < 0:
            break
        p, value, step = candidate, candidate_value, step * 2.0
        if improvement < tol:
            break
    return p


def cagrad_coefficients(gram: np.ndarray, weights: np.ndarray, c: float) -> np.ndarray:
    """CAGrad's direction d = g0 + (c ||g0|| / ||g_p||) g_p as coefficients of the task gradients (Liu et al. 2021,
    Algorithm 1), with p the dual minimiser (:func:`cagrad_solve_dual`); not rescaled.

    d maximises min_i g_i . d over the ball ||d - g0|| <= c ||g0||.

    :return: ``(N,)`` a with d = a^T G (the zero vector's coefficients when g0 = 0).
    """
    g0_norm = math.sqrt(max(float(weights @ gram @ weights), 0.0))
    if g0_norm == 0.0:
        return np.zeros_like(weights)
    p = cagrad_solve_dual(gram, weights, c)
    gp_norm = math.sqrt(max(float(p @ gram @ p), 0.0))
    if gp_norm == 0.0:
        return weights.copy()
    return weights + (c * g0_norm / gp_norm) * p


# ---------------------------------------------------------------------------------------------- with torch
def per_task_gradients(task_losses: th.Tensor, params: list[th.Tensor]) -> th.Tensor:
    """``(N, P)`` gradients of the N task losses w.r.t. ``params``, by one batched backward pass
    (``is_grads_batched``: the N vector-Jacobian products with the rows of the identity run as one vmap)."""
    n_tasks = task_losses.shape[0]
    identity = th.eye(n_tasks, dtype=task_losses.dtype, device=task_losses.device)
    grads = th.autograd.grad(task_losses, params, grad_outputs=identity, is_grads_batched=True, allow_unused=True)
    flat = [
        th.zeros(n_tasks, p.numel(), dtype=p.dtype, device=p.device) if g is None else g.reshape(n_tasks, -1)
        for g, p in zip(grads, params, strict=True)
    ]
    return th.cat(flat, dim=1)


def per_task_gradients_of_rows(
    network: nn.Module, inputs: th.Tensor, outputs: th.Tensor, task_losses: th.Tensor, task_dim: int = 0
) -> th.Tensor:
    """``(N, P)`` gradients of the N task losses w.r.t. ``network``'s parameters, for a network that every task
    shares and that maps each row of a task-major batch on its own (an MLP on state + one-hot).

    Task i's loss then reaches the parameters only through task i's rows of ``outputs``, so one backward pass of
    sum_i L_i to ``outputs`` gives every task's cotangent, and one ``vmap`` over the task axis of the
    vector-Jacobian product of the network turns them into per-task gradients (each weight gradient one batched
    matmul over tasks): the cost of one more forward and backward pass of the network, where
    :func:`per_task_gradients` pays N backward passes.

    :param network: the shared network (called on one task's slice of ``inputs``).
    :param inputs: what ``network`` was called on, with the tasks on axis ``task_dim`` (``(N, L, in)`` for a
        plain MLP; ``(n_members, N, L, in)`` with ``task_dim=1`` for an ensemble of shared members).
    :param outputs: what it returned, with the graph from there to ``task_losses``; any shape that reshapes to
        ``inputs``' shape with the last axis of its own (the rows in task-major order).
    :param task_losses: ``(N,)``.
    :param task_dim: the task axis of ``inputs``.
    :return: ``(N, P)``, columns in the order of ``network.parameters()``.
    """
    (cotangents,) = th.autograd.grad(task_losses.sum(), outputs)
    cotangents = cotangents.reshape(*inputs.shape[:-1], -1)
    params = {name: p.detach() for name, p in network.named_parameters()}

    def task_gradient(task_inputs: th.Tensor, task_cotangent: th.Tensor) -> dict[str, th.Tensor]:
        return grad(lambda p: (functional_call(network, p, (task_inputs,)) * task_cotangent).sum())(params)

    grads = vmap(task_gradient, in_dims=task_dim)(inputs.detach(), cotangents)
    return th.cat([grads[name].reshape(task_losses.shape[0], -1) for name in params], dim=1)


class KeepsRows:
    """Mixin of a module that can keep its last differentiable forward pass for the per-task gradients of
    :func:`per_task_gradients_of_rows` (gradient surgery on the actor or a shared critic).

    Contract: the shared network's parameters reach the step's losses only through the last kept pass (a second
    differentiable pass before the step replaces the first, whose part of the gradient would be lost), and the step
    takes the pass (:meth:`take_kept_rows`) whether it succeeds or not.
    """

    keep_rows: bool = False
    """Whether :meth:`_keep_rows` keeps what it is given (set by the algorithm when it combines gradients)."""
    kept_rows: tuple[th.Tensor, th.Tensor, int] | None = None
    """``(inputs, outputs, task_dim)`` of the last differentiable pass of :attr:`shared_rows_network`."""

    @property
    def shared_rows_network(self) -> nn.Module | None:
        """The network the module is, if all its parameters are shared by the tasks and it maps every row on its
        own (then its per-task gradients cost one more pass of it, not N backward passes); None otherwise."""
        return None

    def _keep_rows(self, inputs: th.Tensor, outputs: th.Tensor, task_dim: int = 0) -> None:
        """Keep a pass that differentiates the shared network's parameters (not one where they are constants)."""
        if self.keep_rows and outputs.requires_grad and next(self.shared_rows_network.parameters()).requires_grad:
            self.kept_rows = (inputs, outputs, task_dim)

    def take_kept_rows(self) -> tuple[th.Tensor, th.Tensor, int] | None:
        """The kept pass, once (it holds the graph)."""
        kept, self.kept_rows = self.kept_rows, None
        return kept


def surgery_direction(method: str, grads: th.Tensor, task_weights: th.Tensor, cagrad_c: float = 0.5) -> th.Tensor:
    """The update direction of PCGrad or CAGrad, flattened (P,), from the per-task gradients.

    PCGrad: sum_i w_i g_i^PC (the average of the projected gradients for MTSAC's w_i = 1/N). CAGrad: d / (1 + c^2)
    with d from :func:`cagrad_coefficients` and g0 = sum_i w_i g_i.

    :param method: ``"pcgrad"`` or ``"cagrad"``.
    :param grads: ``(N, P)`` per-task gradients (:func:`per_task_gradients`, :func:`per_task_gradients_of_rows`).
    :param task_weights: ``(N,)`` weights w_i of the tasks in the average.
    :param cagrad_c: CAGrad's c.
    """
    gram = (grads @ grads.T).detach().to("cpu", th.float64).numpy()
    weights = task_weights.detach().to("cpu", th.float64).numpy()
    if method == "pcgrad":
        combination = weights @ pcgrad_coefficients(gram, pcgrad_orders(len(weights)))
    elif method == "cagrad":
        combination = cagrad_coefficients(gram, weights, cagrad_c) / (1.0 + cagrad_c**2)
    else:
        raise ValueError(f"Unknown gradient surgery method {method!r}: one of {GRADIENT_SURGERY_METHODS}.")
    return th.as_tensor(combination, dtype=grads.dtype, device=grads.device) @ grads


def assign_flat_gradient(params: list[th.Tensor], flat: th.Tensor) -> None:
    """Write a flat (P,) gradient into ``params``' ``.grad``."""
    offset = 0
    for param in params:
        param.grad = flat[offset : offset + param.numel()].view_as(param).clone()
        offset += param.numel()
