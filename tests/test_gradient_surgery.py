"""PCGrad and CAGrad: the maths against plain loops and brute force, and the update they put into MTSAC."""

import dataclasses
import fnmatch
import itertools

import numpy as np
import pytest
import torch as th
from conftest import ENV, tiny_train

from sb3_mtte import MTSAC, make_mt_env
from sb3_mtte.common.ensemble import EnsembleMLP
from sb3_mtte.common.gradient_surgery import (
    cagrad_coefficients,
    cagrad_dual_objective,
    pcgrad_coefficients,
    pcgrad_orders,
    per_task_gradients,
    per_task_gradients_of_rows,
)
from sb3_mtte.experiments.variants import CAGRAD_C, VARIANTS
from sb3_mtte.experiments.zoo.configs import zoo_hyperparameters
from sb3_mtte.mtsac import task_steps

ZOO_ONLY = {"n_timesteps", "n_envs", "eval_freq", "eval_episodes", "save_freq"}
CONFLICTING_3 = np.array([[1.0, 0.2, 0.0], [-0.8, 1.0, 0.3], [0.1, -1.0, 0.5]])


def loop_pcgrad(grads: list[np.ndarray], orders: np.ndarray) -> list[np.ndarray]:
    """Algorithm 1 of Yu et al. (2020), one task and one other task at a time."""
    projected = []
    for i, g in enumerate(grads):
        g_pc = g.copy()
        for j in orders[i]:
            dot = float(g_pc @ grads[j])
            if dot < 0:
                g_pc = g_pc - dot / float(grads[j] @ grads[j]) * grads[j]
        projected.append(g_pc)
    return projected


def pcgrad_by_gram(grads: np.ndarray, orders: np.ndarray) -> np.ndarray:
    return pcgrad_coefficients(grads @ grads.T, orders) @ grads


# ------------------------------------------------------------------------------------------------------ PCGrad
@pytest.mark.parametrize("grads", [np.array([[1.0, 0.0], [-1.0, 1.0]]), CONFLICTING_3])
def test_pcgrad_equals_the_loop_of_algorithm_1_in_the_same_order(grads):
    generator = th.Generator().manual_seed(0)
    for _ in range(5):
        orders = pcgrad_orders(len(grads), generator)
        np.testing.assert_allclose(pcgrad_by_gram(grads, orders), np.stack(loop_pcgrad(list(grads), orders)))


def test_pcgrad_orders_are_random_permutations_of_the_other_tasks():
    generator = th.Generator().manual_seed(0)
    seen = set()
    for _ in range(50):
        orders = pcgrad_orders(3, generator)
        for i, row in enumerate(orders):
            assert sorted(row.tolist()) == sorted(set(range(3)) - {i})
        seen.add(tuple(orders[0]))
    assert seen == {(1, 2), (2, 1)}


def test_pcgrad_draws_every_task_its_own_order():
    """Algorithm 1 orders the other tasks for every task on its own: with 3 tasks, all 2^3 combinations of the three
    orders occur, equally often. Orders cut from one permutation of all tasks would never give the cyclic ones
    (task 0 takes 1 before 2, task 1 takes 2 before 0, task 2 takes 0 before 1)."""
    generator = th.Generator().manual_seed(0)
    draws = 4000
    counts: dict[tuple, int] = {}
    for _ in range(draws):
        combination = tuple(tuple(row) for row in pcgrad_orders(3, generator).tolist())
        counts[combination] = counts.get(combination, 0) + 1
    assert len(counts) == 8
    assert ((1, 2), (2, 0), (0, 1)) in counts and ((2, 1), (0, 2), (1, 0)) in counts
    for count in counts.values():
        assert abs(count / draws - 1 / 8) < 0.03


def test_pcgrad_order_matters_with_three_conflicting_tasks():
    """Task 0's result depends on the order (which the random order is there for)."""
    first = pcgrad_by_gram(CONFLICTING_3, np.array([[1, 2], [0, 2], [0, 1]]))
    second = pcgrad_by_gram(CONFLICTING_3, np.array([[2, 1], [0, 2], [0, 1]]))
    assert not np.allclose(first[0], second[0])


