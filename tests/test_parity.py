"""Parity of the MTSAC family with SB3's SAC: a single task (N = 1) works for every policy, MTSAC's update with
N = 1 is SAC's update, bad envs fail clearly, and (slow) MTSAC learns Pendulum-v1 as well as SAC does."""

from __future__ import annotations

import importlib.util
from collections.abc import Iterator
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv
from torch import nn

from sb3_mtte import MTSAC, evaluate_success, make_mt_env
from sb3_mtte.common.utils import check_multitask_env
from sb3_mtte.envs import OneHotTaskWrapper

POLICIES = ["MlpPolicy", "MultiHeadPolicy", "SoftModularPolicy", "IndependentPolicy"]
SMALL = dict(net_arch=[32, 32])


def one_task_model(policy: str = "MlpPolicy", env: VecEnv | None = None, **kwargs) -> MTSAC:
    env = env or make_mt_env("toy-agree-1", seed=0)
    policy_kwargs = dict(SMALL)
    if policy == "SoftModularPolicy":
        policy_kwargs["actor_kwargs"] = dict(n_layers=2, n_modules=2, module_size=16)
    return MTSAC(policy, env, learning_starts=100, batch_size=16, policy_kwargs=policy_kwargs, seed=0, **kwargs)


# ------------------------------------------------------------------------------------------------- N = 1
@pytest.mark.parametrize("policy", POLICIES)
def test_single_task_trains_saves_loads_and_evaluates(policy, tmp_path):
    model = one_task_model(policy)
    model.learn(300)
    assert model.n_tasks == 1 and model.entropy_coefficients.shape == (1,)
    assert model.replay_buffer.sample(8).observations.shape == (1, 8, 5)  # 4-d state + [1.0]
    model.save(tmp_path / "model")
    loaded = MTSAC.load(tmp_path / "model", env=make_mt_env("toy-agree-1", seed=1))
    assert loaded.n_tasks == 1 and loaded.task_names == ["agree-0"]
    for key, value in model.policy.state_dict().items():
        assert th.equal(value, loaded.policy.state_dict()[key]), key
    obs = make_mt_env("toy-agree-1", seed=3).reset()
    assert np.array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    loaded.learn(50, reset_num_timesteps=False)
    result = evaluate_success(loaded, make_mt_env("toy-agree-1", seed=2), episodes_per_task=2)
    assert result.task_names == ["agree-0"] and 0.0 <= result.mean <= 1.0


def test_single_task_logs_per_task_keys(tmp_path):
    from stable_baselines3.common.logger import configure

    model = one_task_model()
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(400, log_interval=1)
    header = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    assert {"rollout/success/00_agree-0", "train/critic_loss/00_agree-0", "train/ent_coef"} <= set(header)


def test_single_metaworld_task():
    env = make_mt_env(["reach-v3"], seed=0, max_episode_steps=50)
    obs = env.reset()
    assert env.num_envs == 1 and obs.shape == (1, 40) and obs[0, -1] == 1.0
    model = MTSAC("MlpPolicy", env, learning_starts=60, batch_size=8, policy_kwargs=SMALL, seed=0)
    model.learn(100)
    assert model.task_names == ["reach-v3"] and model._n_updates > 0
    assert evaluate_success(model, env, episodes_per_task=2).success_rate.shape == (1,)


# ------------------------------------------------------------------------------------------ one-hot wrapper
def test_one_hot_wrapper_appends_the_one_hot_and_keeps_the_env_seeding():
    plain, wrapped = gym.make("Pendulum-v1"), OneHotTaskWrapper(gym.make("Pendulum-v1"))
    assert wrapped.task_name == "Pendulum-v1" and wrapped.task_index == 0
    assert np.array_equal(wrapped.observation_space.low, [-1.0, -1.0, -8.0, 0.0])
    assert np.array_equal(wrapped.observation_space.high, [1.0, 1.0, 8.0, 1.0])
    obs, info = wrapped.reset(seed=5)
    assert np.array_equal(obs, np.append(plain.reset(seed=5)[0], np.float32(1.0))) and info["task_index"] == 0
    for action in np.linspace(-2.0, 2.0, 5, dtype=np.float32)[:, None]:
        obs, reward, _terminated, _truncated, info = wrapped.step(action)
        expected = plain.step(action)
        assert obs.dtype == np.float32 and np.array_equal(obs[:-1], expected[0]) and obs[-1] == 1.0
        assert reward == expected[1] and info["task_index"] == 0 and "is_success" not in info
    # SB3 seeds a VecEnv through reset(seed=...) of every sub-env.
    vec_plain = DummyVecEnv([lambda: gym.make("Pendulum-v1")])
    vec_wrapped = DummyVecEnv([lambda: OneHotTaskWrapper(gym.make("Pendulum-v1"))])
    vec_plain.seed(3)
    vec_wrapped.seed(3)
    assert np.array_equal(vec_wrapped.reset()[:, :-1], vec_plain.reset())
    check_multitask_env(vec_wrapped)


