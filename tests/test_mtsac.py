"""MTSAC family: losses (Eq. 15-16), per-task temperatures, save/load/resume, reproducibility, bad input,
learning on the toy env and an MT10 smoke run of every variant."""

import copy
from types import SimpleNamespace

import numpy as np
import pytest
import torch as th
from conftest import fixed_randn_like
from references import loop_log_prob, loop_q, loop_split
from stable_baselines3 import SAC
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_mtte import MTSAC, MTSACTE, evaluate_success, make_mt_env
from sb3_mtte.common.losses import clipped_soft_q_loss, per_task_entropy_loss, sac_task_objective

POLICIES = ["MlpPolicy", "MultiHeadPolicy", "SoftModularPolicy", "IndependentPolicy"]
SMALL = dict(net_arch=[32, 32])


def small_model(policy="MlpPolicy", seed=0, env=None, cls=MTSAC, **kwargs):
    env = env or make_mt_env("toy-conflict", seed=seed)
    kwargs.setdefault("policy_kwargs", SMALL)
    kwargs.setdefault("device", "cpu")
    if policy == "SoftModularPolicy":
        kwargs["policy_kwargs"] = {
            **kwargs["policy_kwargs"],
            "actor_kwargs": dict(n_layers=2, n_modules=2, module_size=16),
        }
    return cls(policy, env, learning_starts=100, batch_size=16, seed=seed, **kwargs)


def all_params(model):
    return {k: v.detach().clone() for k, v in model.policy.state_dict().items()}


