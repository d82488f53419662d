"""Networks under K stacked parameter sets (``forward_stacked``) equal a loop over the sets, and actors of other
architectures than linear layers and activations go through the negative-transfer measure mu with the values of
the plain per-task loop."""

from __future__ import annotations

import pytest
import torch as th
from conftest import make_ent_coef, make_rep_batch, make_te_policy
from references import loop_nt_objective, loop_transfer
from torch import nn
from torch.func import functional_call

from sb3_mtte.common.critics import MultiTaskCritic
from sb3_mtte.common.ensemble import MLP
from sb3_mtte.common.policies import MultiTaskActor
from sb3_mtte.mtsacte.objectives import negative_transfer_measure
from sb3_mtte.mtsacte.transfer import TaskObjectives, representation_loss, transfer_matrix

N_TASKS, STEP = 4, 1e-2


class FeatureGain(nn.Module):
    """A module with parameters the package does not know: ``x * gain`` with a learned gain per feature."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.gain = nn.Parameter(0.5 + th.rand(width))

    def forward(self, x: th.Tensor) -> th.Tensor:
        return x * self.gain


class GainActor(MultiTaskActor):
    """An actor with its own layout: a trunk with a :class:`FeatureGain`, a head and a learned output offset."""

    def __init__(self, in_features: int, state_dim: int, action_dim: int, n_tasks: int) -> None:
        super().__init__(state_dim, action_dim, n_tasks)
        self.trunk = nn.Sequential(nn.Linear(in_features, 16), nn.Tanh(), FeatureGain(16))
        self.head = nn.Linear(16, 2 * action_dim)
        self.offset = nn.Parameter(0.1 * th.randn(2 * action_dim))

    def dist_params(self, obs: th.Tensor, task_ids: th.Tensor | None = None) -> th.Tensor:
        return self.head(self.trunk(obs)) + self.offset


def layer_norm_net(policy) -> None:
    """E_phi's actor network with a LayerNorm after its first layer."""
    in_features, out_features = policy.actor.net[0].in_features, policy.actor.net[-1].out_features
    policy.actor.net = MLP(
        nn.Linear(in_features, 16),
        nn.LayerNorm(16),
        nn.ReLU(),
        nn.Linear(16, 16),
        nn.ReLU(),
        nn.Linear(16, out_features),
    )


def gain_actor(policy) -> None:
    in_features = policy.actor.net[0].in_features
    policy.actor = GainActor(in_features, policy.state_dim, policy.action_dim, policy.n_tasks)


ACTORS = {"layer norm in the MLP": layer_norm_net, "custom actor and module": gain_actor}


def policy_with(replace_actor, seed: int):
    policy = make_te_policy(seed=seed, double=False)
    replace_actor(policy)
    return policy.double()


@pytest.mark.parametrize("actor", list(ACTORS))
def test_other_actor_architectures_give_the_plain_loops_transfer_matrix_and_mu(actor):
    policy = policy_with(ACTORS[actor], seed=1)
    batch, ent_coef = make_rep_batch(policy, seed=111), make_ent_coef(N_TASKS)
    before, expected = loop_transfer(policy, batch, ent_coef, STEP)
    expected_mu = [sum(1 for i in range(N_TASKS) if float(expected[k, i]) < 0) for k in range(N_TASKS)]
    assert expected.abs().min() > 1e-4 and expected_mu == [1, 1, 1, 3]  # every sign clear, mu not uniform

    for chunk_size in (None, 1, 3):
        objectives = TaskObjectives(policy, batch, ent_coef, chunk_size=chunk_size)
        with th.no_grad():
            z = objectives.embedding(objectives.phi()[0])[0]
        th.testing.assert_close(objectives.all_tasks(objectives.theta(), z), before, rtol=1e-9, atol=1e-10)
        matrix = transfer_matrix(objectives, z, STEP)
        th.testing.assert_close(matrix, expected, rtol=1e-7, atol=1e-10)
        assert negative_transfer_measure(matrix).tolist() == expected_mu


@pytest.mark.parametrize("actor", list(ACTORS))
def test_other_actor_architectures_give_the_plain_loops_negative_transfer_objective(actor):
    policy = policy_with(ACTORS[actor], seed=1)
    batch, ent_coef = make_rep_batch(policy, seed=106), make_ent_coef(N_TASKS)
    objectives = TaskObjectives(policy, batch, ent_coef)
    harmful = [1, 3]
    loss = representation_loss(objectives, *objectives.phi(), th.tensor(harmful), STEP, 1.0, use_vae=False)
    assert float(loss) == pytest.approx(-loop_nt_objective(policy, batch, ent_coef, harmful, STEP), rel=1e-9)


def stacked_params(module: nn.Module, n_sets: int, seed: int) -> dict[str, th.Tensor]:
    gen = th.Generator().manual_seed(seed)
    return {
        name: p.detach() + 0.1 * th.randn(n_sets, *p.shape, generator=gen, dtype=p.dtype)
        for name, p in module.named_parameters()
    }


@pytest.mark.parametrize("shared_rows", [True, False])
def test_mlp_forward_stacked_equals_a_loop_over_the_parameter_sets(shared_rows):
    th.manual_seed(0)
    net = MLP(nn.Linear(5, 7), nn.LayerNorm(7), nn.ReLU(), FeatureGain(7), nn.Linear(7, 3)).double()
    params = stacked_params(net, 3, seed=1)
    x = th.randn(1 if shared_rows else 3, 4, 5, dtype=th.double)
    got = net.forward_stacked(params, x)
    expected = th.stack(
        [functional_call(net, {k: v[s] for k, v in params.items()}, (x[0 if shared_rows else s],)) for s in range(3)]
    )
    th.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("actor", list(ACTORS))
def test_actor_forward_stacked_equals_a_loop_over_the_parameter_sets(actor):
    policy = policy_with(ACTORS[actor], seed=2)
    params = stacked_params(policy.actor, 3, seed=3)
    in_features = policy.state_dim + policy.z_dim
    obs, noise = th.randn(N_TASKS, 5, in_features, dtype=th.double), th.randn(N_TASKS, 5, 2, dtype=th.double)
    actions, log_probs = policy.actor.forward_stacked(params, obs, noise)
    for s in range(3):
        action, log_prob = functional_call(policy.actor, {k: v[s] for k, v in params.items()}, (obs, noise))
        th.testing.assert_close(actions[s], action, rtol=1e-12, atol=1e-12)
        th.testing.assert_close(log_probs[s], log_prob, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("critic_arch", ["per_task", "shared"])
def test_critic_forward_stacked_with_its_task_parameters_equals_forward(critic_arch):
    th.manual_seed(4)
    critic = MultiTaskCritic(3, 2, N_TASKS, [8, 8], critic_arch=critic_arch, n_critics=2).double()
    obs = th.cat([th.randn(N_TASKS, 6, 3), th.eye(N_TASKS)[:, None].expand(N_TASKS, 6, N_TASKS)], -1).double()
    actions = th.randn(N_TASKS, 6, 2, dtype=th.double)
    task_params = critic.task_parameters()
    expected = critic(obs, actions)  # (n_critics, N, L)
    th.testing.assert_close(critic.forward_stacked(task_params, obs, actions), expected.transpose(0, 1))
    tasks = th.tensor([2, 0])
    subset = critic.forward_stacked({k: v[tasks] for k, v in task_params.items()}, obs[tasks], actions[tasks])
    th.testing.assert_close(subset, expected[:, tasks].transpose(0, 1))