def test_pcgrad_of_two_conflicting_tasks_by_hand():
    """g1 = (1, 0), g2 = (-1, 1): g1 . g2 = -1, so g1^PC = g1 + g2 / 2 = (0.5, 0.5) and g2^PC = g2 + g1 = (0, 1);
    each is orthogonal to the other task's original gradient."""
    grads = np.array([[1.0, 0.0], [-1.0, 1.0]])
    projected = pcgrad_by_gram(grads, np.array([[1], [0]]))
    np.testing.assert_allclose(projected, [[0.5, 0.5], [0.0, 1.0]])
    assert projected[0] @ grads[1] >= -1e-12 and projected[1] @ grads[0] >= -1e-12


def test_pcgrad_each_projection_leaves_no_conflict_with_the_gradient_it_was_projected_on():
    """After the projection of g_i^PC on task j's original gradient, g_i^PC . g_j >= 0 (Algorithm 1); with random
    gradients, at every step of every task's order."""
    rng = np.random.default_rng(0)
    generator = th.Generator().manual_seed(1)
    for _ in range(20):
        grads = rng.normal(size=(4, 6))
        orders = pcgrad_orders(4, generator)
        for i in range(4):
            for length in range(1, 4):
                g_pc = pcgrad_by_gram(grads, orders[:, :length])[i]
                assert g_pc @ grads[orders[i, length - 1]] >= -1e-10


def test_pcgrad_leaves_agreeing_gradients_unchanged():
    grads = np.array([[1.0, 0.5, 0.0], [0.2, 1.0, 0.1], [0.3, 0.0, 1.0]])
    assert (grads @ grads.T >= 0).all()
    np.testing.assert_array_equal(pcgrad_by_gram(grads, pcgrad_orders(3)), grads)


# ------------------------------------------------------------------------------------------------------ CAGrad
def simplex_grid(n_tasks: int, steps: int) -> np.ndarray:
    points = [p for p in itertools.product(range(steps + 1), repeat=n_tasks - 1) if sum(p) <= steps]
    return np.array([[*p, steps - sum(p)] for p in points], dtype=float) / steps


@pytest.mark.parametrize("grads", [np.array([[1.0, 0.0], [-0.6, 1.0]]), CONFLICTING_3[:, :2], CONFLICTING_3])
@pytest.mark.parametrize("c", [0.2, 0.5, 0.9])
def test_cagrad_solves_its_dual_as_a_grid_search_over_the_simplex(grads, c):
    n_tasks = len(grads)
    gram, weights = grads @ grads.T, np.full(n_tasks, 1.0 / n_tasks)
    coefficients = cagrad_coefficients(gram, weights, c)
    p = (coefficients - weights) / (coefficients - weights).sum()  # the dual solution: d = g0 + lambda g_p
    grid = simplex_grid(n_tasks, 400 if n_tasks == 2 else 200)
    best = min(cagrad_dual_objective(q, gram, weights, c) for q in grid)
    assert cagrad_dual_objective(p, gram, weights, c) <= best + 1e-9
    assert cagrad_dual_objective(p, gram, weights, c) >= best - 1e-3 * np.abs(best) - 1e-6


@pytest.mark.parametrize("grads", [np.array([[1.0, 0.0], [-0.6, 1.0]]), CONFLICTING_3[:, :2]])
@pytest.mark.parametrize("c", [0.2, 0.5, 0.9])
def test_cagrad_direction_maximises_the_worst_improvement_in_the_ball(grads, c):
    """The primal problem in 2-D: d on the ball ||d - g0|| <= c ||g0|| with the largest min_i g_i . d, by a grid over
    the ball; CAGrad's d satisfies the constraint and attains that maximum."""
    n_tasks = len(grads)
    weights = np.full(n_tasks, 1.0 / n_tasks)
    d = cagrad_coefficients(grads @ grads.T, weights, c) @ grads
    g0 = weights @ grads
    radius = c * np.linalg.norm(g0)
    assert np.linalg.norm(d - g0) <= radius * (1 + 1e-9)
    angles = np.linspace(0, 2 * np.pi, 20001)
    radii = np.linspace(0, 1, 41)[:, None]
    ball = g0 + radius * radii[..., None] * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    best = (ball @ grads.T).min(axis=-1).max()
    worst_improvement = (grads @ d).min()
    resolution = 1e-3 * radius * np.linalg.norm(grads, axis=1).max()  # of the grid over the ball
    assert best - 1e-9 <= worst_improvement <= best + resolution