class FirstTaskOnlyMTSAC(MTSAC):
    """A gradient-level method written as one override of the actor step: it records what the step receives and
    trains the actor on task 0's loss alone."""

    def _actor_step(self, task_losses: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
        self.received = {
            "losses": task_losses.detach().clone(),
            "weights": task_weights.clone(),
            "actor": copy.deepcopy(self.actor),
            "critic": copy.deepcopy(self.critic),
        }
        loss = super()._actor_step(
            task_losses, th.eye(self.n_tasks, dtype=task_weights.dtype, device=task_weights.device)[0]
        )
        self.received["grads"] = [p.grad.detach().clone() for p in self.actor.parameters()]
        return loss


def test_actor_step_hook_receives_the_per_task_losses_and_changes_the_update(monkeypatch):
    """The actor step gets the (N,) losses -J_SAC,i of a plain per-task loop and the (N,) weights w; overriding it
    changes the update (here: task 0 alone), and the model still trains."""
    model = small_model(cls=FirstTaskOnlyMTSAC, policy_kwargs={"net_arch": [16, 16]})
    before = all_params(model)
    model.learn(200)
    assert model._n_updates > 0 and all(th.isfinite(v).all() for v in all_params(model).values())
    assert any(not th.equal(before[k], v) for k, v in all_params(model).items() if k.startswith("actor."))

    monkeypatch.setattr(model.ent_coef_optimizer, "step", lambda *args, **kwargs: None)  # beta_i fixed
    beta, draw, captured = model.entropy_coefficients.clone(), fixed_randn_like(monkeypatch), {}
    original_sample = model.replay_buffer.sample

    def sample(*args, **kwargs):
        captured["batch"] = original_sample(*args, **kwargs)
        return captured["batch"]

    monkeypatch.setattr(model.replay_buffer, "sample", sample)
    model.train(1, 16)
    received, obs = model.received, captured["batch"].observations
    noise = draw((*obs.shape[:2], model.policy.action_dim), obs.dtype)
    critics, c = SimpleNamespace(critic=received["critic"]), model.critic.n_critics

    def reference_loss(task: int) -> th.Tensor:
        mean, log_std = loop_split(received["actor"].net(obs[task]))
        action, log_prob = loop_log_prob(mean, log_std, noise[task])
        x = th.cat([obs[task][:, : model.policy.state_dim], action], dim=-1)
        min_q = th.stack([loop_q(critics, task * c + j, x) for j in range(c)]).min(dim=0).values
        return (beta[task] * log_prob - min_q).mean()

    losses = [reference_loss(i) for i in range(model.n_tasks)]
    th.testing.assert_close(received["losses"], th.stack(losses).detach(), rtol=1e-5, atol=1e-6)
    th.testing.assert_close(received["weights"], th.full((model.n_tasks,), 1 / model.n_tasks))
    params = list(received["actor"].parameters())
    task_0 = th.autograd.grad(losses[0], params, retain_graph=True)
    for applied, expected in zip(received["grads"], task_0, strict=True):
        th.testing.assert_close(applied, expected, rtol=1e-4, atol=1e-6)
    weighted = th.autograd.grad(sum(losses) / model.n_tasks, params)
    flat = th.cat([g.flatten() for g in task_0])
    assert (th.cat([g.flatten() for g in weighted]) - flat).norm() > 0.1 * flat.norm()


# ------------------------------------------------------------------------------------------------ Eq. 15-16
def test_clipped_q_loss_equals_loop_and_zeroes_gradient_above_clip():
    th.manual_seed(0)
    q = th.randn(2, 3, 5, requires_grad=True)
    target = th.randn(3, 5) * 3
    target[1, 2] = 100.0  # 0.5 * ~100^2 >> clip
    loss = clipped_soft_q_loss(q, target, clip=2.0)
    expected = th.zeros(3)
    for i in range(3):
        for j in range(2):
            per_sample = [min(0.5 * float(q[j, i, b].detach() - target[i, b]) ** 2, 2.0) for b in range(5)]
            expected[i] += sum(per_sample) / 5
    assert th.allclose(loss, expected, atol=1e-5)
    loss.sum().backward()
    above = 0.5 * (q.detach() - target) ** 2 > 2.0
    assert above[:, 1, 2].all()
    assert th.all(q.grad[above] == 0)
    assert th.all(q.grad[~above] != 0)


def test_q_loss_without_clip_is_plain_half_mse():
    th.manual_seed(1)
    q, target = th.randn(2, 4, 6), th.randn(4, 6) * 50
    loss = clipped_soft_q_loss(q, target, clip=None)
    expected = sum(0.5 * ((q[j] - target) ** 2).mean(dim=1) for j in range(2))
    assert th.allclose(loss, expected)


def test_actor_loss_is_negative_sac_objective_per_task():
    log_prob = th.tensor([[1.0, 3.0], [0.0, -2.0]])
    min_q = th.tensor([[2.0, 2.0], [1.0, 5.0]])
    ent = th.tensor([0.5, 2.0])
    # task 0: mean(0.5*[1,3] - 2) = mean([-1.5, -0.5]) = -1; task 1: mean([0-1, -4-5]) = -5
    assert th.allclose(-sac_task_objective(log_prob, min_q, ent), th.tensor([-1.0, -5.0]))


def test_entropy_loss_of_task_i_moves_only_beta_i():
    log_ent_coef = th.zeros(4, requires_grad=True)
    optimizer = th.optim.Adam([log_ent_coef], lr=0.1)
    log_prob = th.randn(4, 8)
    per_task_entropy_loss(log_ent_coef, log_prob, target_entropy=-2.0)[2].backward()
    optimizer.step()
    moved = log_ent_coef.detach() != 0
    assert moved.tolist() == [False, False, True, False]


def test_the_training_steps_beta_update_is_eq_3_per_task():
    """With SGD at lr 1, log beta_i moves by mean_l (log pi_il + H-bar) (minus the gradient of Eq. 3 in log space)."""
    model = small_model()
    model.temperature.optimizer = th.optim.SGD([model.log_ent_coef], lr=1.0)
    before = model.log_ent_coef.detach().clone()
    log_prob = th.tensor([[1.0, -3.0, 0.5], [-2.0, -2.0, -2.0], [0.0, 4.0, -1.0], [-6.0, 0.0, 3.0]])
    used = model.temperature.ent_coef  # what the update's losses use
    model._entropy_coef_step(model.temperature.loss(log_prob), model.temperature.task_weights)
    target = model.target_entropy
    for i in range(4):
        expected_step = sum(value + target for value in log_prob[i].tolist()) / 3
        assert model.log_ent_coef[i].item() - before[i].item() == pytest.approx(expected_step, abs=1e-6), i
    assert th.allclose(used, before.exp())  # the losses of this update use beta before the step


def test_training_updates_every_beta_separately():
    model = small_model()
    model.learn(400)
    betas = model.entropy_coefficients
    assert betas.shape == (4,) and not th.allclose(betas, th.ones(4))
    assert len(set(betas.tolist())) == 4


# ----------------------------------------------------------------------------------------------- save/load
@pytest.mark.parametrize("policy", POLICIES)
def test_save_load_round_trip(policy, tmp_path):
    model = small_model(policy, q_loss_clip=2000.0)
    model.learn(300)
    model.save(tmp_path / "model")
    loaded = MTSAC.load(tmp_path / "model", env=None, device="cpu")
    assert loaded.replay_buffer is None and loaded.n_tasks == 4
    for key, value in all_params(model).items():
        assert th.equal(value, loaded.policy.state_dict()[key]), key
    for name in ("actor.optimizer", "critic.optimizer", "ent_coef_optimizer"):
        saved = eval(f"model.{name}").state_dict()["state"]
        restored = eval(f"loaded.{name}").state_dict()["state"]
        for index in saved:
            for k in saved[index]:
                assert th.equal(saved[index][k], restored[index][k]), (name, k)
    assert th.equal(model.log_ent_coef, loaded.log_ent_coef)
    assert loaded.q_loss_clip == 2000.0
    obs = make_mt_env("toy-conflict", seed=3).reset()
    assert np.array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"gradient_surgery": "pcgrad"},
        {"gradient_surgery": "cagrad", "cagrad_c": 0.3},
        {"gradient_surgery": "pcgrad", "critic_arch": "shared", "ent_coef_arch": "shared"},
    ],
    ids=str,
)
def test_resume_gives_the_same_next_update_as_an_uninterrupted_run(kwargs, tmp_path):
    """Also with gradient surgery: the method, c and the shared critic and beta are restored, and PCGrad's random
    orders replay."""
    model = small_model(**kwargs)
    model.learn(300)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    model.train(gradient_steps=2, batch_size=16)
    expected = all_params(model)

    resumed = MTSAC.load(tmp_path / "model", env=make_mt_env("toy-conflict", seed=0), device="cpu")
    assert {key: getattr(resumed, key) for key in kwargs} == kwargs
    resumed.load_replay_buffer(tmp_path / "buffer")
    resumed.set_logger(model.logger)
    resumed.train(gradient_steps=2, batch_size=16)
    for key, value in expected.items():
        assert th.equal(value, resumed.policy.state_dict()[key]), key


