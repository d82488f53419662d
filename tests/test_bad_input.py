"""Mistakes on the training path end with one line naming the fix: the algorithms' arguments and envs, ``learn``
before learning starts, and ``train``'s flags and hyperparameters."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from conftest import ENV, TINY, small_model_kwargs
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_mtte import MTSAC, MTSACTE
from sb3_mtte.common.utils import check_multitask_env, check_one_hot
from sb3_mtte.envs import OneHotTaskWrapper
from sb3_mtte.experiments.cli import main

MTSAC_KWARGS = {"learning_starts": 100, "batch_size": 8, "buffer_size": 1_000, "policy_kwargs": {"net_arch": [16]}}
ALGORITHMS = {"MTSAC": (MTSAC, MTSAC_KWARGS), "MTSACTE": (MTSACTE, small_model_kwargs(learning_starts=100))}


def train_error(tmp_path: Path, *flags: str, algo: str = "mtsacte") -> str:
    """The one line ``train`` ends with on the toy benchmark."""
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--algo", algo, "--env", ENV, "-f", str(tmp_path), "--eval-freq", "-1", *TINY, *flags])
    message = str(exit_info.value.code)
    assert "\n" not in message
    return message


# ============================================================================================ the algorithms
@pytest.mark.parametrize("name", sorted(ALGORITHMS))
@pytest.mark.parametrize("batch_size", [0, -1, 2.5, True])
def test_batch_size_must_be_a_positive_int(toy_env, name, batch_size):
    cls, kwargs = ALGORITHMS[name]
    with pytest.raises(ValueError, match=r"batch_size \(L, .*\) must be a positive int such as 128, got"):
        cls("MlpPolicy", toy_env, **{**kwargs, "batch_size": batch_size})


@pytest.mark.parametrize("learning_rate", [-1, 0, float("nan")])
def test_learning_rate_must_be_positive(toy_env, learning_rate):
    with pytest.raises(ValueError, match=r"learning_rate must be a positive number such as 3e-4 or a schedule"):
        MTSAC("MlpPolicy", toy_env, **MTSAC_KWARGS, learning_rate=learning_rate)


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_learn_that_ends_before_learning_starts_warns_at_the_caller(toy_env, name):
    cls, kwargs = ALGORITHMS[name]
    model = cls("MlpPolicy", toy_env, **kwargs)
    with pytest.warns(UserWarning, match=r"^learn ended at 40 env steps, not past learning_starts=100: no grad") as w:
        model.learn(40)
    assert [record.filename for record in w if "learning_starts" in str(record.message)] == [__file__]
    assert model._n_updates == 0


def test_learn_past_learning_starts_does_not_warn(toy_env):
    model = MTSAC("MlpPolicy", toy_env, **{**MTSAC_KWARGS, "learning_starts": 20})
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="learn ended")
        model.learn(40)
    assert model._n_updates > 0


def test_mtsacte_critics_are_per_task(toy_env):
    with pytest.raises(ValueError, match=r"MTSACTE's critics are per task .*MTSAC\(\.\.\., critic_arch='shared'\)"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(), critic_arch="shared")
    assert MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(), critic_arch="per_task").critic_arch == "per_task"


# ================================================================================================== the envs
def test_a_plain_env_is_refused_naming_make_mt_env_and_the_one_hot_wrapper():
    with pytest.raises(ValueError, match=r"one-hot.*make_mt_env.*OneHotTaskWrapper"):
        MTSAC("MlpPolicy", gym.make("Pendulum-v1"), **MTSAC_KWARGS).learn(10)
    with pytest.raises(ValueError, match=r"at least 2 tasks .*: build the env with make_mt_env"):
        MTSACTE("MlpPolicy", gym.make("Pendulum-v1"), **small_model_kwargs())


def test_the_one_hot_wrapper_is_offered_only_where_one_task_is_enough():
    """Wrapping one single-task env answers an env of one sub-env for MTSAC; it would not answer an env of several
    sub-envs, nor MTSACTE, which needs two tasks."""
    several = DummyVecEnv([lambda: OneHotTaskWrapper(gym.make("CartPole-v1"))] * 5)
    for refuse, pattern in (
        (lambda: check_multitask_env(several), "cannot hold a state"),
        (lambda: check_one_hot(np.zeros((3, 5)), 3), "identity matrix"),
        (lambda: check_multitask_env(DummyVecEnv([lambda: gym.make("Pendulum-v1")]), min_tasks=2), "at least 2"),
    ):
        with pytest.raises(ValueError, match=pattern) as refused:
            refuse()
        assert "make_mt_env" in str(refused.value) and "OneHotTaskWrapper" not in str(refused.value)
    with pytest.raises(ValueError, match=r"identity matrix.*make_mt_env.*OneHotTaskWrapper"):
        check_one_hot(np.zeros((1, 5)), 1)


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_a_gymnasium_vector_env_is_refused_naming_make_mt_env(toy_env, name):
    cls, kwargs = ALGORITHMS[name]
    vector_env = gym.make_vec("Pendulum-v1", num_envs=4)
    with pytest.raises(ValueError, match=r"SyncVectorEnv is a gymnasium VectorEnv, .*make_mt_env"):
        cls("MlpPolicy", vector_env, **kwargs)
    with pytest.raises(ValueError, match=r"gymnasium VectorEnv"):
        cls("MlpPolicy", toy_env, **kwargs).set_env(vector_env)
    vector_env.close()


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
@pytest.mark.parametrize("buffer_size", [1e6, "1e6", 0])
def test_buffer_size_must_be_a_positive_int(toy_env, name, buffer_size):
    cls, kwargs = ALGORITHMS[name]
    expected = r"^buffer_size \(transitions over all tasks\) must be a positive int such as 1_000_000 or int\(1e6\)"
    with pytest.raises(ValueError, match=expected):
        cls("MlpPolicy", toy_env, **{**kwargs, "buffer_size": buffer_size})


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_an_env_name_is_refused_naming_make_mt_env(name):
    cls, kwargs = ALGORITHMS[name]
    with pytest.raises(ValueError, match=r"^env 'MT10' is a name, not a multi-task env: pass make_mt_env\('MT10'\)"):
        cls("MlpPolicy", "MT10", **kwargs)


# ============================================================================================= train's flags
@pytest.mark.parametrize("steps", ["-100", "0"])
def test_train_refuses_a_budget_of_no_env_step(tmp_path, steps):
    message = train_error(tmp_path, "-n", steps)
    assert message.startswith(f"-n {steps}: n must be a positive number of env steps")
    assert not (tmp_path / "mtsacte").exists()


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        ([], r"^--algo is required: one of mtsac mtsacte "),
        (["--algo", "ppo"], r"^--algo ppo is not an algorithm of sb3_mtte: one of mtsac mtsacte "),
        (["--algo", "mtsactee"], r"^--algo mtsactee is not an algorithm of sb3_mtte: did you mean mtsacte\? "),
    ],
)
def test_train_takes_the_package_algorithms_only(tmp_path, flags, expected):
    with pytest.raises(SystemExit, match=expected):
        main(["train", "--env", ENV, "-f", str(tmp_path), *TINY, *flags])


@pytest.mark.parametrize(
    ("algo", "params", "expected"),
    [
        ("mtsacte", "batch_size:0", r"^mtsacte on toy-conflict: batch_size \(L, .*\) must be a positive int"),
        ("mtsac_mt", "batch_size:0", r"^mtsac_mt on toy-conflict: batch_size \(L, .*\) must be a positive int"),
        ("mtsacte", "learning_rate:-1", r"^mtsacte on toy-conflict: learning_rate must be a positive number"),
        ("mtsacte", "n_select:7", r"^mtsacte on toy-conflict: n_select \(M\) must satisfy 1 <= M < N = 4, got 7"),
        ("mtsacte", "critic_arch:'shared'", r"^mtsacte on toy-conflict: MTSACTE's critics are per task"),
        ("mtsacte", "lerning_rate:1e-3", r"^Unknown hyperparameter lerning_rate \(in -params\) of mtsacte: did you me"),
        (
            "mtsac_mt",
            "eval_freqq:100",
            r"^Unknown hyperparameter eval_freqq \(in -params\) of mtsac_mt: did you mean e",
        ),
        ("mtsacte", "seed:3", r"^seed \(in -params\) is not a hyperparameter: set it with the flag --seed\.$"),
        ("mtsacte", "batch_size:abc", r"^-params batch_size:abc: name 'abc' is not defined; each value is Python"),
        ("mtsac_mt", "buffer_size:1e6", r"^mtsac_mt on toy-conflict: buffer_size \(transitions over all tasks\) must"),
    ],
)
def test_train_hyperparameter_mistakes_end_with_one_line(tmp_path, algo, params, expected):
    message = train_error(tmp_path, "-n", "40", "-params", params, algo=algo)
    assert re.search(expected, message), message
    assert not list((tmp_path / algo).glob(f"{ENV}_*")), "a refused start left a run folder"


def test_a_value_error_from_outside_the_package_keeps_its_traceback(tmp_path, monkeypatch):
    """Only the package's and rl-zoo's own refusals become one line; a ValueError raised elsewhere (a bug, not a
    setting) reaches the user with its traceback."""
    from sb3_mtte.experiments.zoo import adapter

    def broken_setup(self):
        return np.zeros(2).reshape(3)

    monkeypatch.setattr(adapter.ExperimentManager, "setup_experiment", broken_setup)
    with pytest.raises(ValueError, match="cannot reshape"):
        main(["train", "--algo", "mtsacte", "--env", ENV, "-f", str(tmp_path), "--eval-freq", "-1", *TINY])


@pytest.mark.parametrize(
    ("env", "kwarg", "expected"),
    [
        (
            ENV,
            "max_episode_step:10",
            "max_episode_step is not an env keyword argument of 'toy-conflict': did you mean "
            "max_episode_steps? valid: n_tasks, max_episode_steps, render_mode.",
        ),
        (
            "MT10-smoke",
            "reward_fn_version:'v1'",
            "reward_fn_version is not an env keyword argument of 'MT10': did you "
            "mean reward_function_version? valid: n_tasks, max_episode_steps,",
        ),
    ],
)
def test_a_misspelled_env_kwargs_key_names_the_nearest_one(tmp_path, env, kwarg, expected):
    with pytest.raises(SystemExit) as exit_info:
        main(
            ["train", "--algo", "mtsac_mt", "--env", env, "-f", str(tmp_path), "-n", "40", *TINY, "--env-kwargs", kwarg]
        )
    assert str(exit_info.value.code).startswith(f"--env-kwargs: {expected}")
    assert not list(tmp_path.rglob("*.csv"))


@pytest.mark.parametrize("episodes", ["0", "-2"])
def test_train_refuses_evaluations_of_no_episode_before_it_starts(tmp_path, episodes):
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--algo", "mtsacte", "--env", ENV, "-f", str(tmp_path), "--eval-episodes", episodes, *TINY])
    message = str(exit_info.value.code)
    assert message == (
        f"mtsacte on toy-conflict: --eval-episodes {episodes}: give at least 1 episode per task, or --eval-freq -1 to "
        "turn the evaluation off."
    )
    assert not list(tmp_path.rglob("*.zip"))


def test_train_names_the_nearest_key_of_a_misspelled_key_in_a_conf_file(tmp_path):
    conf = tmp_path / "my.yml"
    conf.write_text(f"{ENV}:\n  n_timesteps: 40\n  policy: MlpPolicy\n  batch_sise: 64\n")
    message = train_error(tmp_path, "-conf", str(conf))
    assert message == f"Unknown hyperparameter batch_sise (in {conf}) of mtsacte: did you mean batch_size?"


@pytest.mark.parametrize("conf", ["absent.yml", "no_such_package.hyperparams"])
def test_train_refuses_a_missing_conf_file(tmp_path, conf):
    message = train_error(tmp_path, "-conf", conf)
    assert message.startswith(f"-conf {conf}: no such file; give a hyperparameter file (.yml")