def test_cagrad_of_agreeing_gradients_moves_along_g0_and_of_zero_gradients_is_zero():
    grads = np.array([[1.0, 0.0], [1.0, 0.0]])
    np.testing.assert_allclose(cagrad_coefficients(grads @ grads.T, np.full(2, 0.5), 0.5) @ grads, [1.5, 0.0])
    assert not cagrad_coefficients(np.zeros((2, 2)), np.full(2, 0.5), 0.5).any()


# ------------------------------------------------------------------------------------------- through the model
def small_model(policy: str = "MlpPolicy", **kwargs):
    env = make_mt_env("toy-conflict", seed=0)
    return MTSAC(
        policy,
        env,
        learning_starts=100,
        batch_size=16,
        seed=0,
        device="cpu",
        policy_kwargs={"net_arch": [16, 16]},
        **kwargs,
    )


def test_per_task_gradients_equal_a_loop_of_backward_passes():
    net = th.nn.Sequential(th.nn.Linear(3, 8), th.nn.Tanh(), th.nn.Linear(8, 2))
    x = th.randn(4, 5, 3)
    losses = (net(x) ** 2).mean(dim=(1, 2))
    params = list(net.parameters())
    loop = [th.cat([g.flatten() for g in th.autograd.grad(loss, params, retain_graph=True)]) for loss in losses]
    th.testing.assert_close(per_task_gradients(losses, params), th.stack(loop))


def test_per_task_gradients_of_rows_equal_a_loop_of_backward_passes():
    """One backward pass to the shared network's outputs, then a vmap over tasks: the same as N backward passes,
    with a loss that mixes each task's rows non-linearly and a head after the network (as the actor's tanh-Gaussian
    and critic)."""
    th.manual_seed(0)
    net = th.nn.Sequential(th.nn.Linear(3, 8), th.nn.ReLU(), th.nn.Linear(8, 2)).double()
    x = th.randn(4, 5, 3, dtype=th.float64)
    head = th.randn(4, 1, 2, dtype=th.float64)  # a per-task function of the outputs
    out = net(x)
    losses = (th.tanh(out) * head).sum(-1).logsumexp(-1) + out.pow(2).mean(dim=(1, 2))
    params = list(net.parameters())
    loop = [th.cat([g.flatten() for g in th.autograd.grad(loss, params, retain_graph=True)]) for loss in losses]
    th.testing.assert_close(per_task_gradients_of_rows(net, x, out, losses), th.stack(loop), rtol=1e-12, atol=1e-12)


def test_per_task_gradients_of_rows_of_shared_twins_equal_a_loop_of_backward_passes():
    """A shared twin critic (two ensemble members on the same task-major rows, tasks on axis 1, outputs flattened
    over tasks and rows as the critic returns them): the same as N backward passes."""
    th.manual_seed(1)
    net = EnsembleMLP(2, 3, [8, 8], 1).double()
    x = th.randn(1, 4, 5, 3, dtype=th.float64).expand(2, -1, -1, -1)
    out = net(x.flatten(1, 2))
    q = out.view(2, 4, 5)
    losses = (q.min(dim=0).values.exp() + (q - 1.0).pow(2).sum(0)).mean(-1)
    params = list(net.parameters())
    loop = [th.cat([g.flatten() for g in th.autograd.grad(loss, params, retain_graph=True)]) for loss in losses]
    fast = per_task_gradients_of_rows(net, x, out, losses, task_dim=1)
    th.testing.assert_close(fast, th.stack(loop), rtol=1e-12, atol=1e-12)


