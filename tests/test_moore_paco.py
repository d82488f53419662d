"""MOORE and PaCo: each defining property against a plain loop, the reset of collapsed tasks, save/load/resume and
bad input."""

import numpy as np
import pytest
import torch as th
from test_mtsac import all_params

from sb3_mtte import MTSAC, make_mt_env
from sb3_mtte.common.critics import MultiTaskCritic
from sb3_mtte.experiments.results.statistics import Estimate
from sb3_mtte.experiments.results.tables import BenchmarkStatistics, table1
from sb3_mtte.experiments.variants import paper_sources, paper_table1
from sb3_mtte.mtsac.moore import MooreNetwork, gram_schmidt
from sb3_mtte.mtsac.paco import PaCoNetwork
from sb3_mtte.mtsac.task_conditioned import NetworkShape

SMALL = {
    "MOOREPolicy": {"net_arch": [16, 16], "n_experts": 3},
    "PaCoPolicy": {"net_arch": [16, 16], "n_parameter_sets": 3},
}


def small_model(policy: str, seed: int = 0, learning_starts: int = 100, **policy_kwargs) -> MTSAC:
    env = make_mt_env("toy-conflict", seed=seed)
    kwargs = {**SMALL[policy], **policy_kwargs}
    return MTSAC(
        policy, env, learning_starts=learning_starts, batch_size=16, seed=seed, device="cpu", policy_kwargs=kwargs
    )


# ----------------------------------------------------------------------------------- plain-loop references
def loop_gram_schmidt(vectors: list[th.Tensor]) -> list[th.Tensor]:
    """Classical Gram-Schmidt of a list of 1-D vectors, one dot product at a time."""
    basis = []
    for v in vectors:
        w = v.clone()
        for u in basis:
            w = w - (v @ u) * u
        basis.append(w / (w.norm() + 1e-8))
    return basis


def loop_expert(net: MooreNetwork, copy: int, expert: int, x: th.Tensor) -> th.Tensor:
    """Expert ``expert`` of copy ``copy`` applied to one input row, layer by layer."""
    member = copy * net.n_experts + expert
    layers = net.experts.layers
    for index, layer in enumerate(layers):
        x = x @ layer.weight[member] + layer.bias[member, 0]
        if index < len(layers) - 1:
            x = th.relu(x)
    return x


def loop_moore(net: MooreNetwork, copy: int, task: int, x: th.Tensor) -> th.Tensor:
    """MOORE for one row of one task: experts, Gram-Schmidt, tanh(sum_j w_j u_j), the task's head."""
    basis = loop_gram_schmidt([loop_expert(net, copy, j, x) for j in range(net.n_experts)])
    feature = th.tanh(sum(net.task_weights[copy, task, j] * basis[j] for j in range(net.n_experts)))
    head = copy * net.n_tasks + task
    return feature @ net.heads.weight[head] + net.heads.bias[head, 0]


def loop_task_parameters(net: PaCoNetwork, copy: int, task: int) -> list[tuple[th.Tensor, th.Tensor]]:
    """theta_tau = sum_k w_tau[k] phi_k for every layer, one set at a time."""
    w = net.task_weights[copy, task]
    return [
        (
            sum(w[k] * weight[copy, k] for k in range(net.n_parameter_sets)),
            sum(w[k] * bias[copy, k, 0] for k in range(net.n_parameter_sets)),
        )
        for weight, bias in zip(net.weights, net.biases, strict=True)
    ]


def loop_paco(net: PaCoNetwork, copy: int, task: int, x: th.Tensor) -> th.Tensor:
    layers = loop_task_parameters(net, copy, task)
    for index, (weight, bias) in enumerate(layers):
        x = x @ weight + bias
        if index < len(layers) - 1:
            x = th.relu(x)
    return x