def test_one_hot_wrapper_as_task_i_of_n():
    env = OneHotTaskWrapper(gym.make("Pendulum-v1"), task_index=1, n_tasks=3, task_name="pendulum-b")
    assert np.array_equal(env.reset(seed=0)[0][-3:], [0.0, 1.0, 0.0]) and env.task_name == "pendulum-b"
    with pytest.raises(ValueError, match="task_index"):
        OneHotTaskWrapper(gym.make("Pendulum-v1"), task_index=3, n_tasks=3)


# ------------------------------------------------------------------------------------------------ bad envs
class NoSubEnvs(VecEnv):
    """A VecEnv with zero sub-envs (SB3's own VecEnv constructor needs at least one)."""

    def __init__(self) -> None:
        self.num_envs, self.render_mode, self.metadata = 0, None, {}
        self.observation_space = self.action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.reset_infos, self._seeds, self._options = [], [], []

    def reset(self):
        return np.zeros((0, 3), np.float32)

    def step_async(self, actions) -> None:
        raise NotImplementedError

    def step_wait(self):
        raise NotImplementedError

    def close(self) -> None:
        pass

    def get_attr(self, attr_name, indices=None):
        return []

    def set_attr(self, attr_name, value, indices=None) -> None:
        pass

    def env_method(self, method_name, *method_args, indices=None, **method_kwargs):
        return []

    def env_is_wrapped(self, wrapper_class, indices=None):
        return []


class DictObsEnv(gym.Env):
    observation_space = spaces.Dict({"state": spaces.Box(-1.0, 1.0, (3,), np.float32)})
    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)


def test_empty_or_malformed_envs_fail_clearly():
    with pytest.raises(ValueError, match=r"at least 1 task \(one sub-env per task\); got 0 sub-envs"):
        MTSAC("MlpPolicy", NoSubEnvs())
    with pytest.raises(ValueError, match="at least 1 task"):
        make_mt_env([])
    with pytest.raises(ValueError, match="at least 1 task, got 0"):
        make_mt_env("toy-agree-0")
    plain = DummyVecEnv([lambda: gym.make("Pendulum-v1")])  # no one-hot: the last state entry is not 1
    with pytest.raises(ValueError, match="one-hot"):
        MTSAC("MlpPolicy", plain, learning_starts=10, policy_kwargs=SMALL).learn(10)
    with pytest.raises(ValueError, match="flat Box"):
        check_multitask_env(DummyVecEnv([DictObsEnv]))  # MTSAC("MlpPolicy", ...) is refused by SB3 first
    with pytest.raises(ValueError, match="cannot hold a state"):
        check_multitask_env(DummyVecEnv([lambda: OneHotTaskWrapper(gym.make("CartPole-v1"))] * 5))
    one_task = make_mt_env("toy-agree-1")
    assert check_multitask_env(one_task) == 1
    with pytest.raises(ValueError, match=r"at least 2 tasks \(one sub-env per task\); got 1 sub-env: build the env"):
        check_multitask_env(one_task, min_tasks=2)


# ------------------------------------------------------------------------------------- same update as SAC
def linears(module: nn.Module) -> list[nn.Linear]:
    return [m for m in module.modules() if isinstance(m, nn.Linear)]


