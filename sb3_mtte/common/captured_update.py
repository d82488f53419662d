"""An update step replayed as a CUDA graph.

A multi-task SAC update is a few hundred small kernels; on a GPU their launches, not their arithmetic, set its pace.
:class:`CapturedUpdate` records the kernels of one call of the update function once (``torch.cuda.CUDAGraph``) and
replays them every step: the same function as the eager path, on static copies of its inputs, with the optimizers
made capturable (their step counters and learning rates on the device).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch as th

from sb3_mtte.common.update_monitor import Stats

UpdateFunction = Callable[[Any, bool], Stats]


def prepare_for_capture(optimizer: th.optim.Optimizer, capturable: bool) -> None:
    """Hold every parameter group's learning rate in a 0-dim tensor on its parameters' device (updated in place by
    :func:`set_learning_rate`), and, when ``capturable``, make the optimizer's step a sequence of device kernels."""
    for group in optimizer.param_groups:
        device = group["params"][0].device
        if not isinstance(group["lr"], th.Tensor):
            dtype = th.float32 if device.type == "cuda" else th.float64  # CUDA's fused Adam reads a float32 one
            group["lr"] = th.tensor(float(group["lr"]), dtype=dtype, device=device)
        group["capturable"] = capturable
    if capturable:
        for param, state in optimizer.state.items():
            if isinstance(state.get("step"), th.Tensor):
                state["step"] = state["step"].to(param.device)


def set_learning_rate(optimizers: Sequence[th.optim.Optimizer], learning_rate: float) -> None:
    """SB3's ``update_learning_rate``, writing a tensor learning rate in place (a captured step reads it there)."""
    for optimizer in optimizers:
        for group in optimizer.param_groups:
            if isinstance(group["lr"], th.Tensor):
                group["lr"].fill_(learning_rate)
            else:
                group["lr"] = learning_rate


class CapturedUpdate:
    """Run ``update(batch, polyak)`` as a CUDA graph.

    The optimizers are made capturable at once, so the first :attr:`WARMUP` calls, which run eagerly on a side
    stream (cuBLAS and the caching allocator settle; they are real updates), take the same Adam steps as the graph
    (an optimizer's capturable and plain branches round its bias correction differently). The next call copies its
    batch into static tensors, captures one graph per value of ``polyak`` (capturing runs nothing) and replays it;
    every later call copies its batch and replays. Outputs are cloned out of the graph's memory, which the next
    replay overwrites.

    :param update: the eager update function: ``(batch, polyak) -> stats``; it must not read a device tensor on the
        host, nor branch on one.
    :param get_optimizers: the optimizers the update steps (made capturable here when ``capture``).
    :param device: the CUDA device of the update (its streams and graphs are made there).
    :param capture: False runs everything but the graph (static inputs, tensor learning rates): the CPU's view of
        this path, for tests.
    """

    WARMUP = 3

    def __init__(
        self,
        update: UpdateFunction,
        get_optimizers: Callable[[], Sequence[th.optim.Optimizer]],
        device: th.device,
        capture: bool = True,
    ) -> None:
        self.update, self.device, self.capture = update, device, capture
        self.warmup_calls = 0
        self.static_batch: NamedTuple | None = None
        self.graphs: dict[bool, th.cuda.CUDAGraph] = {}
        self.outputs: dict[bool, Stats] = {}
        for optimizer in get_optimizers():
            prepare_for_capture(optimizer, capturable=capture)

    def __call__(self, batch: NamedTuple, polyak: bool) -> Stats:
        if not self.capture:
            return self._run(batch, polyak)
        with th.cuda.device(self.device):
            return self._run(batch, polyak)

    def _run(self, batch: NamedTuple, polyak: bool) -> Stats:
        if self.static_batch is not None and [f.shape for f in self.static_batch] != [f.shape for f in batch]:
            self.static_batch, self.graphs, self.outputs = None, {}, {}  # another batch size: warmed up, captured
            self.warmup_calls = 0
        if self.warmup_calls < self.WARMUP:
            self.warmup_calls += 1
            return self._eager(batch, polyak)
        if self.static_batch is None:
            self.static_batch = type(batch)(*(field.clone() for field in batch))
        else:
            for static, field in zip(self.static_batch, batch, strict=True):
                static.copy_(field)
        if not self.capture:
            return self.update(self.static_batch, polyak)
        if polyak not in self.graphs:
            self._capture(polyak)
        self.graphs[polyak].replay()
        return {key: value.clone() for key, value in self.outputs[polyak].items()}

    def _eager(self, batch: NamedTuple, polyak: bool) -> Stats:
        if not self.capture:
            return self.update(batch, polyak)
        stream = th.cuda.Stream()
        stream.wait_stream(th.cuda.current_stream())
        with th.cuda.stream(stream):
            stats = self.update(batch, polyak)
        th.cuda.current_stream().wait_stream(stream)
        return stats

    def _capture(self, polyak: bool) -> None:
        graph = th.cuda.CUDAGraph()
        with th.cuda.graph(graph):
            self.outputs[polyak] = self.update(self.static_batch, polyak)
        self.graphs[polyak] = graph