# ------------------------------------------------------------------------------------------------- MOORE
@th.no_grad()
def test_gram_schmidt_gives_orthonormal_vectors_equal_to_a_plain_loop():
    th.manual_seed(0)
    vectors = th.randn(2, 5, 4, 7, dtype=th.float64)
    basis = gram_schmidt(vectors)
    gram = basis @ basis.transpose(-1, -2)
    assert th.allclose(gram, th.eye(4, dtype=th.float64).expand_as(gram), atol=1e-5)
    for a in range(2):
        for b in range(5):
            expected = th.stack(loop_gram_schmidt(list(vectors[a, b])))
            assert th.allclose(basis[a, b], expected, atol=1e-10)


@th.no_grad()
def test_moore_experts_are_orthonormal_per_state_and_equal_loop_gram_schmidt():
    th.manual_seed(1)
    net = MooreNetwork(NetworkShape(2, 5, 3, [16, 8], 2, th.nn.ReLU), n_experts=4).double()
    x = th.randn(2, 6, 5, dtype=th.float64)
    basis = net.orthonormal_experts(x)
    gram = basis @ basis.transpose(-1, -2)
    assert th.allclose(gram, th.eye(4, dtype=th.float64).expand_as(gram), atol=1e-5)
    for c in range(2):
        for row in range(6):
            expected = loop_gram_schmidt([loop_expert(net, c, j, x[c, row]) for j in range(4)])
            assert th.allclose(basis[c, row], th.stack(expected), atol=1e-10)


@th.no_grad()
def test_moore_task_combination_and_heads_equal_a_loop_over_tasks():
    th.manual_seed(2)
    net = MooreNetwork(NetworkShape(2, 5, 3, [16, 8], 2, th.nn.ReLU), n_experts=4).double()
    x = th.randn(2, 3, 4, 5, dtype=th.float64)
    out = net(x)
    for c in range(2):
        for task in range(3):
            expected = th.stack([loop_moore(net, c, task, row) for row in x[c, task]])
            assert th.allclose(out[c, task], expected, atol=1e-10)
    rows, task_ids = x[:, :, 0].clone(), th.tensor([2, 0, 1])
    gathered = net.forward_gather(rows, task_ids)
    for c in range(2):
        for b, task in enumerate(task_ids.tolist()):
            assert th.allclose(gathered[c, b], loop_moore(net, c, task, rows[c, b]), atol=1e-10)


def test_moore_gradients_equal_those_of_the_plain_loop():
    """The forward never builds the basis (it combines the raw expert outputs with w^T T); its gradients must still
    be those of Gram-Schmidt followed by the task combination."""
    th.manual_seed(3)
    net = MooreNetwork(NetworkShape(2, 5, 3, [16, 8], 2, th.nn.ReLU), n_experts=4).double()
    x = th.randn(2, 3, 4, 5, dtype=th.float64)
    params = list(net.parameters())
    fast = th.autograd.grad(net(x).square().sum(), params)
    loop = sum(
        loop_moore(net, c, task, row).square().sum() for c in range(2) for task in range(3) for row in x[c, task]
    )
    for got, expected in zip(fast, th.autograd.grad(loop, params), strict=True):
        assert th.allclose(got, expected, atol=1e-10)


# -------------------------------------------------------------------------------------------------- PaCo
def test_paco_task_parameters_are_the_weighted_sum_of_the_shared_sets():
    th.manual_seed(3)
    net = PaCoNetwork(NetworkShape(2, 5, 3, [16, 8], 2, th.nn.ReLU), n_parameter_sets=4).double()
    for layer, (weight, bias) in enumerate(net.task_parameters()):
        assert weight.shape == (2, 3, *net.weights[layer].shape[2:])
        for c in range(2):
            for task in range(3):
                expected_w, expected_b = loop_task_parameters(net, c, task)[layer]
                assert th.allclose(weight[c, task], expected_w, atol=1e-12)
                assert th.allclose(bias[c, task, 0], expected_b, atol=1e-12)


def test_paco_forward_equals_a_loop_over_tasks_with_their_parameters():
    th.manual_seed(4)
    net = PaCoNetwork(NetworkShape(2, 5, 3, [16, 8], 2, th.nn.ReLU), n_parameter_sets=4).double()
    x = th.randn(2, 3, 4, 5, dtype=th.float64)
    out = net(x)
    for c in range(2):
        for task in range(3):
            assert th.allclose(out[c, task], loop_paco(net, c, task, x[c, task]), atol=1e-10)
    rows, task_ids = x[:, :, 0].clone(), th.tensor([1, 1, 0])
    gathered = net.forward_gather(rows, task_ids)
    for c in range(2):
        for b, task in enumerate(task_ids.tolist()):
            assert th.allclose(gathered[c, b], loop_paco(net, c, task, rows[c, b]), atol=1e-10)


