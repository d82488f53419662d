"""Shared fixtures: small MTSACTE networks in float64, task-major batches with fixed noise, and a tiny
multi-task env whose episode returns are known in advance."""

from __future__ import annotations

import sb3_mtte  # first: the package sets OpenMP's spin-wait before torch loads

# isort: split

import importlib.util
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.vec_env import DummyVecEnv
from torch import nn

from sb3_mtte.mtsacte.policies import MTSACTEPolicy
from sb3_mtte.mtsacte.transfer import RepresentationBatch, TaskObjectives


# ---------------------------------------------------------------------------------------------- install
CHECKOUT = Path(__file__).resolve().parent.parent


def checkout_install_problem() -> str | None:
    """Why these tests cannot run, or None: they test this checkout, so ``sb3_mtte`` and its zoo configs (the
    top-level ``zoo_configs/``, installed as ``sb3_mtte.zoo_configs``) must both come from it, as an editable
    install gives them. A plain ``pip install .`` gives neither: the installed copy is tested, or, from the checkout,
    the package is found without its configs."""
    package = Path(sb3_mtte.__file__).resolve().parent
    configs = importlib.util.find_spec("sb3_mtte.zoo_configs")
    origin = None if configs is None or configs.origin is None else Path(configs.origin).resolve()
    if package == CHECKOUT / "sb3_mtte" and origin is not None and origin.is_relative_to(CHECKOUT):
        return None
    found = "without its zoo configs" if package == CHECKOUT / "sb3_mtte" else f"from {package}"
    return (
        f"The tests need sb3_mtte installed from this checkout in editable mode; Python finds it {found}: run "
        f'pip install -e ".[tests]" in {CHECKOUT} (pip install -e . at least), then the tests again.'
    )


def pytest_configure(config: pytest.Config) -> None:
    """Stop before collecting, with one line naming the install, when the checkout is not installed editable."""
    problem = checkout_install_problem()
    if problem is not None:
        pytest.exit(problem, returncode=pytest.ExitCode.USAGE_ERROR)


# --------------------------------------------------------------------------------------------- networks
def make_te_policy(
    n_tasks: int = 4,
    state_dim: int = 3,
    action_dim: int = 2,
    z_dim: int = 3,
    net_arch: list[int] | None = None,
    activation_fn: type[nn.Module] = nn.ReLU,
    seed: int = 0,
    double: bool = True,
    critic_scale: float = 10.0,
) -> MTSACTEPolicy:
    """A small MTSACTE policy (encoder, decoder, actor, per-task twin critics), float64 by default.

    The critics' output layer is scaled by ``critic_scale`` so that the Q-terms (independent per task) dominate
    the entropy terms and the tasks' policy gradients conflict: mu is then neither all 0 nor all N. E_phi's mean head
    keeps PyTorch's scale (``z_mean_init_gain=1``), the setting the hand-checked cases were built on.
    """
    th.manual_seed(seed)
    obs_space = spaces.Box(-np.inf, np.inf, shape=(state_dim + n_tasks,), dtype=np.float32)
    act_space = spaces.Box(-1.0, 1.0, shape=(action_dim,), dtype=np.float32)
    policy = MTSACTEPolicy(
        obs_space,
        act_space,
        lambda _: 1e-3,
        n_tasks=n_tasks,
        net_arch=net_arch or [16, 16],
        activation_fn=activation_fn,
        z_dim=z_dim,
        z_mean_init_gain=1.0,
        optimizer_kwargs={},
    )
    with th.no_grad():
        policy.critic.q_net.layers[-1].weight.mul_(critic_scale)
        policy.critic_target.load_state_dict(policy.critic.state_dict())
    return policy.double() if double else policy


def make_rep_batch(policy: MTSACTEPolicy, batch_size: int = 8, seed: int = 1) -> RepresentationBatch:
    """A task-major batch (N, L, state + one-hot) with its z and action noise, in the policy's dtype."""
    dtype = next(policy.parameters()).dtype
    gen = th.Generator().manual_seed(seed)
    n = policy.n_tasks
    state = th.randn(n, batch_size, policy.state_dim, generator=gen, dtype=dtype)
    one_hot = th.eye(n, dtype=dtype)[:, None, :].expand(n, batch_size, n)
    obs = th.cat([state, one_hot], dim=-1)
    z_noise = th.randn(n, batch_size, policy.z_dim, generator=gen, dtype=dtype)
    action_noise = th.randn(n, batch_size, policy.action_dim, generator=gen, dtype=dtype)
    return RepresentationBatch(obs, z_noise, action_noise)


def make_ent_coef(n_tasks: int, dtype: th.dtype = th.float64) -> th.Tensor:
    """Distinct per-task entropy coefficients beta_i."""
    return th.linspace(0.005, 0.03, n_tasks, dtype=dtype)


@pytest.fixture
def small_setup():
    """``(policy, batch, ent_coef, objectives)``: N=4 tasks, L=8, net_arch=[16, 16], float64.

    With this seed and a step size of 1e-2, mu = [2, 3, 1, 2] (a tie between tasks 0 and 3).
    """
    policy = make_te_policy(seed=6)
    batch = make_rep_batch(policy, seed=106)
    ent_coef = make_ent_coef(policy.n_tasks)
    return policy, batch, ent_coef, TaskObjectives(policy, batch, ent_coef)


def fixed_randn_like(monkeypatch, seed: int = 0):
    """Make ``th.randn_like`` return the same standard normal draw at every call of a given shape (so the noise of
    a reparameterised sample is known); return the function ``draw(shape, dtype)`` that reproduces it."""

    def draw(shape, dtype) -> th.Tensor:
        return th.randn(tuple(shape), generator=th.Generator().manual_seed(seed), dtype=dtype)

    monkeypatch.setattr(th, "randn_like", lambda x, **kwargs: draw(x.shape, x.dtype).to(x.device))
    return draw