def test_a_model_saved_before_learning_starts_resumes_its_random_warm_up_actions(tmp_path):
    """SB3 draws the actions before learning_starts from the action space's generator, which loading re-seeds."""
    model = small_model(seed=3)
    model.learn(40)  # 40 env steps, before learning_starts=100
    model.save(tmp_path / "model")
    continued = [model.action_space.sample() for _ in range(3)]
    resumed = MTSAC.load(tmp_path / "model", device="cpu")
    assert np.array_equal(np.stack(continued), np.stack([resumed.action_space.sample() for _ in range(3)]))


def test_same_seed_same_run():
    first = small_model(seed=7).learn(300)
    second = small_model(seed=7).learn(300)
    for key, value in all_params(first).items():
        assert th.equal(value, second.policy.state_dict()[key]), key
    third = small_model(seed=8)
    third.learn(300)
    assert not all(th.equal(v, third.policy.state_dict()[k]) for k, v in all_params(first).items())


def test_loading_another_algorithm_or_task_count_fails_clearly(tmp_path):
    small_model().save(tmp_path / "mtsac")
    with pytest.raises(ValueError, match="saved by MTSAC"):
        MTSACTE.load(tmp_path / "mtsac")
    with pytest.raises(ValueError, match="trained on 4 tasks"):
        MTSAC.load(tmp_path / "mtsac", env=make_mt_env("toy-conflict-6"))
    env = make_mt_env("toy-conflict")
    SAC("MlpPolicy", env, learning_starts=10, buffer_size=100).save(tmp_path / "sac")
    with pytest.raises(ValueError, match="another algorithm"):
        MTSAC.load(tmp_path / "sac")


