"""Each batched ensemble equals a loop over separate networks holding the same weights."""

import pytest
import torch as th
from torch import nn

from sb3_mtte.common.critics import MultiTaskCritic
from sb3_mtte.common.ensemble import EnsembleLinear, EnsembleMLP
from sb3_mtte.mtsac.policies import IndependentActor, MultiHeadActor, SharedActor, SoftModularActor


def member_as_linear(layer: EnsembleLinear, e: int) -> nn.Linear:
    linear = nn.Linear(layer.in_features, layer.out_features)
    with th.no_grad():
        linear.weight.copy_(layer.weight[e].T)
        linear.bias.copy_(layer.bias[e, 0])
    return linear


def member_as_mlp(ensemble: EnsembleMLP, e: int) -> nn.Sequential:
    modules = []
    for layer in ensemble.layers:
        modules += [member_as_linear(layer, e), nn.ReLU()]
    return nn.Sequential(*modules[:-1])


def test_ensemble_linear_equals_loop_forward_and_backward():
    th.manual_seed(0)
    layer = EnsembleLinear(5, 7, 3)
    x = th.randn(5, 11, 7)
    out = layer(x)
    loops = [member_as_linear(layer, e) for e in range(5)]
    expected = th.stack([loops[e](x[e]) for e in range(5)])
    assert th.allclose(out, expected, atol=1e-6)
    out.pow(2).sum().backward()
    for e in range(5):
        loops[e](x[e]).pow(2).sum().backward()
        assert th.allclose(layer.weight.grad[e], loops[e].weight.grad.T, atol=1e-5)
        assert th.allclose(layer.bias.grad[e, 0], loops[e].bias.grad, atol=1e-5)


def test_ensemble_mlp_equals_loop_and_gather_path():
    th.manual_seed(1)
    net = EnsembleMLP(4, 6, [16, 16], 2)
    x = th.randn(4, 9, 6)
    expected = th.stack([member_as_mlp(net, e)(x[e]) for e in range(4)])
    assert th.allclose(net(x), expected, atol=1e-5)
    members = th.tensor([3, 0, 0, 2, 1, 3])
    rows = th.randn(6, 6)
    gathered = net.forward_gather(rows, members)
    expected_rows = th.stack([member_as_mlp(net, int(m))(r) for r, m in zip(rows, members, strict=True)])
    assert th.allclose(gathered, expected_rows, atol=1e-5)


def test_ensemble_init_matches_nn_linear_scale():
    layer = EnsembleLinear(3, 400, 400)
    bound = 1 / 400**0.5
    assert layer.weight.abs().max() <= bound and layer.weight.abs().max() > 0.9 * bound


@pytest.mark.parametrize("critic_arch", ["per_task", "shared"])
def test_multitask_critic_equals_loop_over_tasks(critic_arch):
    th.manual_seed(2)
    n, state_dim, action_dim, length = 3, 5, 2, 4
    critic = MultiTaskCritic(state_dim, action_dim, n, [8, 8], critic_arch=critic_arch)
    obs = th.cat([th.randn(n * length, state_dim), th.eye(n).repeat_interleave(length, 0)], dim=1)
    actions = th.randn(n * length, action_dim)
    q = critic(obs.view(n, length, -1), actions.view(n, length, -1))
    assert q.shape == (2, n, length)
    for i in range(n):
        rows = slice(i * length, (i + 1) * length)
        for j in range(2):
            if critic_arch == "per_task":
                net, x = member_as_mlp(critic.q_net, 2 * i + j), th.cat([obs[rows, :state_dim], actions[rows]], 1)
            else:
                net, x = member_as_mlp(critic.q_net, j), th.cat([obs[rows], actions[rows]], 1)
            assert th.allclose(q[j, i], net(x).squeeze(-1), atol=1e-5)


@pytest.mark.parametrize("actor_class", [SharedActor, MultiHeadActor, IndependentActor, SoftModularActor])
def test_task_major_path_equals_gather_path(actor_class):
    """Training (task-major bmm) and acting (per-row gather) compute the same distribution."""
    th.manual_seed(3)
    n, state_dim, length = 4, 6, 5
    actor = actor_class(state_dim, 2, n, [16, 16], nn.ReLU)
    task_ids = th.arange(n).repeat_interleave(length)
    obs = th.cat([th.randn(n * length, state_dim), th.eye(n)[task_ids]], dim=1)
    batched = actor.dist_params(obs.view(n, length, -1)).view(n * length, -1)
    permutation = th.randperm(n * length)
    gathered = actor.dist_params(obs[permutation], task_ids[permutation])
    assert th.allclose(batched[permutation], gathered, atol=1e-5)
    # Acting reads the tasks from the one-hot: its deterministic action is tanh of the task-major mean.
    assert th.allclose(actor.act(obs[permutation], deterministic=True), th.tanh(batched[permutation, :2]), atol=1e-5)


def test_independent_actor_equals_separate_networks():
    th.manual_seed(4)
    n, state_dim, length = 3, 5, 4
    actor = IndependentActor(state_dim, 2, n, [8, 8], nn.ReLU)
    obs = th.cat([th.randn(n * length, state_dim), th.eye(n).repeat_interleave(length, 0)], dim=1)
    out = actor.dist_params(obs.view(n, length, -1))
    for i in range(n):
        expected = member_as_mlp(actor.nets, i)(obs[i * length : (i + 1) * length, :state_dim])
        assert th.allclose(out[i], expected, atol=1e-5)


def test_multi_head_actor_equals_trunk_plus_separate_heads():
    th.manual_seed(5)
    n, state_dim, length = 3, 5, 4
    actor = MultiHeadActor(state_dim, 2, n, [8, 8], nn.ReLU)
    obs = th.cat([th.randn(n * length, state_dim), th.eye(n).repeat_interleave(length, 0)], dim=1)
    out = actor.dist_params(obs.view(n, length, -1))
    for i in range(n):
        latent = actor.trunk(obs[i * length : (i + 1) * length])
        assert th.allclose(out[i], member_as_linear(actor.heads, i)(latent), atol=1e-5)


def test_soft_modular_routing_is_a_convex_mix_of_modules():
    """A plain per-sample loop over modules reproduces the batched soft-modular forward."""
    th.manual_seed(6)
    n, state_dim, m = 3, 5, 3
    actor = SoftModularActor(state_dim, 2, n, [8, 8], nn.ReLU, n_layers=3, n_modules=m, module_size=4)
    obs = th.cat([th.randn(n, state_dim), th.eye(n)], dim=1)
    out = actor.dist_params(obs)
    for b in range(n):
        state, one_hot = obs[b, :state_dim], obs[b, state_dim:]
        features = actor.state_encoder(state)
        context = features * actor.task_encoder(one_hot)
        logits = actor.route_down[0](th.relu(context))
        outs = [th.relu(member_as_linear(actor.modules_per_layer[0], i)(features)) for i in range(m)]
        for layer in range(1, 3):
            weights = logits.view(m, m).softmax(-1)
            mixed = [sum(weights[j, i] * outs[i] for i in range(m)) for j in range(m)]
            outs = [th.relu(member_as_linear(actor.modules_per_layer[layer], j)(mixed[j])) for j in range(m)]
            if layer < 2:
                logits = actor.route_down[layer](th.relu(actor.route_up[layer - 1](logits) * context))
        assert th.allclose(out[b], actor.head(sum(outs)), atol=1e-5)