def record_combined_steps(model, monkeypatch):
    """Record in ``model.records`` the per-task losses, the parameters and the gradients of every combined step."""
    combined_step = task_steps.combined_step

    def recording_step(optimizer, name, task_losses, task_weights, monitor, combining_hook, module=None):
        params = [p for group in optimizer.param_groups for p in group["params"]]
        loop = [th.autograd.grad(task_losses[i], params, retain_graph=True) for i in range(model.n_tasks)]
        loop = np.stack([th.cat([g.flatten() for g in grads]).double().numpy() for grads in loop])
        rng_state = th.get_rng_state()
        before = [p.detach().clone() for p in params]
        calls = model.__dict__.setdefault("gradient_calls", [])  # filled by the spies of the test that sets them
        calls_before = len(calls)
        result = combined_step(optimizer, name, task_losses, task_weights, monitor, combining_hook, module)
        grad = [p.grad.clone() for p in params]
        weights = task_weights.double().numpy()
        model.records[name] = {
            "loop": loop,
            "w": weights,
            "rng": rng_state,
            "before": before,
            "params": params,
            "grad": grad,
            "gradients_by": calls[calls_before:],
        }
        return result

    monkeypatch.setattr(task_steps, "combined_step", recording_step)


SURGERED = {"actor loss", "critic loss", "entropy coefficient loss"}


def spy(function, calls):
    """``function``, appending its name to ``calls`` at every call."""

    def recorded(*args, **kwargs):
        calls.append(function.__name__)
        return function(*args, **kwargs)

    return recorded


@pytest.mark.parametrize(
    "method, arch, policy",
    [
        ("pcgrad", "per_task", "MlpPolicy"),
        ("cagrad", "per_task", "MlpPolicy"),
        ("pcgrad", "shared", "MlpPolicy"),
        ("cagrad", "shared", "MlpPolicy"),
        ("pcgrad", "per_task", "MultiHeadPolicy"),
    ],
)
def test_the_update_applies_the_surgered_gradient_of_a_plain_loop(method, arch, policy, monkeypatch):
    """The gradient in ``.grad`` before Adam's step is the method's combination (with the model's c) of per-task
    gradients from a loop of backward passes, and the actor's parameter change is Adam's first step on it; the
    critic and the entropy coefficient are surgered too when shared (``arch``), not when per task (their tasks share
    no parameter). SAC-MT's actor and the shared critic take the one-pass gradients, a multi-head actor
    (per-task heads) and beta the generic ones."""
    model = small_model(
        policy, gradient_surgery=method, cagrad_c=0.7, critic_arch=arch, ent_coef_arch=arch, learning_rate=1e-3
    )
    model.learn(800)  # by then the last task's actor gradient conflicts with the others'
    model.records, model.gradient_calls = {}, []
    record_combined_steps(model, monkeypatch)
    for function in ("per_task_gradients", "per_task_gradients_of_rows"):
        monkeypatch.setattr(task_steps, function, spy(getattr(task_steps, function), model.gradient_calls))
    fresh_adam = th.optim.Adam(model.actor.parameters(), lr=1e-3)
    model.actor.optimizer = fresh_adam
    model.train(1, 16)
    one_pass = {"actor loss": policy == "MlpPolicy", "critic loss": True, "entropy coefficient loss": False}
    for name, record in model.records.items():
        assert record["gradients_by"] == ["per_task_gradients_of_rows" if one_pass[name] else "per_task_gradients"]
    assert model.actor.kept_rows is None and model.critic.kept_rows is None  # nothing outlives the update
    assert set(model.records) == (SURGERED if arch == "shared" else {"actor loss"})
    for name, record in model.records.items():
        grads, weights = record["loop"], record["w"]  # 1/N for the actor and a shared beta, ones for the critic
        if method == "pcgrad":
            rng = th.get_rng_state()
            th.set_rng_state(record["rng"])
            orders = pcgrad_orders(model.n_tasks)
            th.set_rng_state(rng)
            expected = weights @ np.stack(loop_pcgrad(list(grads), orders))
        else:
            expected = cagrad_coefficients(grads @ grads.T, weights, 0.7) @ grads / (1 + 0.7**2)
        applied = th.cat([g.flatten() for g in record["grad"]]).double().numpy()
        np.testing.assert_allclose(applied, expected, rtol=1e-4, atol=1e-7, err_msg=name)
        if name != "entropy coefficient loss":  # (its tasks agree here: see the next test)
            assert np.linalg.norm(expected - weights @ grads) > 1e-3 * np.linalg.norm(expected), name
    record = model.records["actor loss"]
    for before, param, grad in zip(record["before"], record["params"], record["grad"], strict=True):
        th.testing.assert_close(param.detach(), before - 1e-3 * grad / (grad.abs() + 1e-8), rtol=1e-5, atol=1e-7)