def disable_representation_updates(model, monkeypatch) -> None:
    """The next train() calls run SAC updates only (no J^rep step, no recomputation of mu, C_s and w)."""
    monkeypatch.setattr(model, "update_representation", lambda batch_size: None)


# ----------------------------------------------------------------------------------------- environments
def episode_reward(task: int, episode: int, step: int) -> float:
    """Reward of step ``step`` of episode ``episode`` of task ``task``: a multiple of 1/4 (exact in float32)."""
    return ((5 * episode + 3 * task + 2 * step) % 7) * 0.25


def episode_return(task: int, episode: int, length: int) -> float:
    return sum(episode_reward(task, episode, t) for t in range(length))


class EpisodeEnv(gym.Env):
    """Sub-env ``task`` of a multi-task env whose rewards depend only on (task, episode, step), not on the action.

    Observation: (task, step, episode) followed by a one-hot of size ``one_hot_size`` (default ``n_tasks``).
    Episodes are truncated after ``episode_length`` steps.
    """

    def __init__(self, task: int, n_tasks: int, episode_length: int = 5, one_hot_size: int | None = None) -> None:
        self.task, self.episode_length = task, episode_length
        size = n_tasks if one_hot_size is None else one_hot_size
        self.one_hot = np.zeros(size, dtype=np.float32)
        self.one_hot[task] = 1.0
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(3 + size,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.episode, self.t = -1, 0
        self.task_name = f"episode-task-{task}"

    def _obs(self) -> np.ndarray:
        return np.concatenate([np.array([self.task, self.t, self.episode], dtype=np.float32), self.one_hot])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self.episode += 1
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        reward = episode_reward(self.task, self.episode, self.t)
        self.t += 1
        truncated = self.t >= self.episode_length
        return self._obs(), reward, False, truncated, {"is_success": False, "task_index": self.task}


def make_episode_env(n_tasks: int = 4, n_envs: int | None = None, **kwargs: Any) -> DummyVecEnv:
    """DummyVecEnv of ``n_envs`` (default ``n_tasks``) :class:`EpisodeEnv`, sub-env i being task i."""
    n_envs = n_tasks if n_envs is None else n_envs
    return DummyVecEnv([lambda i=i: EpisodeEnv(i, n_tasks, **kwargs) for i in range(n_envs)])


@pytest.fixture
def toy_env():
    """The 4-task toy-conflict env (seed 0)."""
    from sb3_mtte import make_mt_env

    env = make_mt_env("toy-conflict", seed=0)
    yield env
    env.close()


def small_model_kwargs(**overrides: Any) -> dict[str, Any]:
    """Keyword arguments of a small, fast MTSACTE on CPU."""
    kwargs: dict[str, Any] = {
        "learning_starts": 40,
        "batch_size": 8,
        "buffer_size": 4_000,
        "top_k": 3,
        "iteration_length": 10,
        "rep_gradient_steps": 2,
        "policy_kwargs": {"net_arch": [16, 16], "z_dim": 3},
        "seed": 0,
        "device": "cpu",
    }
    kwargs.update(overrides)
    return kwargs


def all_parameters(model) -> dict[str, th.Tensor]:
    """Every trainable tensor of a model: policy state dict (encoder, decoder, actor, critics, targets), beta."""
    params = {f"policy.{k}": v.detach().clone() for k, v in model.policy.state_dict().items()}
    if model.log_ent_coef is not None:
        params["log_ent_coef"] = model.log_ent_coef.detach().clone()
    return params


def assert_state_equal(a: Any, b: Any, path: str = "") -> None:
    """Recursive exact equality of nested dicts / lists / tensors / arrays (optimizer state dicts, ...)."""
    if isinstance(a, th.Tensor):
        assert isinstance(b, th.Tensor), path
        assert a.dtype == b.dtype and a.shape == b.shape, path
        assert th.equal(a, b), path
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=path)
    elif isinstance(a, dict):
        assert set(a) == set(b), path
        for key in a:
            assert_state_equal(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_state_equal(x, y, f"{path}[{i}]")
    else:
        assert a == b, path


# ---------------------------------------------------------------------------------------------------- zoo
CUDA = pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")
ENV = "toy-conflict"
# CPU: on a GPU the resumed runs below would mix eager updates with graph replays, equal only within float tolerance
QUIET_CPU = ["--no-progress", "--verbose", "0", "--device", "cpu"]
TINY = [*QUIET_CPU, "--seed", "3"]


def tiny_train(log_dir: Path, algo: str = "mtsacte", *extra: str, steps: int = 400) -> Path:
    """Train ``algo`` on the 4-task toy for ``steps`` env steps with the zoo; return the run folder."""
    from sb3_mtte.experiments.cli import main

    main(
        [
            "train",
            "--algo",
            algo,
            "--env",
            ENV,
            "-f",
            str(log_dir),
            "-n",
            str(steps),
            "--eval-freq",
            "200",
            "--eval-episodes",
            "2",
            *TINY,
            *extra,
        ]
    )
    runs = sorted((log_dir / algo).glob(f"{ENV}_*"), key=lambda p: int(p.name.rsplit("_", 1)[1]))
    return runs[-1]


def capture_applied_gradients(model, monkeypatch) -> dict:
    """Wrap ``model._apply_gradients`` so that the encoder's and decoder's gradients it applies are kept under "enc"
    and "dec" of the returned dict."""
    captured: dict = {}
    original_apply = model._apply_gradients

    def apply(enc, dec):
        captured["enc"], captured["dec"] = enc, dec
        return original_apply(enc, dec)

    monkeypatch.setattr(model, "_apply_gradients", apply)
    return captured
