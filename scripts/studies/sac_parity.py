"""Parity of MTSAC with a single task and SB3's SAC: same hyperparameters, budget, seeds and evaluation.

MTSAC("MlpPolicy") trains on the env with a 1-dim one-hot appended to the observation (``[1.0]``), SB3's
SAC("MlpPolicy") on the same env without it. With N = 1, MTSAC's ``batch_size`` (transitions per task) is SAC's
batch size. Every ``--eval-freq`` env steps (and before training), both are evaluated with deterministic actions
on a separate env built the same way for both:

- ``pendulum``: ``Pendulum-v1``, rl-zoo3's SAC hyperparameters (20k steps, lr 1e-3, SB3's SAC defaults otherwise),
  mean return of ``--eval-episodes`` episodes of an env seeded with ``seed + 1000``;
- ``reach``: Meta-World ``reach-v3`` built by :func:`sb3_mtte.make_mt_env` (SAC gets the same env with the
  one-hot stripped), 2 x 400 nets, batch 128, lr 3e-4; mean return and success of ``--eval-episodes`` full
  500-step episodes on goal variations 0, 1, ... of the seed's 50 (the order ``evaluate_success`` uses; success
  = solved at any step).

Each run writes ``OUT/<env>/<algo>_seed<seed>.json``: the curve (``steps``, ``return``, ``success``),
hyperparameters, seed, wall time, env steps/s and library versions. ``--plot`` draws every run found under OUT
into one figure (mean +- std over seeds): Pendulum return, reach return, reach success::

    python scripts/studies/sac_parity.py --envs pendulum --seeds 0 1 2
    python scripts/studies/sac_parity.py --envs reach --seeds 0 1 2
    python scripts/studies/sac_parity.py --no-train --plot
"""

from __future__ import annotations

import argparse
import copy
import json
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import stable_baselines3
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

import sb3_mtte
from sb3_mtte import MTSAC, make_mt_env
from sb3_mtte.envs import OneHotTaskWrapper, make_env_fns

ALGOS = ("mtsac", "sac")
ENV_IDS = ("pendulum", "reach")

SHARED_HYPERPARAMS: dict[str, Any] = {
    "buffer_size": 1_000_000,
    "tau": 0.005,
    "gamma": 0.99,
    "train_freq": 1,
    "gradient_steps": 1,
    "ent_coef": "auto_1.0",
    "target_entropy": "auto",
    "target_update_interval": 1,
}
HYPERPARAMS: dict[str, dict[str, Any]] = {
    # rl-zoo3 hyperparams/sac.yml, Pendulum-v1: lr 1e-3 and 20k steps; the rest are SB3's SAC defaults.
    "pendulum": {
        **SHARED_HYPERPARAMS,
        "learning_rate": 1e-3,
        "learning_starts": 100,
        "batch_size": 256,
        "policy_kwargs": {"net_arch": [256, 256]},
    },
    # The Meta-World setting of the MT benchmarks; learning starts after 3 episodes of 500 steps.
    "reach": {
        **SHARED_HYPERPARAMS,
        "learning_rate": 3e-4,
        "learning_starts": 1500,
        "batch_size": 128,
        "policy_kwargs": {"net_arch": [400, 400]},
    },
}
DEFAULTS: dict[str, dict[str, int]] = {
    "pendulum": {"steps": 20_000, "eval_freq": 1_000, "eval_episodes": 5},
    # about 5-6 min per run at 1 thread on this project's CPU (28.8 SAC, 36.6 MTSAC training steps per CPU-s)
    "reach": {"steps": 10_000, "eval_freq": 2_000, "eval_episodes": 5},
}


class DropOneHot(gym.ObservationWrapper):
    """Strip the trailing ``n_tasks``-dim one-hot from a multi-task sub-env's observation.

    :param env: a sub-env whose observation is a state followed by the one-hot.
    :param n_tasks: size of the one-hot.
    """

    def __init__(self, env: gym.Env, n_tasks: int = 1) -> None:
        super().__init__(env)
        space = env.observation_space
        assert isinstance(space, spaces.Box)
        self.n_tasks = n_tasks
        self.observation_space = spaces.Box(space.low[:-n_tasks], space.high[:-n_tasks], dtype=space.dtype)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return observation[: -self.n_tasks]