def test_paco_resets_exactly_the_tasks_above_the_threshold():
    model = small_model("PaCoPolicy", task_loss_threshold=10.0)
    policy, hook = model.policy, model.update_hook
    before = all_params(model)
    kept = hook.loss_mask(th.tensor([3.0, 12.0, 10.0, 1e6]))
    assert kept.tolist() == [1.0, 0.0, 1.0, 0.0]  # a loss equal to the threshold is kept
    hook.after_update()
    collapsed, after = th.tensor([False, True, False, True]), all_params(model)
    assert policy.collapse_counts.tolist() == [0, 1, 0, 1]
    for key, value in before.items():
        if key == "collapse_counts":
            continue
        if not key.endswith("task_weights"):
            assert th.equal(value, after[key]), key  # the shared sets (and everything else) are untouched
            continue
        assert th.equal(value[:, ~collapsed], after[key][:, ~collapsed]), key
        assert not th.isclose(value[:, collapsed], after[key][:, collapsed]).all(), key
    assert th.equal(
        after["critic_target.q_net.task_weights"],
        before["critic_target.q_net.task_weights"].where(~collapsed[None, :, None], after["critic.q_net.task_weights"]),
    )
    # each reset w is one convex combination of the kept tasks' w, the same in the actor and every critic
    old = th.cat([before["actor.net.task_weights"], before["critic.q_net.task_weights"]]).double()
    new = th.cat([after["actor.net.task_weights"], after["critic.q_net.task_weights"]]).double()
    for task in th.nonzero(collapsed).flatten().tolist():
        system = old[:, ~collapsed].permute(0, 2, 1).reshape(-1, int((~collapsed).sum()))
        mix = th.linalg.lstsq(system, new[:, task].reshape(-1, 1)).solution.squeeze(1)
        assert th.allclose(system @ mix, new[:, task].reshape(-1), atol=1e-5)
        assert (mix >= -1e-5).all() and abs(float(mix.sum()) - 1) < 1e-5
    assert hook.loss_mask(th.tensor([3.0, 2.0, 1.0, 0.0])).tolist() == [1.0] * 4
    hook.after_update()
    assert th.equal(all_params(model)["actor.net.task_weights"], after["actor.net.task_weights"])


def test_paco_update_masks_collapsed_tasks_and_resets_them():
    """Every task above the threshold: the first update (no optimizer momentum yet) moves no shared parameter and
    resets every w; with a threshold no loss reaches, the next update trains and resets nothing."""
    model = small_model("PaCoPolicy", learning_starts=1000)
    model.learn(200)
    assert model._n_updates == 0
    model.policy.task_loss_threshold = 1e-12
    before = all_params(model)
    model.train(1, 16)
    after = all_params(model)
    assert model.policy.collapse_counts.tolist() == [1, 1, 1, 1]
    for key in ("actor.net.weights.0", "critic.q_net.weights.1", "actor.net.biases.2"):
        assert th.equal(before[key], after[key]), key
    assert not th.isclose(before["actor.net.task_weights"], after["actor.net.task_weights"]).any()
    model.policy.task_loss_threshold = 1e12
    model.train(1, 16)
    assert not th.equal(after["actor.net.weights.0"], all_params(model)["actor.net.weights.0"])
    assert model.policy.collapse_counts.tolist() == [1, 1, 1, 1]


