"""How much task information the representation z carries: a linear probe of the task from z."""

from __future__ import annotations

import torch as th


def task_probe_accuracy(z: th.Tensor, ridge: float = 1e-3) -> float:
    """Held-out accuracy of a linear probe that predicts the task from z.

    A ridge regression from (z, 1) onto the task's one-hot is fitted on the even samples of every task and scored on
    the odd ones (predicted task = argmax). Chance level is 1 / N; 1.0 means z alone tells the tasks apart linearly.

    :param z: ``(N, L, z_dim)`` task-major samples of z; the fit runs on the CPU in float64.
    :return: the accuracy, or NaN when L < 2 (nothing to hold out).
    :param ridge: L2 penalty of the fit.
    """
    n_tasks, length, _ = z.shape
    if length < 2:
        return float("nan")
    z = z.detach().to("cpu", th.float64)
    features = th.cat([z, z.new_ones(*z.shape[:-1], 1)], dim=-1)
    fit, held_out = features[:, 0::2], features[:, 1::2]
    targets = th.eye(n_tasks, dtype=features.dtype).unsqueeze(1).expand(-1, fit.shape[1], -1)
    x, y = fit.reshape(-1, features.shape[-1]), targets.reshape(-1, n_tasks)
    gram = x.T @ x + ridge * th.eye(x.shape[1], dtype=x.dtype)
    weights = th.linalg.solve(gram, x.T @ y)
    predicted = (held_out.reshape(-1, features.shape[-1]) @ weights).argmax(dim=-1)
    labels = th.arange(n_tasks).repeat_interleave(held_out.shape[1])
    return float((predicted == labels).double().mean())