def matched_tensors(mtsac: MTSAC, sac: SAC) -> Iterator[tuple[str, th.Tensor, th.Tensor]]:
    """``(name, view into an MTSAC parameter, the SAC parameter it must equal)`` for every SAC parameter.

    The one-hot input column of SAC-MT's actor has no SAC counterpart and is left out.
    """
    actor = mtsac.actor
    if hasattr(actor, "net"):  # SharedActor: state + one-hot in, mean and log-std out of one Linear
        mine = [(layer.weight, layer.bias) for layer in linears(actor.net)]
        mine[0] = (mine[0][0][:, :-1], mine[0][1])
    else:  # IndependentActor: a 1-member ensemble on the state
        mine = [(layer.weight[0].T, layer.bias[0, 0]) for layer in actor.nets.layers]
    theirs = [(layer.weight, layer.bias) for layer in linears(sac.actor.latent_pi)]
    theirs.append(
        (th.cat([sac.actor.mu.weight, sac.actor.log_std.weight]), th.cat([sac.actor.mu.bias, sac.actor.log_std.bias]))
    )
    assert len(mine) == len(theirs)
    for k, ((weight, bias), (sac_weight, sac_bias)) in enumerate(zip(mine, theirs, strict=True)):
        yield f"actor.{k}.weight", weight, sac_weight
        yield f"actor.{k}.bias", bias, sac_bias
    for name in ("critic", "critic_target"):
        ensemble, twins = getattr(mtsac, name).q_net, getattr(sac, name).q_networks
        for c, q_net in enumerate(twins):  # member c of the 1-task ensemble is twin c
            for k, (layer, linear) in enumerate(zip(ensemble.layers, linears(q_net), strict=True)):
                yield f"{name}.{c}.{k}.weight", layer.weight[c].T, linear.weight
                yield f"{name}.{c}.{k}.bias", layer.bias[c, 0], linear.bias
    yield "log_ent_coef", mtsac.log_ent_coef, sac.log_ent_coef


def sac_and_one_task_mtsac(policy: str, optimizer_class: type[th.optim.Optimizer] = th.optim.Adam) -> tuple[SAC, MTSAC]:
    """SAC on Pendulum and MTSAC on Pendulum + one-hot, same weights, same 200 random transitions."""
    kwargs = dict(learning_rate=1e-3, buffer_size=1_000, learning_starts=0, tau=0.2, device="cpu")  # targets move
    sac_net = dict(net_arch=[16, 16], optimizer_class=optimizer_class)
    sac = SAC("MlpPolicy", DummyVecEnv([lambda: gym.make("Pendulum-v1")]), policy_kwargs=sac_net, **kwargs)
    env = DummyVecEnv([lambda: OneHotTaskWrapper(gym.make("Pendulum-v1"))])
    mtsac = MTSAC(policy, env, policy_kwargs=dict(net_arch=[16, 16], optimizer_class=optimizer_class), **kwargs)
    with th.no_grad():
        for _, mine, theirs in matched_tensors(mtsac, sac):
            mine.copy_(theirs)
        if hasattr(mtsac.actor, "net"):
            linears(mtsac.actor.net)[0].weight[:, -1] = 0.0  # the one-hot column: SAC's actor outputs
    rng = np.random.default_rng(0)
    for step in range(200):
        obs, next_obs = rng.normal(size=(2, 1, 3)).astype(np.float32)
        action, reward = rng.uniform(-1, 1, size=(1, 1)).astype(np.float32), rng.normal(size=1)
        done = np.array([step % 20 == 19])
        infos = [{"TimeLimit.truncated": step % 40 == 39}]
        sac.replay_buffer.add(obs, next_obs, action, reward, done, infos)
        one_hot = np.ones((1, 1), np.float32)
        mtsac.replay_buffer.add(np.hstack([obs, one_hot]), np.hstack([next_obs, one_hot]), action, reward, done, infos)
    for model in (sac, mtsac):
        model.set_logger(Logger(None, []))
    return sac, mtsac


def assert_same_update(mtsac: MTSAC, sac: SAC, step: int) -> None:
    """Same parameters, and the same logged losses and entropy coefficient."""
    for name, mine, theirs in matched_tensors(mtsac, sac):
        assert th.allclose(mine, theirs, rtol=0.0, atol=5e-6), (step, name, (mine - theirs).abs().max())
    if step > 0:
        for key in ("train/actor_loss", "train/critic_loss", "train/ent_coef", "train/ent_coef_loss"):
            mine, theirs = mtsac.logger.name_to_value[key], sac.logger.name_to_value[key]
            assert mine == pytest.approx(theirs, rel=1e-5, abs=1e-7), (step, key)