def make_env(env_id: str, algo: str, seed: int) -> VecEnv:
    """The training or evaluation env of ``algo``: one-hot appended for MTSAC, plain for SAC.

    :param env_id: ``"pendulum"`` or ``"reach"``.
    :param algo: ``"mtsac"`` or ``"sac"``.
    :param seed: for reach, the benchmark seed (goal variations); Pendulum envs are seeded by the algorithm.
    """
    if env_id == "pendulum":
        if algo == "mtsac":
            return DummyVecEnv([lambda: Monitor(OneHotTaskWrapper(gym.make("Pendulum-v1")))])
        return DummyVecEnv([lambda: Monitor(gym.make("Pendulum-v1"))])
    if algo == "mtsac":
        return make_mt_env(["reach-v3"], seed=seed)
    env_fn = make_env_fns(["reach-v3"], seed=seed)[0]
    return DummyVecEnv([lambda: Monitor(DropOneHot(env_fn()))])


def evaluate(model: BaseAlgorithm, env: VecEnv, n_episodes: int) -> tuple[float, float | None]:
    """Mean return and success rate (None without ``is_success``) of deterministic episodes on a 1-env VecEnv.

    An env with an evaluation mode (Meta-World) is switched to it first, so episode k uses goal variation k.
    """
    has_eval_mode = env.has_attr("set_eval_mode")
    if has_eval_mode:
        env.env_method("set_eval_mode", True)
    returns, successes = [], []
    obs, episode_return = env.reset(), 0.0
    while len(returns) < n_episodes:
        action, _ = model.predict(obs, deterministic=True)  # type: ignore[arg-type]
        obs, reward, done, infos = env.step(action)
        episode_return += float(reward[0])
        if done[0]:
            returns.append(episode_return)
            episode_return = 0.0
            if "is_success" in infos[0]:
                successes.append(float(infos[0]["is_success"]))
    if has_eval_mode:
        env.env_method("set_eval_mode", False)
    return float(np.mean(returns)), (float(np.mean(successes)) if successes else None)


class ParityEvalCallback(BaseCallback):
    """Evaluate before training and every ``eval_freq`` env steps; keep the curve.

    :param eval_env: the evaluation env (1 sub-env).
    :param eval_freq: env steps between evaluations.
    :param n_episodes: episodes per evaluation.
    """

    def __init__(self, eval_env: VecEnv, eval_freq: int, n_episodes: int) -> None:
        super().__init__()
        self.eval_env, self.eval_freq, self.n_episodes = eval_env, eval_freq, n_episodes
        self.curve: dict[str, list] = {"steps": [], "return": [], "success": []}

    def _evaluate(self) -> None:
        mean_return, success = evaluate(self.model, self.eval_env, self.n_episodes)
        self.curve["steps"].append(int(self.num_timesteps))
        self.curve["return"].append(mean_return)
        self.curve["success"].append(success)

    def _on_training_start(self) -> None:
        self._evaluate()

    def _on_step(self) -> bool:
        if self.num_timesteps % self.eval_freq == 0:
            self._evaluate()
        return True


def build_model(env_id: str, algo: str, seed: int, env: VecEnv) -> BaseAlgorithm:
    """MTSAC or SAC with the env's shared hyperparameters, on CPU (a copy: SB3 adds entries to policy_kwargs)."""
    algo_class: Callable[..., BaseAlgorithm] = MTSAC if algo == "mtsac" else SAC
    return algo_class("MlpPolicy", env, seed=seed, device="cpu", **copy.deepcopy(HYPERPARAMS[env_id]))