class MaskCheckingMTSAC(MTSAC):
    """Checks that each critic and actor step puts into ``.grad`` the gradient of the kept tasks' losses alone."""

    def _checked_step(self, step, optimizer, task_losses, task_weights, reference_weights):
        params = [p for group in optimizer.param_groups for p in group["params"]]
        expected = th.autograd.grad((reference_weights * task_losses).sum(), params, retain_graph=True)
        loss = step(task_losses, task_weights)
        for param, grad in zip(params, expected, strict=True):
            assert th.allclose(param.grad, grad, rtol=1e-5, atol=1e-8)
        self.checked.append(optimizer)
        return loss

    def _critic_step(self, task_losses, task_weights):
        kept = (~self.collapsed).to(task_losses.dtype)
        return self._checked_step(super()._critic_step, self.critic.optimizer, task_losses, task_weights, kept)

    def _actor_step(self, task_losses, task_weights):
        kept = (~self.collapsed).to(task_losses.dtype) / self.n_tasks
        return self._checked_step(super()._actor_step, self.actor.optimizer, task_losses, task_weights, kept)


def test_paco_update_with_one_collapsed_task_trains_the_others_and_resets_that_one():
    """One task of four above the threshold in a real update: the critic and the actor step on the three other
    tasks' losses (the collapsed one contributes nothing, the others everything), and only that task is reset."""
    model = small_model("PaCoPolicy", learning_starts=1000)
    model.learn(200)
    policy, loss_mask = model.policy, model.update_hook.loss_mask

    def threshold_below_the_largest_loss(task_losses: th.Tensor) -> th.Tensor:
        policy.task_loss_threshold = float(task_losses.topk(2).values.mean())
        model.collapsed = task_losses > policy.task_loss_threshold
        return loss_mask(task_losses)

    model.update_hook.loss_mask = threshold_below_the_largest_loss
    model.__class__, model.checked = MaskCheckingMTSAC, []
    before = all_params(model)
    model.train(1, 16)
    assert model.checked == [model.critic.optimizer, model.actor.optimizer]
    assert int(model.collapsed.sum()) == 1
    assert policy.collapse_counts.tolist() == model.collapsed.long().tolist()
    kept = ~model.collapsed
    after = all_params(model)
    for key in ("actor.net.task_weights", "critic.q_net.task_weights"):
        assert not th.isclose(before[key][:, kept], after[key][:, kept]).all(), key  # trained, not reset
        assert not th.isclose(before[key][:, ~kept], after[key][:, ~kept]).any(), key  # reset


# -------------------------------------------------------------------------------------- both, end to end
@pytest.mark.parametrize("policy", ["MOOREPolicy", "PaCoPolicy"])
def test_acting_reads_the_task_of_every_row(policy):
    model = small_model(policy)
    obs = th.as_tensor(make_mt_env("toy-conflict", seed=5).reset())
    order = th.tensor([2, 0, 3, 1, 1])
    gathered = model.actor.dist_params(obs[order], order)
    assert th.allclose(gathered, model.actor.dist_params(obs.unsqueeze(1))[order, 0], atol=1e-6)
    assert th.allclose(model.actor.act(obs[order], True), model.actor.act(obs, True)[order], atol=1e-6)


@pytest.mark.parametrize("policy", ["MOOREPolicy", "PaCoPolicy"])
def test_save_load_resume_restores_everything(policy, tmp_path):
    model = small_model(policy)
    model.learn(300)
    if policy == "PaCoPolicy":
        model.policy.reset_task_weights(th.tensor([False, True, False, False]))
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    obs = make_mt_env("toy-conflict", seed=3).reset()
    expected_action = model.predict(obs, deterministic=True)[0]
    model.train(gradient_steps=2, batch_size=16)
    expected = all_params(model)

    resumed = MTSAC.load(tmp_path / "model", env=make_mt_env("toy-conflict", seed=0))
    assert type(resumed.policy).__name__ == policy
    assert resumed.policy.network_kwargs() == model.policy.network_kwargs()
    if policy == "PaCoPolicy":
        assert resumed.policy.collapse_counts.tolist() == [0, 1, 0, 0]
        assert resumed.policy.task_loss_threshold == model.policy.task_loss_threshold
    assert np.array_equal(resumed.predict(obs, deterministic=True)[0], expected_action)
    resumed.load_replay_buffer(tmp_path / "buffer")
    resumed.set_logger(model.logger)
    resumed.train(gradient_steps=2, batch_size=16)
    for key, value in expected.items():
        assert th.equal(value, resumed.policy.state_dict()[key]), key


