"""Where the replay buffer's transitions live when the model trains on a GPU.

The buffer's numpy arrays stay the record that ``save_replay_buffer`` writes. With ``storage="device"`` a copy of
them lives on the model's device (:class:`DeviceStorage`): each vector step writes its N transitions there, and a
batch is gathered there from indices drawn on the host by the same numpy draw as on the CPU (N x L integers cross
to the device, never the batch). With ``storage="pinned"`` (for a buffer the GPU cannot hold) the batch is gathered
on the host and copied to the device from page-locked memory, without waiting for the copy.
"""

from __future__ import annotations

import numpy as np
import torch as th

from sb3_mtte.common import gpu_defaults

STORAGES = ("auto", "host", "pinned", "device")
DEVICE_SHARE = 0.5
"""``"auto"`` with :data:`~sb3_mtte.common.gpu_defaults.FAST_PATH_BY_DEFAULT` keeps the buffer on the GPU when it takes
at most this share of the GPU's free memory."""


def check_storage(storage: str) -> None:
    """:raises ValueError: for a storage other than those of :data:`STORAGES`."""
    if storage not in STORAGES:
        raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}.")


def resolve_storage(storage: str, device: th.device, n_bytes: int) -> str:
    """``"host"``, ``"pinned"`` or ``"device"`` for a buffer of ``n_bytes`` on ``device``: ``"auto"`` is, on CUDA
    with :data:`~sb3_mtte.common.gpu_defaults.FAST_PATH_BY_DEFAULT` (the default), the GPU where the buffer fits, else
    pinned; the host otherwise.

    :raises ValueError: for an unknown storage.
    """
    check_storage(storage)
    if storage != "auto":
        return storage
    if device.type != "cuda" or not gpu_defaults.FAST_PATH_BY_DEFAULT:
        return "host"
    free, _ = th.cuda.mem_get_info(device)
    return "device" if n_bytes <= DEVICE_SHARE * free else "pinned"


def _pinned(array: np.ndarray) -> th.Tensor:
    return th.from_numpy(np.ascontiguousarray(array)).pin_memory()


def to_device(array: np.ndarray, device: th.device) -> th.Tensor:
    """``array`` on ``device``; from page-locked memory without waiting when it is a GPU (PyTorch's host allocator
    keeps the page-locked block until the copy is done)."""
    if device.type != "cuda":
        return th.from_numpy(np.ascontiguousarray(array)).to(device)
    return _pinned(array).to(device, non_blocking=True)


class DeviceStorage:
    """The buffer's ``(rows, N, ...)`` transition arrays mirrored on ``device``.

    :param arrays: the buffer's arrays by field name (uploaded once: empty for a new buffer, full after a load).
    :param device: the model's device.
    """

    def __init__(self, arrays: dict[str, np.ndarray], device: th.device) -> None:
        self.device = device
        self.tensors = {name: th.from_numpy(array).to(device, copy=True) for name, array in arrays.items()}
        self.columns = th.arange(next(iter(arrays.values())).shape[1], device=device)[:, None]

    def write(self, row: int, arrays: dict[str, np.ndarray]) -> None:
        """Copy row ``row`` of every array to the device (from page-locked memory when it is a GPU)."""
        stage = _pinned if self.device.type == "cuda" else th.from_numpy
        for name, array in arrays.items():
            self.tensors[name][row].copy_(stage(array[row]), non_blocking=True)

    def gather(self, rows: np.ndarray) -> dict[str, th.Tensor]:
        """``(N, L, ...)`` tensors: row ``rows[i, j]`` of task i's column, for every array."""
        index = to_device(rows, self.device)
        return {name: tensor[index, self.columns] for name, tensor in self.tensors.items()}