@pytest.mark.parametrize(
    "policy, n_updates, optimizer_class",
    [
        ("MlpPolicy", 1, th.optim.Adam),
        ("IndependentPolicy", 20, th.optim.Adam),
        ("IndependentPolicy", 20, th.optim.SGD),
    ],
)
def test_one_task_update_is_sb3_sac_update(policy, n_updates, optimizer_class):
    """Same weights, same batch rows, same noise: MTSAC with N = 1 moves every parameter as SAC does.

    SAC-MT's actor also reads the one-hot [1.0], a second bias of its first layer with its own optimizer state:
    from the second update on it makes the actor differ, so SAC-MT is compared over one update and SAC-Ind (whose
    actor reads the state alone, as SAC's) over many. SGD (linear in the gradients, unlike Adam's first steps)
    makes any difference of gradients show in the parameters.
    """
    sac, mtsac = sac_and_one_task_mtsac(policy, optimizer_class)
    assert_same_update(mtsac, sac, 0)
    for step in range(1, n_updates + 1):
        for model in (sac, mtsac):  # the same rows (numpy) and the same action noise (torch) for both
            np.random.seed(step)
            th.manual_seed(step)
            model.train(gradient_steps=1, batch_size=32)
        assert_same_update(mtsac, sac, step)
    assert not th.equal(mtsac.log_ent_coef, th.zeros(1))


# ---------------------------------------------------------------------------------------------- learning
def load_parity_script():
    path = Path(__file__).resolve().parents[1] / "scripts" / "studies" / "sac_parity.py"
    spec = importlib.util.spec_from_file_location("sac_parity", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("env_id", ["pendulum", "reach"])
def test_parity_script_gives_sac_the_same_env_without_the_one_hot(env_id):
    parity = load_parity_script()
    mtsac_env, sac_env = parity.make_env(env_id, "mtsac", 0), parity.make_env(env_id, "sac", 0)
    for env in (mtsac_env, sac_env):
        env.seed(4)
        if env.has_attr("set_eval_mode"):
            env.env_method("set_eval_mode", True)
    assert mtsac_env.observation_space.shape[0] == sac_env.observation_space.shape[0] + 1
    obs, sac_obs = mtsac_env.reset(), sac_env.reset()
    actions = np.random.default_rng(0).uniform(-1, 1, size=(30, 1, *sac_env.action_space.shape)).astype(np.float32)
    for action in actions:
        assert np.array_equal(obs[:, :-1], sac_obs) and obs[0, -1] == 1.0
        (obs, reward, _, infos), (sac_obs, sac_reward, _, sac_infos) = mtsac_env.step(action), sac_env.step(action)
        assert reward == sac_reward and infos[0].get("is_success") == sac_infos[0].get("is_success")


@pytest.mark.slow
def test_pendulum_learns_as_with_sb3_sac():
    """rl-zoo3's Pendulum-v1 SAC setting (20k steps, lr 1e-3), identical for both, seeds 0-2.

    Bar: both reach a mean final return > -400 (a random policy scores about -1200), and the mean final
    returns differ by less than 50. Measured (scripts/studies/sac_parity.py): MTSAC -134.9 +- 10.1, SAC -135.5 +- 9.3
    over seeds 0-2, so the standard error of the difference of the two means is about 8: 50 is six of them.
    """
    parity = load_parity_script()
    th.set_num_threads(1)
    final = {algo: [] for algo in parity.ALGOS}
    for seed in (0, 1, 2):
        for algo in parity.ALGOS:
            record = parity.run_one("pendulum", algo, seed, steps=20_000, eval_freq=20_000, eval_episodes=10)
            final[algo].append(record["curve"]["return"][-1])
    means = {algo: float(np.mean(values)) for algo, values in final.items()}
    assert min(means.values()) > -400, final
    assert abs(means["mtsac"] - means["sac"]) < 50, final
