"""Tests of MTSACTE's refusals of bad input and its numerical guards: a NaN or infinity in a loss, a reward or
the entropy coefficient stops training with a message naming the quantity."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch as th
from conftest import (
    EpisodeEnv,
    assert_state_equal,
    disable_representation_updates,
    make_episode_env,
    small_model_kwargs,
)
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_mtte import MTSACTE


# ========================================================================================================= bad input
def test_invalid_hyperparameters(toy_env):
    with pytest.raises(ValueError, match=r"n_select \(M\) must satisfy 1 <= M < N = 4"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(n_select=4))
    with pytest.raises(ValueError, match="n_select"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(n_select=7))
    with pytest.raises(ValueError, match="n_select"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(n_select=0))
    for top_k in (0, -3):
        with pytest.raises(ValueError, match=r"top_k \(K\) must be at least 1"):
            MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(top_k=top_k))
    for clip in (0.0, -5.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match=r"q_loss_clip \(V_clip\) must be a positive number or None"):
            MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(q_loss_clip=clip))
    with pytest.raises(ValueError, match="nt_estimator"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(nt_estimator="exact"))
    with pytest.raises(ValueError, match="iteration_length"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(iteration_length=0))
    for bad in ({"nt_step_size": -1e-3}, {"c_vae": -1.0}, {"rep_learning_rate": 0.0}):
        with pytest.raises(ValueError, match="nt_step_size and c_vae must be >= 0 and rep_learning_rate > 0"):
            MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(**bad))


@pytest.mark.parametrize(
    "bad, message",
    [
        ({"nt_chunk_size": 0}, "nt_chunk_size must be 'auto', None or a positive int"),
        ({"nt_chunk_size": "all"}, "nt_chunk_size must be 'auto', None or a positive int"),
        ({"nt_measure": "median"}, "nt_measure must be one of"),
        ({"rep_gradient_steps": 0}, r"iteration_length \(H\) and rep_gradient_steps must be at least 1"),
        ({"policy_kwargs": {"rep_learning_rate": 1e-3}}, "rep_learning_rate is an argument of MTSACTE"),
        ({"critic_arch": "shared"}, "MTSACTE's critics are per task"),
    ],
)
def test_each_argument_check_names_its_argument(toy_env, bad, message):
    with pytest.raises(ValueError, match=message):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(**bad))


def test_env_without_one_sub_env_per_task():
    """3 sub-envs whose observations carry a 4-entry one-hot: rejected with a message naming the one-hot layout."""
    env = make_episode_env(n_tasks=4, n_envs=3)
    with pytest.raises(ValueError, match="one-hot"):
        MTSACTE("MlpPolicy", env, **small_model_kwargs()).learn(12)
    # A single sub-env is not a multi-task env.
    with pytest.raises(ValueError, match="at least 2 tasks"):
        MTSACTE("MlpPolicy", DummyVecEnv([lambda: EpisodeEnv(0, 1)]), **small_model_kwargs())


@pytest.fixture
def trained_model(toy_env):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.learn(200)
    return model


def test_nan_critic_output_stops_training(trained_model, monkeypatch):
    model = trained_model
    disable_representation_updates(model, monkeypatch)
    critic_before = copy.deepcopy(model.critic.state_dict())
    original = type(model.critic).forward
    # NaN Q-values, with and without the clip; +inf Q-values without the clip (with it, Eq. 16 clamps an infinite
    # per-sample loss to V_clip, and the infinite Q then shows up in the actor loss instead).
    for bad, clip in ((float("nan"), 2000.0), (float("nan"), None), (float("inf"), None)):
        model.q_loss_clip = clip
        monkeypatch.setattr(model.critic, "forward", lambda obs, act, bad=bad: original(model.critic, obs, act) + bad)
        with pytest.raises(FloatingPointError, match="critic loss"):
            model.train(1, 8)
    assert_state_equal(model.critic.state_dict(), critic_before, "critic")  # stopped before the optimizer step


def test_infinite_q_with_clip_stops_before_the_critic_step(trained_model, monkeypatch):
    model = trained_model
    disable_representation_updates(model, monkeypatch)
    assert model.q_loss_clip == 2000.0
    critic_before = copy.deepcopy(model.critic.state_dict())
    original = type(model.critic).forward
    monkeypatch.setattr(model.critic, "forward", lambda obs, act: original(model.critic, obs, act) + float("inf"))
    with pytest.raises(FloatingPointError, match="critic loss"):
        model.train(1, 8)
    assert_state_equal(model.critic.state_dict(), critic_before, "critic")


def test_nan_actor_loss_stops_training(trained_model, monkeypatch):
    model = trained_model
    disable_representation_updates(model, monkeypatch)
    original = type(model.critic).forward
    calls = {"n": 0}

    def forward(obs, actions):  # the 2nd critic call of an update evaluates Q at the policy's actions
        calls["n"] += 1
        out = original(model.critic, obs, actions)
        return out * float("nan") if calls["n"] % 2 == 0 else out

    monkeypatch.setattr(model.critic, "forward", forward)
    actor_before = copy.deepcopy(model.actor.state_dict())
    with pytest.raises(FloatingPointError, match="actor loss"):
        model.train(1, 8)
    assert_state_equal(model.actor.state_dict(), actor_before, "actor")


def test_nan_reward_stops_training(trained_model, monkeypatch):
    model = trained_model
    disable_representation_updates(model, monkeypatch)
    model.replay_buffer.rewards[:] = np.nan
    with pytest.raises(FloatingPointError, match="critic loss"):
        model.train(1, 8)


def test_nan_entropy_coefficient_stops_training(trained_model, monkeypatch):
    model = trained_model
    disable_representation_updates(model, monkeypatch)
    with th.no_grad():
        model.log_ent_coef[1] = float("nan")
    with pytest.raises(FloatingPointError, match="entropy coefficient loss"):
        model.train(1, 8)


def test_nan_representation_loss_stops_training(trained_model):
    model = trained_model
    encoder_before = copy.deepcopy(model.encoder.state_dict())
    with th.no_grad():
        model.decoder[0].weight[0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match=r"J\^rep"):
        model.update_representation(8)
    assert_state_equal(model.encoder.state_dict(), encoder_before, "encoder")
    # A NaN in the top-K store's observations is caught the same way (VAE off, so only J^NT sees it).
    with th.no_grad():
        model.decoder[0].weight[0, 0] = 0.0
    model.use_vae = False
    model.replay_buffer._top_k[0].data["observations"][:] = np.nan
    with pytest.raises(FloatingPointError, match=r"J\^rep"):
        model.update_representation(8)
