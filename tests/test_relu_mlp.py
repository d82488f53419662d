"""The one-node ReLU MLP computes what the layer-by-layer graph computes: values and every gradient."""

import configparser
import re
from importlib.metadata import requires
from pathlib import Path

import pytest
import torch as th
from torch import nn
from packaging.requirements import Requirement
from torch.func import grad, vmap

from sb3_mtte.common.ensemble import EnsembleMLP, mlp
from sb3_mtte.common import relu_mlp
from sb3_mtte.common.relu_mlp import fused_relu_mlp


def loop_forward(weights, biases, x, stacked: bool, relu_last: bool) -> th.Tensor:
    """Layer by layer, member by member for an ensemble, with plain matmuls."""
    if stacked:
        return th.stack(
            [
                loop_forward([w[e] for w in weights], [b[e, 0] for b in biases], x[e], False, relu_last)
                for e in range(x.shape[0])
            ]
        )
    h = x
    for index, (w, b) in enumerate(zip(weights, biases, strict=True)):
        h = h @ w.t() + b
        if relu_last or index < len(weights) - 1:
            h = th.where(h > 0, h, th.zeros_like(h))
    return h


def params_of(net: nn.Module, stacked: bool) -> tuple[list[th.Tensor], list[th.Tensor]]:
    if stacked:
        return [layer.weight.transpose(1, 2) for layer in net.layers], [layer.bias for layer in net.layers]
    linears = [m for m in net if isinstance(m, nn.Linear)]
    return [layer.weight for layer in linears], [layer.bias for layer in linears]


CASES = {  # name: (network, input shape, stacked, relu_last)
    "ensemble": (lambda: EnsembleMLP(3, 5, [7, 6], 2), (3, 4, 5), True, False),
    "mlp 2-D": (lambda: mlp(5, [7, 6], 2, nn.ReLU), (4, 5), False, False),
    "mlp task-major 3-D": (lambda: mlp(5, [7, 6], 2, nn.ReLU), (2, 4, 5), False, False),
    "trunk ending in a ReLU": (lambda: mlp(5, [7, 6], 0, nn.ReLU), (4, 5), False, True),
    "one layer": (lambda: mlp(5, [], 2, nn.ReLU), (4, 5), False, False),
}


@pytest.mark.parametrize("case", list(CASES))
def test_values_and_gradients_equal_the_layer_by_layer_loop(case):
    make, shape, stacked, relu_last = CASES[case]
    th.manual_seed(0)
    net = make().double()
    x = th.randn(*shape, dtype=th.double, requires_grad=True)
    out = net(x)
    assert out.grad_fn is not None and "ReLUMLP" in type(out.grad_fn).__name__  # the fused node ran
    cotangent = th.randn_like(out)
    kept = cotangent.clone()
    got = th.autograd.grad(out, [x, *net.parameters()], cotangent)
    assert th.equal(cotangent, kept)  # the caller's gradient is read, never written

    weights, biases = params_of(net, stacked)
    expected_out = loop_forward(weights, biases, x, stacked, relu_last)
    expected = th.autograd.grad(expected_out, [x, *net.parameters()], cotangent)
    th.testing.assert_close(out, expected_out, rtol=1e-12, atol=1e-12)
    for g, e in zip(got, expected, strict=True):
        th.testing.assert_close(g, e, rtol=1e-12, atol=1e-12)


def test_frozen_network_gives_only_the_input_gradient():
    """The actor loss differentiates Q(s, pi(s)) w.r.t. the action alone: no weight gradient is formed."""
    th.manual_seed(1)
    net = EnsembleMLP(2, 4, [8, 8], 1).double().requires_grad_(False)
    x = th.randn(2, 5, 4, dtype=th.double, requires_grad=True)
    (got,) = th.autograd.grad(net(x).sum(), x)
    weights, biases = params_of(net, True)
    (expected,) = th.autograd.grad(loop_forward(weights, biases, x, True, False).sum(), x)
    th.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)
    assert all(p.grad is None for p in net.parameters())


def test_parameter_gradients_when_the_input_needs_none():
    th.manual_seed(2)
    net = mlp(4, [8, 8], 1, nn.ReLU).double()
    x = th.randn(6, 4, dtype=th.double)
    net(x).sum().backward()
    got = [p.grad.clone() for p in net.parameters()]
    expected = th.autograd.grad(loop_forward(*params_of(net, False), x, False, False).sum(), list(net.parameters()))
    for g, e in zip(got, expected, strict=True):
        th.testing.assert_close(g, e, rtol=1e-12, atol=1e-12)


