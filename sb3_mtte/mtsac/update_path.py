"""How MTSAC runs its updates: eagerly, or replayed as a CUDA graph (the default on CUDA where the update allows it:
:mod:`~sb3_mtte.common.gpu_defaults`).

Both paths run one function, :meth:`sb3_mtte.MTSAC._update` (the SAC update of Eq. 3, 9 and 15-16, then Polyak); the
CUDA-graph path records its kernels once and replays them (:class:`~sb3_mtte.common.captured_update.CapturedUpdate`),
and reads the finiteness of the losses and the logged statistics only when the logger dumps
(:class:`~sb3_mtte.common.update_monitor.UpdateMonitor`). An update whose hooks read the GPU on the host (gradient
surgery's solve on the Gram matrix, PaCo's reset of collapsed tasks) runs eagerly.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch as th

from sb3_mtte.common import gpu_defaults
from sb3_mtte.common.captured_update import CapturedUpdate, UpdateFunction


def resolve_update_path(update_path: str, device: th.device, capturable: bool) -> str:
    """``"eager"`` or ``"cuda_graph"``: ``"auto"`` takes the graph on CUDA when the update's hooks allow it
    (``capturable``) and :data:`~sb3_mtte.common.gpu_defaults.FAST_PATH_BY_DEFAULT` is set (the default), else eager.

    :raises ValueError: for ``"cuda_graph"`` off CUDA or with hooks that read the GPU on the host.
    """
    if update_path == "auto":
        fast = gpu_defaults.FAST_PATH_BY_DEFAULT and device.type == "cuda" and capturable
        return "cuda_graph" if fast else "eager"
    if update_path == "cuda_graph" and device.type != "cuda":
        raise ValueError(f"update_path='cuda_graph' needs a CUDA device, got {device}: use 'auto' or 'eager'.")
    if update_path == "cuda_graph" and not capturable:
        raise ValueError(
            "update_path='cuda_graph': this update reads the GPU on the host every step (gradient surgery, or "
            "PaCo's reset with a task_loss_threshold): use 'auto' or 'eager'."
        )
    return update_path


def update_runner(
    path: str,
    update: UpdateFunction,
    get_optimizers: Callable[[], Sequence[th.optim.Optimizer]],
    device: th.device,
    capture: bool = True,
) -> UpdateFunction:
    """What runs every update on ``path``: ``update`` itself (eager), or its :class:`CapturedUpdate`.

    :param path: ``"eager"`` or ``"cuda_graph"``.
    :param update: the eager update, ``(batch, polyak) -> stats``.
    :param get_optimizers: the optimizers ``update`` steps.
    :param device: the model's device.
    :param capture: False runs the graph path without the graph (the CPU can run it).
    """
    if path != "eager":
        return CapturedUpdate(update, get_optimizers, device, capture)
    for optimizer in get_optimizers():  # a checkpoint of the graph path keeps its optimizers' flag
        for group in optimizer.param_groups:
            group["capturable"] = False
    return update