def test_a_one_pass_gradient_refuses_an_optimizer_over_other_parameters():
    """The one-pass gradients are those of the module's shared network, column by column: an optimizer whose
    parameters are not that network's, in order, is refused rather than given misplaced gradients."""
    model = small_model(gradient_surgery="pcgrad", critic_arch="shared", ent_coef_arch="shared")
    model.learn(100)
    model.critic.optimizer = th.optim.Adam(list(model.critic.parameters())[::-1], lr=1e-3)
    with pytest.raises(RuntimeError, match="shared network, in order"):
        model.train(1, 16)


@pytest.mark.parametrize("method", ["pcgrad", "cagrad"])
def test_a_shared_entropy_coefficient_takes_the_surgered_step_of_conflicting_tasks(method, monkeypatch):
    """Task i's temperature loss has the gradient -mean(log pi_i + H-bar) in log beta: tasks above and below the
    target entropy conflict. The shared beta then steps along the method's combination (PCGrad: every projected
    gradient is 0, each one conflicting with a task of the other sign), not along the mean."""
    model = small_model(gradient_surgery=method, cagrad_c=0.7, critic_arch="shared", ent_coef_arch="shared")
    model.records = {}
    record_combined_steps(model, monkeypatch)
    offsets = th.tensor([0.5, 0.2, -0.3, 0.1])[:, None]  # mean(log pi_i + H-bar) per task
    log_prob = offsets - model.target_entropy + 0.05 * th.randn(4, 16)
    model._entropy_coef_step(model.temperature.loss(log_prob), model.temperature.task_weights)
    grads, weights = model.records["entropy coefficient loss"]["loop"], np.full(4, 0.25)
    np.testing.assert_allclose(grads[:, 0], -(log_prob + model.target_entropy).mean(1).numpy(), rtol=1e-5)
    if method == "pcgrad":
        expected = np.zeros(1)
    else:
        expected = cagrad_coefficients(grads @ grads.T, weights, 0.7) @ grads / (1 + 0.7**2)
    assert abs(expected - weights @ grads).item() > 1e-3
    applied = model.records["entropy coefficient loss"]["grad"][0].double().numpy()
    np.testing.assert_allclose(applied, expected, rtol=1e-5, atol=1e-6)


def test_a_shared_entropy_coefficient_without_surgery_minimises_the_mean_over_every_sample():
    """One beta for every task (SB3's SAC on the whole batch): its gradient is -mean(log pi + H-bar) over all N x L
    samples; the losses still see it once per task."""
    model = small_model(ent_coef_arch="shared")
    assert model.log_ent_coef.shape == (1,)
    log_prob = th.randn(4, 16) - model.target_entropy + th.tensor([1.0, 0.0, -2.0, 0.5])[:, None]
    before = model.entropy_coefficients.clone()
    ent_coef = model.temperature.ent_coef  # what the update's losses use
    model._entropy_coef_step(model.temperature.loss(log_prob), model.temperature.task_weights)
    th.testing.assert_close(model.log_ent_coef.grad, -(log_prob + model.target_entropy).mean().reshape(1))
    assert th.equal(ent_coef, before) and th.equal(before, before[:1].expand(4))


