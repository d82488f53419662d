"""ReLU MLPs as one autograd node: every ReLU runs in place on its layer's output, every ReLU gradient in place.

Layer by layer, eager PyTorch writes each ReLU output and each ReLU input-gradient to fresh memory: on a CPU with a
few MB of cache per core that is a pass to main memory per activation (12-13% of an SAC update with 400-wide
layers, in a profile). Here the ReLU runs in place on the matmul's output while it is still in cache, and the
backward pass masks each input gradient in the buffer its matmul just wrote. The numbers are those of the
layer-by-layer graph (``tests/test_relu_mlp.py`` compares values and gradients).

The layer-by-layer graph is used instead inside ``torch.func`` transforms (``vmap``/``grad``/``vjp``), under
autocast, within ``with fused_relu_mlp(False):``, on a PyTorch release outside :data:`TESTED_TORCH` (the
release ``.ci/run`` tests; setup.cfg admits every release stable-baselines3 does), and on a PyTorch without the two
private functions that tell a transform or a vmapped tensor apart (``torch._C._are_functorch_transforms_active``,
``torch._C._dispatch_keys``). The node is differentiable once: a backward pass through it with ``create_graph=True``
raises an error that says to turn it off.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache

import torch as th

_threshold_backward = th.ops.aten.threshold_backward
_enabled = True

TESTED_TORCH = ((2, 13), (2, 14))
"""PyTorch releases ``[lower, upper)`` (major, minor) the fused node is tested on (``.ci/run`` pins 2.13.0)."""


@contextmanager
def fused_relu_mlp(enabled: bool) -> Iterator[None]:
    """Within the block, ReLU MLPs run as one node (``True``, the default outside) or layer by layer (``False``,
    e.g. for second derivatives)."""
    global _enabled
    before, _enabled = _enabled, bool(enabled)
    try:
        yield
    finally:
        _enabled = before


def private_internals_present() -> bool:
    """Whether this PyTorch has the private functions the fused node relies on (else: layer by layer)."""
    return all(hasattr(th._C, name) for name in ("_are_functorch_transforms_active", "_dispatch_keys"))


@lru_cache
def tested_release(version: str) -> bool:
    """Whether PyTorch ``version`` (``th.__version__``) lies in :data:`TESTED_TORCH`."""
    match = re.match(r"(\d+)\.(\d+)", version)
    lower, upper = TESTED_TORCH
    return match is not None and lower <= (int(match[1]), int(match[2])) < upper


def fused_relu_mlp_applies(x: th.Tensor, stacked: bool) -> bool:
    """Whether :func:`relu_mlp` may take ``x``: turned on, a tested PyTorch release with its private functions, not
    under a ``torch.func`` transform nor autocast, 3-D if stacked."""
    return (
        _enabled
        and tested_release(th.__version__)
        and private_internals_present()
        and not th._C._are_functorch_transforms_active()
        and not th.is_autocast_enabled(x.device.type)
        and (not stacked or x.dim() == 3)
    )


def _is_vmapped(tensor: th.Tensor) -> bool:
    """A tensor batched by ``vmap`` (e.g. in ``autograd.grad(..., is_grads_batched=True)``): no out= ops on it."""
    return "Batched" in str(th._C._dispatch_keys(tensor))  # Batched (autograd's vmap) or FuncTorchBatched


def _affine(x: th.Tensor, weight: th.Tensor, bias: th.Tensor, stacked: bool) -> th.Tensor:
    return th.matmul(x, weight if stacked else weight.t()).add_(bias)


def _weight_grad(x: th.Tensor, grad: th.Tensor, stacked: bool) -> th.Tensor:
    if stacked:  # (E, B, in), (E, B, out) -> (E, in, out)
        return th.bmm(x.transpose(1, 2), grad)
    return grad.reshape(-1, grad.shape[-1]).t().mm(x.reshape(-1, x.shape[-1]))  # (out, in), as nn.Linear


def _bias_grad(grad: th.Tensor, stacked: bool) -> th.Tensor:
    if stacked:  # (E, 1, out)
        return grad.sum(1, keepdim=True)
    return grad.reshape(-1, grad.shape[-1]).sum(0)


class _ReLUMLP(th.autograd.Function):
    @staticmethod
    def forward(ctx, x: th.Tensor, stacked: bool, relu_last: bool, *params: th.Tensor) -> th.Tensor:
        weights, biases = params[0::2], params[1::2]
        layer_inputs, h = [], x
        for index, (weight, bias) in enumerate(zip(weights, biases, strict=True)):
            layer_inputs.append(h)
            h = _affine(h, weight, bias, stacked)
            if relu_last or index < len(weights) - 1:
                h.relu_()
        ctx.stacked, ctx.relu_last, ctx.n_layers = stacked, relu_last, len(weights)
        ctx.save_for_backward(*layer_inputs, *weights, *((h,) if relu_last else ()))
        return h

    @staticmethod
    def backward(ctx, grad_output: th.Tensor):
        if th.is_grad_enabled():
            raise RuntimeError(
                "Second derivatives through a ReLU MLP of sb3_mtte need the layer-by-layer graph: run the forward "
                "and backward passes within `with sb3_mtte.common.relu_mlp.fused_relu_mlp(False):`."
            )
        saved, n, stacked = ctx.saved_tensors, ctx.n_layers, ctx.stacked
        layer_inputs, weights = saved[:n], saved[n : 2 * n]
        grad = _threshold_backward(grad_output, saved[2 * n], 0) if ctx.relu_last else grad_output
        param_grads: list[th.Tensor | None] = []
        for index in reversed(range(n)):
            x, weight = layer_inputs[index], weights[index]
            needs_weight, needs_bias = ctx.needs_input_grad[3 + 2 * index : 5 + 2 * index]
            param_grads[:0] = [
                _weight_grad(x, grad, stacked) if needs_weight else None,
                _bias_grad(grad, stacked) if needs_bias else None,
            ]
            if index == 0 and not ctx.needs_input_grad[0]:
                return None, None, None, *param_grads
            grad_x = th.matmul(grad, weight.transpose(-1, -2) if stacked else weight)
            if index > 0:  # x is a ReLU output: x > 0 exactly where the pre-activation was
                grad_x = (
                    _threshold_backward.grad_input(grad_x, x, 0, grad_input=grad_x)
                    if not _is_vmapped(grad_x)
                    else _threshold_backward(grad_x, x, 0)
                )
            grad = grad_x
        return grad, None, None, *param_grads


def relu_mlp(
    x: th.Tensor, weights: list[th.Tensor], biases: list[th.Tensor], stacked: bool, relu_last: bool
) -> th.Tensor:
    """Affine layers with a ReLU after each but the last (and after the last if ``relu_last``), as one node.

    :param x: ``(E, B, in)`` if ``stacked``, else ``(..., in)``.
    :param weights: ``(E, in, out)`` per layer if ``stacked``, else ``nn.Linear``'s ``(out, in)``.
    :param biases: ``(E, 1, out)`` per layer if ``stacked``, else ``(out,)``.
    :param stacked: E independent networks (an ensemble) or one.
    :param relu_last: apply the ReLU after the last layer too.
    :return: the output, ``(E, B, out)`` or ``(..., out)``.
    """
    params = [p for pair in zip(weights, biases, strict=True) for p in pair]
    return _ReLUMLP.apply(x, stacked, relu_last, *params)