# ------------------------------------------------------------------------------------------------ bad input
def test_rejects_env_without_one_sub_env_per_task():
    fns = [lambda: make_mt_env("toy-conflict").envs[0]] * 3  # 3 sub-envs whose one-hot has 4 entries
    env = DummyVecEnv(fns)
    with pytest.raises(ValueError, match="one-hot"):  # refused at construction, before learn()
        MTSAC("MlpPolicy", env, learning_starts=10, policy_kwargs=SMALL)


def test_rejects_non_positive_clip_and_bad_critic_and_ent_coef_arch():
    with pytest.raises(ValueError, match="q_loss_clip"):
        small_model(q_loss_clip=0.0)
    with pytest.raises(ValueError, match="critic_arch"):
        small_model(critic_arch="bogus")
    with pytest.raises(ValueError, match="ent_coef_arch must be one of"):
        small_model(ent_coef_arch="per_sample")


def test_nan_loss_stops_training_and_names_the_loss():
    model = small_model()
    model.learn(200)
    model.replay_buffer.rewards[:] = np.nan
    with pytest.raises(FloatingPointError, match="critic loss"):
        model.train(1, 16)


# ------------------------------------------------------------------------------------------------- logging
def test_logs_per_task_success_and_critic_loss(tmp_path):
    from stable_baselines3.common.logger import configure

    model = small_model()
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(800, log_interval=1)
    header = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    assert "rollout/success/03_conflict" in header
    assert "train/critic_loss/00_agree-0" in header
    assert "rollout/success_rate" in header and "train/ent_coef" in header


def _logged(tmp_path, key):
    import csv

    with open(tmp_path / "progress.csv") as file:
        return [float(row[key]) for row in csv.DictReader(file) if row.get(key)]


@pytest.mark.parametrize("q_loss_clip, fraction", [(None, None), (1e-12, 1.0), (1e12, 0.0)])
def test_logs_the_share_of_clipped_q_samples_only_with_a_clip(tmp_path, q_loss_clip, fraction):
    from stable_baselines3.common.logger import configure

    model = small_model(q_loss_clip=q_loss_clip)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(400, log_interval=1)
    header = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    if fraction is None:
        assert "train/q_loss_clip_fraction" not in header
    else:
        values = _logged(tmp_path, "train/q_loss_clip_fraction")
        assert values and all(value == fraction for value in values)


def test_clip_fraction_is_the_mean_over_the_updates_between_dumps(tmp_path):
    from stable_baselines3.common.logger import configure

    model = small_model(q_loss_clip=1.0)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    n = model.n_tasks
    for fractions in ([0.0, 0.5, 1.0, 0.5], [0.25, 0.25, 0.25, 0.25]):
        stats = {"actor_loss": np.float32(0), "critic_loss": np.zeros(n), "ent_coef": np.ones(n)}
        model._record_train_stats({**stats, "q_loss_clip_fraction": np.array(fractions)})
    model.logger.dump(0)
    assert _logged(tmp_path, "train/q_loss_clip_fraction") == [pytest.approx((0.5 + 0.25) / 2)]