def test_without_surgery_the_update_is_unchanged():
    """gradient_surgery=None, the default, gives the same parameters as a model built without the argument, and PCGrad
    other ones (the weighted-sum step itself: test_mtsac.py)."""
    first = small_model().learn(800)
    second = small_model(gradient_surgery=None).learn(800)
    third = small_model(gradient_surgery="pcgrad").learn(800)
    assert not th.equal(
        first.policy.state_dict()["actor.net.0.weight"], third.policy.state_dict()["actor.net.0.weight"]
    )
    for key, value in first.policy.state_dict().items():
        assert th.equal(value, second.policy.state_dict()[key]), key


def test_bad_gradient_surgery_arguments_fail_clearly():
    with pytest.raises(ValueError, match="gradient_surgery"):
        small_model(gradient_surgery="mgda")
    for c in (0.0, 1.0, -0.5, float("nan")):
        with pytest.raises(ValueError, match="cagrad_c"):
            small_model(gradient_surgery="cagrad", cagrad_c=c)


AUTHORS_KEYS = {"mtsac_pcgrad": "pcgrad", "mtsac_cagrad": "cagrad"}
ACTOR_KEYS = {"mtsac_pcgrad_actor": "pcgrad", "mtsac_cagrad_actor": "cagrad"}


def zoo_model(algo: str) -> MTSAC:
    """The model of a zoo key's toy entry, with small networks and an early start."""
    entry = dict(zoo_hyperparameters(algo)[ENV])
    kwargs = {key: value for key, value in entry.items() if key not in ZOO_ONLY}
    kwargs.update(learning_starts=100, batch_size=16, policy_kwargs={"net_arch": [16, 16]})
    return MTSAC(env=make_mt_env(ENV, seed=0), seed=0, device="cpu", **kwargs)


@pytest.mark.parametrize("algo", [*AUTHORS_KEYS, *ACTOR_KEYS])
def test_each_zoo_key_surgers_the_losses_of_its_configuration(algo, monkeypatch):
    """The authors' keys send the critic, actor and entropy-coefficient losses through the method (one critic and one
    beta for every task) and carry the published numbers; the ``_actor`` keys only the actor's (per-task critics and
    beta_i), and publish none."""
    model = zoo_model(algo)
    model.learn(200)
    model.records = {}
    record_combined_steps(model, monkeypatch)
    model.train(1, 16)
    authors = algo in AUTHORS_KEYS
    assert model.gradient_surgery == {**AUTHORS_KEYS, **ACTOR_KEYS}[algo]
    assert set(model.records) == (SURGERED if authors else {"actor loss"})
    assert model.log_ent_coef.shape == ((1,) if authors else (model.n_tasks,))
    assert bool(VARIANTS[algo].paper) == authors


def test_cagrad_c_comes_from_the_registry_entry_of_the_benchmark_and_reaches_the_model(tmp_path, monkeypatch):
    """Every env entry of the family file takes the c of the one benchmark pattern of CAGRAD_C it matches, and the
    value the registry gives a benchmark is the c of the model the zoo trains on it."""
    for env_key, entry in zoo_hyperparameters("mtsac_cagrad").items():
        matches = [c for pattern, c in CAGRAD_C.items() if fnmatch.fnmatchcase(env_key, pattern)]
        assert len(matches) == 1 and entry["cagrad_c"] == matches[0], env_key
    registered = VARIANTS["mtsac_cagrad"]
    build = dataclasses.replace(registered.build, env_overrides={"toy-*": {"cagrad_c": 0.37}})
    variant = dataclasses.replace(registered, build=build)
    monkeypatch.setitem(VARIANTS, "mtsac_cagrad", variant)
    run = tiny_train(tmp_path, "mtsac_cagrad", "-params", "learning_starts:100", steps=200)
    model = MTSAC.load(run / f"{ENV}.zip")
    assert model.cagrad_c == 0.37 and model.gradient_surgery == "cagrad"