@pytest.mark.parametrize("policy", ["MOOREPolicy", "PaCoPolicy"])
def test_structured_critic_can_be_switched_off(policy):
    model = small_model(policy, structured_critic=False)
    assert isinstance(model.critic, MultiTaskCritic) and model.critic.per_task
    model.learn(200)
    assert model._n_updates > 0


@pytest.mark.parametrize(
    "policy, kwargs, match",
    [
        ("MOOREPolicy", {"n_experts": 0}, "n_experts"),
        ("MOOREPolicy", {"n_experts": 17}, "n_experts"),
        ("MOOREPolicy", {"net_arch": []}, "hidden layer"),
        ("PaCoPolicy", {"n_parameter_sets": 0}, "n_parameter_sets"),
        ("PaCoPolicy", {"task_loss_threshold": 0.0}, "task_loss_threshold"),
        ("PaCoPolicy", {"critic_arch": "shared"}, "structured_critic"),
    ],
)
def test_bad_input_raises_a_clear_error(policy, kwargs, match):
    with pytest.raises(ValueError, match=match):
        if "critic_arch" in kwargs:
            MTSAC(policy, make_mt_env("toy-conflict"), critic_arch=kwargs["critic_arch"], policy_kwargs=SMALL[policy])
        else:
            small_model(policy, **kwargs)


def test_table1_of_mt10_100k_shows_the_anchor_at_its_budget_beside_sac_mt():
    """MT10-100k's Table 1 gives, in a column of its own and its caption, the published success at 100k env steps
    per task (McLean et al. 2025) beside SAC-MT, and '-' beside the algorithms it has no number of."""
    estimate = Estimate(0.5, 0.4, 0.6)
    scores = {label: np.full((3, 10), 0.5) for label in ("SAC-MT", "Ours")}
    aggregates = {label: {"mean": estimate, "iqm": estimate} for label in scores}
    text = table1("MT10-100k", BenchmarkStatistics(scores, aggregates, None, {}), reps=5)
    assert "Published (%) | At this budget (%) |" in text and "At this budget: McLean et al. 2025" in text
    assert (
        f"| SAC-MT | 3 | 50.0 [40.0, 60.0] | 50.0 [40.0, 60.0] | {paper_table1()['SAC-MT']['MT10']:.1f} | 28-33 |"
        in text
    )
    assert "| Ours | 3 | 50.0 [40.0, 60.0] | 50.0 [40.0, 60.0] |" in text and text.rstrip().endswith("| - |")
    assert "At this budget" not in table1("MT10-cpu", BenchmarkStatistics(scores, aggregates, None, {}), reps=5)


@pytest.mark.parametrize("env_name", ["MT10-cpu", "MT20-cpu"])
def test_table1_shows_every_published_number_and_source_of_the_registry(env_name):
    """Table 1 of a benchmark lists, beside each algorithm with runs, its published number on that benchmark family
    as the registry holds it, and the source of every number that is not the paper's Table 1, once per source."""
    published = paper_table1()
    assert {"MOORE", "PaCo", "PCGrad", "CAGrad"} <= set(paper_sources()) <= set(published)
    scores = {label: np.full((2, 3), 0.5) for label in published}
    estimate = Estimate(0.5, 0.4, 0.6)
    aggregates = {label: {"mean": estimate, "iqm": estimate} for label in scores}
    text = table1(env_name, BenchmarkStatistics(scores, aggregates, None, {}), reps=5)
    family = env_name.split("-")[0]
    for label, values in published.items():
        cell = f"{values[family]:.1f}" if family in values else "-"
        assert f"| {label} | 2 | 50.0 [40.0, 60.0] | 50.0 [40.0, 60.0] | {cell} |" in text, label
    for source in set(paper_sources().values()):
        labels = [label for label, s in paper_sources().items() if s == source and family in published[label]]
        if labels:  # one sentence per source, naming every algorithm whose number it gives
            assert text.count(source) == 1 and f" {' and '.join(labels)}: {source}." in text, source