def test_logs_are_dumped_once_per_step_when_several_sub_envs_end_together(tmp_path):
    """The 4 sub-envs end their episodes at the same step: with log_interval=1 SB3 would dump 4 tables there."""
    from stable_baselines3.common.logger import configure

    model = small_model()
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(400, log_interval=1)
    lines = (tmp_path / "progress.csv").read_text().splitlines()
    steps = [row.split(",")[lines[0].split(",").index("time/total_timesteps")] for row in lines[1:]]
    assert len(steps) >= 2 and len(steps) == len(set(steps)), steps


# ------------------------------------------------------------------------------------------------ learning
@pytest.mark.parametrize(
    "policy, critic_arch",
    [pytest.param(policy, "per_task", marks=pytest.mark.slow) for policy in POLICIES]
    + [pytest.param("MlpPolicy", "shared", marks=pytest.mark.slow)],
)
def test_every_variant_learns_the_toy_conflict_env(policy, critic_arch):
    """Budget: 12k env steps (3k vector steps, 4 tasks), 2x64 nets, L=64; stated bar: mean success >= 0.75. Long:
    .ci/run runs the MlpPolicy per-task one after the default suite."""
    env = make_mt_env("toy-conflict", seed=0)
    kwargs = dict(net_arch=[64, 64])
    if policy == "SoftModularPolicy":
        kwargs["actor_kwargs"] = dict(n_layers=2, n_modules=2, module_size=32)
    model = MTSAC(
        policy,
        env,
        learning_starts=1000,
        batch_size=64,
        learning_rate=1e-3,
        critic_arch=critic_arch,
        policy_kwargs=kwargs,
        seed=0,
        device="cpu",
    )
    model.learn(12_000)
    result = evaluate_success(model, make_mt_env("toy-conflict", seed=100), episodes_per_task=10)
    assert result.mean >= 0.75, result.as_dict()


@pytest.mark.parametrize("policy", POLICIES)
def test_mt10_smoke_run(policy):
    env = make_mt_env("MT10", seed=0)
    model = MTSAC(policy, env, learning_starts=100, batch_size=16, buffer_size=20_000, seed=0, q_loss_clip=2000.0)
    model.learn(300)
    assert model.num_timesteps == 300 and model._n_updates >= 15
    assert model.replay_buffer.sample(4).observations.shape == (10, 4, 49)


def test_polyak_update_moves_every_target_by_tau_towards_its_parameter():
    from sb3_mtte.common.utils import polyak_update

    params = [th.tensor([1.0, -2.0]), th.tensor([[0.5]])]
    targets = [th.tensor([3.0, 2.0]), th.tensor([[-0.5]])]
    polyak_update(params, targets, 0.25)  # 0.75 * target + 0.25 * param
    assert th.allclose(targets[0], th.tensor([2.5, 1.0])) and th.allclose(targets[1], th.tensor([[-0.25]]))
    with pytest.raises(ValueError):
        polyak_update(params, targets[:1], 0.25)


@pytest.mark.parametrize("cls", [MTSAC, MTSACTE])
def test_the_actor_backward_pass_skips_the_critic_and_changes_no_number(cls):
    """The critic is a constant of the actor loss: its weight gradients are not computed there. Training must be
    bit-identical to the straightforward update, which lets them accumulate in .grad (the critic step zeroes them)."""
    fast = small_model(cls=cls).learn(300)
    plain = small_model(cls=cls)
    plain.critic.requires_grad_ = lambda requires_grad=True: plain.critic  # the straightforward update
    plain.learn(300)
    for key, value in all_params(fast).items():
        assert th.equal(value, all_params(plain)[key]), key
    for model, changed in ((fast, False), (plain, True)):
        after_critic_step = []
        critic_step = model._critic_step

        def recording_critic_step(*args, model=model, critic_step=critic_step, record=after_critic_step):
            loss = critic_step(*args)
            record.extend(p.grad.clone() for p in model.critic.parameters())
            return loss

        model._critic_step = recording_critic_step
        model.train(1, 16)
        after_update = [p.grad for p in model.critic.parameters()]
        assert any(not th.equal(a, b) for a, b in zip(after_critic_step, after_update, strict=True)) == changed
