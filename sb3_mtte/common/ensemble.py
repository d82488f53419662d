"""Batched per-task networks: E independent layers held as stacked weights, applied with one bmm."""

from __future__ import annotations

import math

import torch as th
from torch import nn
from torch.func import functional_call, vmap

from sb3_mtte.common.relu_mlp import fused_relu_mlp_applies, relu_mlp
import itertools


class EnsembleLinear(nn.Module):
    """``n_members`` independent linear layers evaluated with a single batched matmul.

    Weights are stored as ``(E, in, out)`` so the training path is one ``baddbmm`` over a task-major batch
    ``(E, B, in) -> (E, B, out)``. Initialisation matches ``nn.Linear`` member by member.

    :param n_members: number of independent layers E (tasks, or tasks x twin critics).
    :param in_features: input size.
    :param out_features: output size.
    """

    def __init__(self, n_members: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.n_members, self.in_features, self.out_features = n_members, in_features, out_features
        self.weight = nn.Parameter(th.empty(n_members, in_features, out_features))
        self.bias = nn.Parameter(th.empty(n_members, 1, out_features))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        bound = 1.0 / math.sqrt(self.in_features)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: th.Tensor) -> th.Tensor:
        """:param x: ``(E, B, in)``, member e applied to ``x[e]``. :return: ``(E, B, out)``."""
        return th.baddbmm(self.bias, x, self.weight)

    def forward_gather(self, x: th.Tensor, members: th.Tensor) -> th.Tensor:
        """Apply member ``members[b]`` to row ``x[b]`` (any order, any mix).

        :param x: ``(B, in)``.
        :param members: ``(B,)`` long indices.
        :return: ``(B, out)``.
        """
        return th.baddbmm(self.bias[members], x.unsqueeze(1), self.weight[members]).squeeze(1)

    def extra_repr(self) -> str:
        return f"n_members={self.n_members}, in_features={self.in_features}, out_features={self.out_features}"


class EnsembleMLP(nn.Module):
    """``n_members`` independent MLPs (hidden activations between layers, linear output), batched.

    :param n_members: number of independent networks E.
    :param in_features: input size.
    :param hidden_sizes: hidden layer widths.
    :param out_features: output size.
    :param activation_fn: activation between layers.
    """

    def __init__(
        self,
        n_members: int,
        in_features: int,
        hidden_sizes: list[int],
        out_features: int,
        activation_fn: type[nn.Module] = nn.ReLU,
    ) -> None:
        super().__init__()
        sizes = [in_features, *hidden_sizes, out_features]
        self.layers = nn.ModuleList(EnsembleLinear(n_members, a, b) for a, b in itertools.pairwise(sizes))
        self.activation = activation_fn()

    def forward(self, x: th.Tensor) -> th.Tensor:
        """:param x: ``(E, B, in)``. :return: ``(E, B, out)``."""
        if type(self.activation) is nn.ReLU and fused_relu_mlp_applies(x, stacked=True):
            weights, biases = zip(*((layer.weight, layer.bias) for layer in self.layers), strict=True)
            return relu_mlp(x, list(weights), list(biases), stacked=True, relu_last=False)
        for layer in self.layers[:-1]:
            x = self.activation(layer(x))
        return self.layers[-1](x)

    def forward_gather(self, x: th.Tensor, members: th.Tensor) -> th.Tensor:
        """:param x: ``(B, in)``; row b goes through member ``members[b]``. :return: ``(B, out)``."""
        for layer in self.layers[:-1]:
            x = self.activation(layer.forward_gather(x, members))
        return self.layers[-1].forward_gather(x, members)


class MLP(nn.Sequential):
    """``nn.Sequential`` of ``nn.Linear`` layers, each but possibly the last followed by an activation (the
    state-dict keys of ``nn.Sequential``); with ReLU it runs as one node of :func:`relu_mlp`."""

    def forward(self, x: th.Tensor) -> th.Tensor:
        fusable = len(self) > 0 and all(type(module) in (nn.Linear, nn.ReLU) for module in self)
        if fusable and fused_relu_mlp_applies(x, stacked=False):
            linears = [module for module in self if isinstance(module, nn.Linear)]
            weights, biases = [layer.weight for layer in linears], [layer.bias for layer in linears]
            return relu_mlp(x, weights, biases, stacked=False, relu_last=isinstance(self[-1], nn.ReLU))
        return super().forward(x)

    def forward_stacked(self, params: dict[str, th.Tensor], x: th.Tensor) -> th.Tensor:
        """The network under K parameter sets at once: each linear layer one batched matmul over the sets, any
        other module with parameters mapped over them (``vmap``), parameter-free modules applied as they are.

        :param params: ``{"<index>.<name>": (K, ...)}``, named as :meth:`named_parameters`.
        :param x: ``(K, B, in)``, or ``(1, B, in)`` for the same rows under every set.
        :return: ``(K, B, out)``.
        """
        n_sets = next(iter(params.values())).shape[0]
        for index, module in enumerate(self):
            own = {name: params[f"{index}.{name}"] for name, _ in module.named_parameters()}
            if type(module) is nn.Linear and module.bias is not None:
                x = th.baddbmm(own["bias"].unsqueeze(1), x.expand(n_sets, *x.shape[1:]), own["weight"].transpose(1, 2))
            elif own:
                x = vmap(lambda p, h, module=module: functional_call(module, p, (h,)))(
                    own, x.expand(n_sets, *x.shape[1:])
                )
            else:
                x = module(x)
        return x


def mlp(in_features: int, hidden_sizes: list[int], out_features: int, activation_fn: type[nn.Module]) -> MLP:
    """Plain MLP with ``activation_fn`` between layers and a linear output (``out_features < 1``: no output layer)."""
    sizes = [in_features, *hidden_sizes]
    modules: list[nn.Module] = []
    for a, b in itertools.pairwise(sizes):
        modules += [nn.Linear(a, b), activation_fn()]
    if out_features > 0:
        modules.append(nn.Linear(sizes[-1], out_features))
    return MLP(*modules)
