"""Acting replayed as a CUDA graph, the second graph of the fast path beside the update's.

Acting on a GPU is a few dozen small kernels: the actor's forward pass and its sampling, after E_phi's for MTSACTE.
Their launches, and a copy of the actions to the host that waits for them, set its pace. :class:`CapturedAction`
records the kernels of one call of the policy's eager acting function (its ``act``) once per observation shape and
mode, and replays them every step. The actions come to the host as one copy into pinned memory.

The random draws advance between replays as they would between eager calls. PyTorch's CUDA generator is graph-safe:
each replay reads the generator's current Philox offset and moves it on by what the captured kernels draw, as for the
update's graph (:mod:`~sb3_mtte.common.captured_update`). A replay thus draws the noise an eager call would draw at
that point of the stream.
"""

from __future__ import annotations

from collections.abc import Callable

import torch as th

from sb3_mtte.common import gpu_defaults

ActFunction = Callable[[th.Tensor, bool], th.Tensor]
"""``(observations, deterministic) -> actions``, on the policy's device; it must not read a device tensor on the
host, nor branch on one."""
GraphKey = tuple[tuple[int, ...], th.dtype, bool]
"""What one graph serves: the observations' shape and dtype, and ``deterministic``."""
CAPTURE_ACTING = False
"""True: where a model's update path asks for the fast path on CUDA, its acting is captured too. False (the default
until the device check has measured it on a GPU) acts eagerly beside the captured update."""


def resolve_action_path(update_path: str, device: th.device) -> str:
    """``"eager"`` or ``"cuda_graph"``: acting takes the graph on CUDA where the update path asks for the fast path
    (``"auto"`` while :data:`~sb3_mtte.common.gpu_defaults.FAST_PATH_BY_DEFAULT` is set, or ``"cuda_graph"``),
    whatever the update's hooks, and :data:`CAPTURE_ACTING` is set. ``"eager"``, and every other device, act
    eagerly."""
    if device.type != "cuda" or update_path == "eager" or not CAPTURE_ACTING:
        return "eager"
    return "cuda_graph" if update_path == "cuda_graph" or gpu_defaults.FAST_PATH_BY_DEFAULT else "eager"


def action_runner(path: str, act: ActFunction, device: th.device, capture: bool = True) -> CapturedAction | None:
    """What a policy's ``_predict`` runs on ``path``: None (``act`` itself, eagerly), or ``act``'s
    :class:`CapturedAction` (``capture=False``: the graph path without the graph, which the CPU can run)."""
    return None if path == "eager" else CapturedAction(act, device, capture)


class CapturedAction:
    """Run ``act(observations, deterministic)`` as a CUDA graph; return the actions on the host.

    Each graph key (observations' shape and dtype, ``deterministic``) is served by its own graph. Its first
    :attr:`WARMUP` calls run eagerly on a side stream (cuBLAS and the caching allocator settle; they are real
    actions). The next call copies the observations into a static tensor, captures the graph (capturing runs
    nothing) and replays it; every later call copies and replays. The actions come back by one copy into pinned host
    memory, and are returned as a CPU tensor of their own.

    :param act: the policy's eager acting function.
    :param device: the CUDA device of the policy (its streams and graphs are made there).
    :param capture: False runs everything but the graph (static inputs, the warm-up, the copy out): the CPU's view
        of this path, for tests.
    """

    WARMUP = 3

    def __init__(self, act: ActFunction, device: th.device, capture: bool = True) -> None:
        self.act, self.device, self.capture = act, device, capture
        self.warmup_calls: dict[GraphKey, int] = {}
        self.static_observations: dict[GraphKey, th.Tensor] = {}
        self.static_actions: dict[GraphKey, th.Tensor] = {}
        self.host_actions: dict[GraphKey, th.Tensor] = {}
        self.graphs: dict[GraphKey, th.cuda.CUDAGraph] = {}

    def __call__(self, observations: th.Tensor, deterministic: bool = False) -> th.Tensor:
        with th.no_grad():
            if not self.capture:
                return self._run(observations, deterministic)
            with th.cuda.device(self.device):
                return self._run(observations, deterministic)

    def _run(self, observations: th.Tensor, deterministic: bool) -> th.Tensor:
        key = (tuple(observations.shape), observations.dtype, deterministic)
        calls = self.warmup_calls.get(key, 0)
        if calls < self.WARMUP:
            self.warmup_calls[key] = calls + 1
            return self._eager(observations, deterministic).cpu()
        static = self.static_observations.get(key)
        if static is None:
            static = self.static_observations[key] = observations.clone()
        else:
            static.copy_(observations)
        if not self.capture:
            return self._to_host(key, self.act(static, deterministic))
        if key not in self.graphs:
            self._capture(key)
        self.graphs[key].replay()
        return self._to_host(key, self.static_actions[key])

    def _eager(self, observations: th.Tensor, deterministic: bool) -> th.Tensor:
        if not self.capture:
            return self.act(observations, deterministic)
        stream = th.cuda.Stream()
        stream.wait_stream(th.cuda.current_stream())
        with th.cuda.stream(stream):
            actions = self.act(observations, deterministic)
        th.cuda.current_stream().wait_stream(stream)
        return actions

    def _capture(self, key: GraphKey) -> None:
        graph = th.cuda.CUDAGraph()
        with th.cuda.graph(graph):
            self.static_actions[key] = self.act(self.static_observations[key], key[2])
        self.graphs[key] = graph

    def _to_host(self, key: GraphKey, actions: th.Tensor) -> th.Tensor:
        """One copy of ``actions`` into the key's pinned host buffer, waited for; a CPU tensor of their own."""
        host = self.host_actions.get(key)
        if host is None:
            host = th.empty(actions.shape, dtype=actions.dtype, pin_memory=self.capture)
            self.host_actions[key] = host
        host.copy_(actions, non_blocking=self.capture)
        if self.capture:
            th.cuda.current_stream().synchronize()
        return host.clone()