def versions() -> dict[str, str]:
    """Versions of the libraries and interpreter the run used."""
    found = {
        "sb3_mtte": sb3_mtte.__version__,
        "stable_baselines3": stable_baselines3.__version__,
        "torch": th.__version__,
        "gymnasium": gym.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    try:
        from importlib.metadata import version

        found["metaworld"] = version("metaworld")
    except Exception:  # pragma: no cover - metaworld is an install requirement
        pass
    return found


def run_one(env_id: str, algo: str, seed: int, steps: int, eval_freq: int, eval_episodes: int) -> dict[str, Any]:
    """Train one run and return its record (curve, hyperparameters, speed, versions)."""
    model = build_model(env_id, algo, seed, make_env(env_id, algo, seed))
    eval_env = make_env(env_id, algo, seed)
    if env_id == "pendulum":
        eval_env.seed(seed + 1000)
    callback = ParityEvalCallback(eval_env, eval_freq, eval_episodes)
    start = time.perf_counter()
    model.learn(steps, callback=callback)
    wall = time.perf_counter() - start
    eval_env.close()
    model.get_env().close()  # type: ignore[union-attr]
    return {
        "env": env_id,
        "algo": algo,
        "seed": seed,
        "steps": steps,
        "eval_freq": eval_freq,
        "eval_episodes": eval_episodes,
        "hyperparams": HYPERPARAMS[env_id],
        "curve": callback.curve,
        "wall_s": wall,
        "steps_per_s": steps / wall,
        "num_threads": th.get_num_threads(),
        "versions": versions(),
    }


def run_path(out: Path, env_id: str, algo: str, seed: int) -> Path:
    return out / env_id / f"{algo}_seed{seed}.json"


def load_runs(out: Path) -> list[dict[str, Any]]:
    """Every run record found under ``out``."""
    return [json.loads(path.read_text()) for path in sorted(out.glob("*/*_seed*.json"))]


def mean_std_curve(records: list[dict[str, Any]], key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Steps, mean and std over seeds of ``curve[key]`` (evaluation points common to all seeds)."""
    curves = [r["curve"] for r in records if r["curve"][key] and r["curve"][key][0] is not None]
    if not curves:
        return None
    n = min(len(c["steps"]) for c in curves)
    values = np.array([c[key][:n] for c in curves], dtype=np.float64)
    return np.asarray(curves[0]["steps"][:n]), values.mean(axis=0), values.std(axis=0)


PANELS = (("pendulum", "return", "(a) Pendulum-v1: return"), ("reach", "return", "(b) reach-v3: return"),
          ("reach", "success", "(c) reach-v3: success rate"))  # fmt: skip
LABELS = {"mtsac": "MTSAC (N = 1, one-hot)", "sac": "SB3 SAC"}


def plot(out: Path, figure: Path) -> None:
    """One figure, three panels: mean +- std over seeds of every algorithm found under ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    records = load_runs(out)
    fig, axes = plt.subplots(1, len(PANELS), figsize=(5 * len(PANELS), 3.8))
    fig.suptitle(
        "MTSAC with one task vs SB3 SAC: identical hyperparameters, budget and seeds (0-2); mean ± std", fontsize=10
    )
    for ax, (env_id, key, title) in zip(axes, PANELS, strict=True):
        for algo in ALGOS:
            group = [r for r in records if r["env"] == env_id and r["algo"] == algo]
            stats = mean_std_curve(group, key)
            if stats is None:
                continue
            steps, mean, std = stats
            (line,) = ax.plot(steps, mean, label=f"{LABELS[algo]} ({len(group)} seeds)")
            ax.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.25)
        if key == "success":
            ax.set_ylim(-0.02, 1.02)
        ax.set_title(title)
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x / 1000:g}k"))
        ax.set_xlabel("env steps")
        ax.set_ylabel(key)
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no runs", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    figure.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(figure, dpi=120)
    plt.close(fig)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", choices=ENV_IDS, default=list(ENV_IDS))
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=None, help="env steps per run (default: per env)")
    parser.add_argument("--eval-freq", type=int, default=None, help="env steps between evaluations")
    parser.add_argument("--eval-episodes", type=int, default=None, help="episodes per evaluation")
    parser.add_argument("--num-threads", type=int, default=1, help="torch.set_num_threads")
    parser.add_argument("--out", type=Path, default=Path("runs/parity"), help="folder of the JSON records")
    parser.add_argument("--no-train", action="store_true", help="run nothing (with --plot: plot existing runs)")
    parser.add_argument("--plot", action="store_true", help="write the figure from every run under --out")
    parser.add_argument("--figure", type=Path, default=Path("docs/figures/sac_parity.png"))
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    th.set_num_threads(args.num_threads)
    if not args.no_train:
        for env_id in args.envs:
            defaults = DEFAULTS[env_id]
            steps = args.steps or defaults["steps"]
            eval_freq = args.eval_freq or defaults["eval_freq"]
            eval_episodes = args.eval_episodes or defaults["eval_episodes"]
            for seed in args.seeds:
                for algo in args.algos:
                    record = run_one(env_id, algo, seed, steps, eval_freq, eval_episodes)
                    path = run_path(args.out, env_id, algo, seed)
                    path.parent.mkdir(parents=True, exist_ok=True)
                    path.write_text(json.dumps(record, indent=1))
                    final = record["curve"]["return"][-1]
                    print(f"{env_id} {algo} seed {seed}: final return {final:.1f}, {record['steps_per_s']:.0f} steps/s")
    if args.plot:
        plot(args.out, args.figure)
        print(f"wrote {args.figure}")


if __name__ == "__main__":
    main()