def test_output_used_twice_gets_the_summed_gradient():
    """Gradients that reach the node through a pass-through op (an add) are not corrupted by the in-place mask."""
    th.manual_seed(4)
    net = mlp(3, [5, 5], 0, nn.ReLU).double()
    x = th.randn(7, 3, dtype=th.double, requires_grad=True)
    y = net(x)
    got = th.autograd.grad((y + y * 2).sum() + y.pow(2).sum(), [x, *net.parameters()])
    with fused_relu_mlp(False):
        y = net(x)
        assert y.grad_fn is not None and "ReLUMLP" not in type(y.grad_fn).__name__
        expected = th.autograd.grad((y + y * 2).sum() + y.pow(2).sum(), [x, *net.parameters()])
    for g, e in zip(got, expected, strict=True):
        th.testing.assert_close(g, e, rtol=1e-12, atol=1e-12)


def test_batched_vector_jacobian_products():
    """``autograd.grad(..., is_grads_batched=True)`` (used to form per-task gradients) vmaps the backward pass."""
    th.manual_seed(5)
    net = EnsembleMLP(3, 5, [7, 6], 2).double()
    x = th.randn(3, 4, 5, dtype=th.double)
    eye = th.eye(3, dtype=th.double)
    got = th.autograd.grad(net(x).sum((1, 2)), list(net.parameters()), eye, is_grads_batched=True)
    weights, biases = params_of(net, True)
    rows = loop_forward(weights, biases, x, True, False).sum((1, 2))
    for e in range(3):
        expected = th.autograd.grad(rows[e], list(net.parameters()), retain_graph=True)
        for g, ex in zip(got, expected, strict=True):
            th.testing.assert_close(g[e], ex, rtol=1e-12, atol=1e-12)


def test_torch_func_transforms_take_the_layer_by_layer_graph():
    th.manual_seed(6)
    net = mlp(4, [6], 1, nn.ReLU).double()
    params = dict(net.named_parameters())
    xs = th.randn(3, 2, 4, dtype=th.double)
    per_row = vmap(grad(lambda p, x: th.func.functional_call(net, p, (x,)).sum()), in_dims=(None, 0))(params, xs)
    for i in range(3):
        output = loop_forward(*params_of(net, False), xs[i], False, False).sum()
        expected = th.autograd.grad(output, list(params.values()))
        for name, e in zip(params, expected, strict=True):
            th.testing.assert_close(per_row[name][i], e, rtol=1e-12, atol=1e-12)


def test_second_derivatives_raise_a_clear_error_and_work_layer_by_layer():
    th.manual_seed(7)
    net = mlp(3, [5], 1, nn.ReLU).double()
    x = th.randn(4, 3, dtype=th.double, requires_grad=True)
    with pytest.raises(RuntimeError, match="fused_relu_mlp\\(False\\)"):
        th.autograd.grad(net(x).sum(), x, create_graph=True)
    with fused_relu_mlp(False):
        (g,) = th.autograd.grad(net(x).pow(3).sum(), x, create_graph=True)
        g.sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert "ReLUMLP" in type(net(x).grad_fn).__name__  # the block restored the default


def test_autocast_takes_the_layer_by_layer_graph():
    net = mlp(3, [5], 1, nn.ReLU)
    with th.autocast("cpu", dtype=th.bfloat16):
        out = net(th.randn(2, 3))
    assert "ReLUMLP" not in type(out.grad_fn).__name__ and out.dtype == th.bfloat16
    out.float().sum().backward()
    assert all(p.grad is not None for p in net.parameters())


def test_other_activations_keep_the_layer_by_layer_graph():
    net = mlp(3, [5], 1, nn.Tanh)
    assert "ReLUMLP" not in type(net(th.randn(2, 3)).grad_fn).__name__
    ensemble = EnsembleMLP(2, 3, [5], 1, nn.Tanh)
    assert "ReLUMLP" not in type(ensemble(th.randn(2, 4, 3)).grad_fn).__name__


@pytest.mark.parametrize("missing", ["_are_functorch_transforms_active", "_dispatch_keys"])
@pytest.mark.parametrize("case", ["ensemble", "mlp 2-D"])
def test_a_pytorch_without_the_private_functions_takes_the_layer_by_layer_graph(monkeypatch, missing, case):
    """If a PyTorch release renames either private function, every network still runs (layer by layer) with the
    same values and gradients, and torch.func transforms keep working."""
    make, shape, stacked, _ = CASES[case]
    th.manual_seed(8)
    net = make().double()
    x = th.randn(*shape, dtype=th.double)
    expected = net(x)
    expected_grads = th.autograd.grad(expected.pow(2).sum(), list(net.parameters()))
    with fused_relu_mlp(False):
        plain = net(x)
        plain_grads = th.autograd.grad(plain.pow(2).sum(), list(net.parameters()))
    monkeypatch.delattr(th._C, missing)
    out = net(x)
    assert "ReLUMLP" not in type(out.grad_fn).__name__
    th.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)
    assert th.equal(out, plain)  # exactly the plain path
    got_grads = th.autograd.grad(out.pow(2).sum(), list(net.parameters()))
    for g, e, p in zip(got_grads, expected_grads, plain_grads, strict=True):
        th.testing.assert_close(g, e, rtol=1e-12, atol=1e-12)
        assert th.equal(g, p)
    if not stacked:  # a transform: gradients per row
        params = dict(net.named_parameters())
        per_row = vmap(grad(lambda p, row: th.func.functional_call(net, p, (row,)).sum()), in_dims=(None, 0))(
            params, x.unsqueeze(1)
        )
        assert all(v.shape[0] == x.shape[0] for v in per_row.values())


@pytest.mark.parametrize("version", ["2.12.1", "2.14.0", "3.0.0", "2.14.0a0+git1234", "unknown"])
@pytest.mark.parametrize("case", ["ensemble", "mlp 2-D"])
def test_an_untested_pytorch_release_takes_the_layer_by_layer_graph(monkeypatch, version, case):
    make, shape, _, _ = CASES[case]
    th.manual_seed(9)
    net = make().double()
    x = th.randn(*shape, dtype=th.double, requires_grad=True)
    with fused_relu_mlp(False):
        plain = net(x)
    monkeypatch.setattr(th, "__version__", version)
    out = net(x)
    assert "ReLUMLP" not in type(out.grad_fn).__name__
    assert th.equal(out, plain)


@pytest.mark.parametrize("version", ["2.13.0", "2.13.1+cu121", "2.13.0+cpu"])
def test_a_tested_pytorch_release_takes_the_fused_node(monkeypatch, version):
    monkeypatch.setattr(th, "__version__", version)
    out = mlp(3, [5], 1, nn.ReLU)(th.randn(2, 3))
    assert "ReLUMLP" in type(out.grad_fn).__name__


def test_setup_cfg_requires_what_sb3_requires_and_the_pinned_test_release_is_a_tested_one():
    """A user's PyTorch 2.8 to 2.x is kept (no downgrade); CI's torch==2.13.0 is a release the fused node takes."""
    root = Path(__file__).resolve().parents[1]
    config = configparser.ConfigParser(inline_comment_prefixes=("#",))
    config.read(root / "setup.cfg")
    ours = [Requirement(line) for line in config["options"]["install_requires"].splitlines() if line.strip()]
    sb3 = [Requirement(line) for line in requires("stable-baselines3") or []]
    assert [r.specifier for r in ours if r.name == "torch"] == [r.specifier for r in sb3 if r.name == "torch"]
    pinned = re.search(r"torch==([\d.]+)", (root / ".ci" / "run").read_text())
    assert pinned is not None and relu_mlp.tested_release(pinned[1])
    assert relu_mlp.tested_release(th.__version__)


def test_an_untested_release_trains_as_the_layer_by_layer_graph(monkeypatch):
    """A whole short run under a spoofed PyTorch 2.15 gives the parameters of the layer-by-layer run."""
    from sb3_mtte import MTSAC, make_mt_env

    def train() -> dict[str, th.Tensor]:
        model = MTSAC(
            "MlpPolicy",
            make_mt_env("toy-conflict", seed=0),
            policy_kwargs={"net_arch": [16, 16]},
            learning_starts=40,
            batch_size=8,
            seed=0,
            device="cpu",
        )
        model.learn(120)
        return model.policy.state_dict()

    with fused_relu_mlp(False):
        plain = train()
    assert relu_mlp.fused_relu_mlp_applies(th.zeros(2, 3), stacked=False)
    monkeypatch.setattr(th, "__version__", "2.15.0")
    assert not relu_mlp.fused_relu_mlp_applies(th.zeros(2, 3), stacked=False)
    spoofed = train()
    assert all(th.equal(spoofed[k], plain[k]) for k in plain)
