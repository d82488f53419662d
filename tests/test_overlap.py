"""The env step overlapped with the update (``overlap_env_step=True``, :mod:`sb3_mtte.common.overlapped_rollout`).

Each step sends its actions, runs its updates and then receives its observations, so the updates of step k sample
the transitions of steps 1 to k - 1. The tests instrument the replay buffer against SB3's order, where they sample
steps 1 to k, and check the same seed, every VecEnv, save and resume, the learning of the toy and the refusals."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import pytest
import torch as th
from conftest import CUDA, all_parameters, small_model_kwargs
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_mtte import MTSAC, MTSACTE, evaluate_success, make_mt_env
from sb3_mtte.envs import EnvPoolVecEnv, OneHotTaskWrapper

N_TASKS = 4  # toy-conflict's
MTSAC_KEYS = ("learning_starts", "batch_size", "buffer_size", "seed", "device")
ROOT = Path(__file__).resolve().parents[1]
OLD_CHECKPOINTS = ROOT / "tests" / "data" / "old_checkpoints"


def build(cls=MTSAC, overlap: bool = True, env=None, **overrides):
    """A small model on the 4-task toy (learning_starts 40, L = 8, 2 x 16 nets)."""
    kwargs = small_model_kwargs(**overrides)
    if cls is MTSAC:
        kwargs = {key: kwargs[key] for key in kwargs if key in MTSAC_KEYS or key in overrides}
        kwargs.setdefault("policy_kwargs", {"net_arch": [16, 16]})
    return cls("MlpPolicy", env or make_mt_env("toy-conflict", seed=0), overlap_env_step=overlap, **kwargs)


def record_draws(model, method: str = "sample") -> list[tuple[int, int]]:
    """Wrap the replay buffer's ``method``: (env steps so far, steps stored per task) at each of its calls."""
    buffer, draws = model.replay_buffer, []
    original = getattr(buffer, method)

    def recorded(*args, **kwargs):
        assert not buffer.full
        draws.append((model.num_timesteps, buffer.pos))
        return original(*args, **kwargs)

    setattr(buffer, method, recorded)
    return draws


def same_parameters(a, b) -> bool:
    first, second = all_parameters(a), all_parameters(b)
    return first.keys() == second.keys() and all(th.equal(first[key], second[key]) for key in first)


@pytest.mark.parametrize("cls", [MTSAC, MTSACTE])
def test_the_same_seed_gives_the_same_run_and_another_than_the_plain_order(cls):
    first, second, plain = (build(cls, overlap).learn(160) for overlap in (True, True, False))  # seeded, trained
    assert first._n_updates == plain._n_updates == 30
    assert same_parameters(first, second)
    assert not same_parameters(first, plain)


@pytest.mark.parametrize(
    "cls, schedule",
    [
        (MTSAC, {}),
        (MTSAC, {"train_freq": 3, "gradient_steps": 2}),
        (MTSAC, {"train_freq": 2, "gradient_steps": -1}),
        (MTSACTE, {}),
    ],
    ids=["every-step", "3-steps-2-updates", "as-many-as-env-steps", "mtsacte"],
)
def test_the_updates_of_step_k_sample_exactly_the_transitions_up_to_step_k_minus_1(cls, schedule):
    """At the same env steps as in SB3's order, and as many; MTSACTE's iterations open at the same steps."""
    draws, openings = {}, {}
    for overlap in (False, True):
        model = build(cls, overlap, **schedule)
        draws[overlap] = record_draws(model)
        openings[overlap] = record_draws(model, "sample_top_k") if cls is MTSACTE else []
        model.learn(120)
    plain, overlapped = draws[False], draws[True]
    assert len(plain) >= 8 and [t for t, _ in overlapped] == [t for t, _ in plain]
    assert all(stored == timesteps // N_TASKS for timesteps, stored in plain)  # SB3: steps 1 to k
    assert [stored for _, stored in overlapped] == [stored - 1 for _, stored in plain]  # here: steps 1 to k - 1
    if cls is MTSACTE:
        assert len(openings[False]) >= 4 and [t for t, _ in openings[True]] == [t for t, _ in openings[False]]


def test_each_step_sends_its_actions_updates_and_then_receives():
    model, events = build(), []
    env = model.get_env()
    for name, method in (("send", env.step_async), ("receive", env.step_wait), ("update", model.train)):
        setattr(env if name != "update" else model, method.__name__, recording(events, name, method))
    model.learn(48)  # 12 steps: the first 10 collect (learning_starts 40), the last two update
    steps = " ".join(events).replace("send receive", "step").split()
    assert steps == ["step"] * 10 + ["send", "update", "receive"] * 2


def recording(events: list[str], name: str, method):
    def recorded(*args, **kwargs):
        events.append(name)
        return method(*args, **kwargs)

    return recorded


def test_every_vec_env_gives_the_same_run():
    """``DummyVecEnv`` (order only), ``SubprocVecEnv`` (the processes step during the update) and ``EnvPoolVecEnv``
    (its pools would; here it holds the toy's envs)."""
    models = [
        build(env=make_mt_env("toy-conflict", seed=0, vec_env_cls=vec_env_cls)).learn(120)
        for vec_env_cls in (DummyVecEnv, SubprocVecEnv, EnvPoolVecEnv)
    ]
    for model in models:
        model.get_env().close()
    assert isinstance(models[1].get_env(), SubprocVecEnv) and isinstance(models[2].get_env(), EnvPoolVecEnv)
    assert same_parameters(models[0], models[1]) and same_parameters(models[0], models[2])


@pytest.mark.parametrize("cls", [MTSAC, MTSACTE])
def test_a_run_saved_with_its_replay_buffer_resumes_exactly(cls, tmp_path):
    """Saved between two ``learn`` calls, loaded with the env where it stopped (not reset): the run continues as the
    one that was not interrupted, and as one ``learn`` call of the whole length."""
    uninterrupted = build(cls).learn(120)
    uninterrupted.save(tmp_path / "model")
    uninterrupted.save_replay_buffer(tmp_path / "buffer")
    uninterrupted.learn(120, reset_num_timesteps=False)
    interrupted = build(cls).learn(120)  # the same run, stopped where the checkpoint was saved
    resumed = cls.load(tmp_path / "model", env=interrupted.get_env(), device="cpu", force_reset=False)
    assert resumed.overlap_env_step is True
    resumed.load_replay_buffer(tmp_path / "buffer")
    resumed.learn(120, reset_num_timesteps=False)
    whole = build(cls).learn(240)
    assert resumed._n_updates == uninterrupted._n_updates == whole._n_updates
    assert same_parameters(resumed, uninterrupted) and same_parameters(whole, uninterrupted)


def test_the_setting_is_off_by_default_and_in_older_checkpoints(tmp_path):
    build(overlap=True).save(tmp_path / "on")
    assert MTSAC.load(tmp_path / "on", device="cpu").overlap_env_step is True
    assert MTSAC("MlpPolicy", make_mt_env("toy-conflict", seed=0), device="cpu").overlap_env_step is False
    for path in sorted(OLD_CHECKPOINTS.glob("*.zip")):  # saved before the setting existed
        cls = MTSACTE if path.stem.startswith("mtsacte") else MTSAC
        assert cls.load(path, device="cpu").overlap_env_step is False, path.stem


def test_what_the_overlapped_order_cannot_run_is_refused_in_one_line(tmp_path):
    with pytest.raises(ValueError, match="overlap_env_step must be True or False"):
        build(overlap="yes")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"empty replay buffer .* set learning_starts >= 4, the number of sub-envs"):
        build(learning_starts=3).learn(40)
    build(learning_starts=4).learn(40)  # the first update finds step 1
    model = build()
    model.learn(80)
    model.save(tmp_path / "model")
    resumed = MTSAC.load(tmp_path / "model", env=make_mt_env("toy-conflict", seed=0), device="cpu")
    with pytest.raises(ValueError, match="or load the replay buffer first"):
        resumed.learn(40, reset_num_timesteps=False)
    single = DummyVecEnv([lambda: OneHotTaskWrapper(gym.make("Pendulum-v1"))])
    with pytest.raises(ValueError, match=r"pass train_freq in steps, e.g. train_freq=1 or \(1, 'step'\)"):
        MTSAC("MlpPolicy", single, train_freq=(1, "episode"), overlap_env_step=True, device="cpu").learn(10)


def test_a_callback_sees_each_step_after_its_updates_and_can_stop_the_run():
    from stable_baselines3.common.callbacks import BaseCallback

    class StopAtStep(BaseCallback):
        def _on_step(self) -> bool:
            self.updates_seen = self.model._n_updates
            return self.num_timesteps < 60

    callback = StopAtStep()
    model = build()
    model.learn(400, callback=callback)
    assert model.num_timesteps == 60 and callback.updates_seen == model._n_updates == 5


@pytest.mark.slow
def test_the_toy_is_still_learned():
    """The budget and bar of ``test_every_variant_learns_the_toy_conflict_env`` (MlpPolicy, per-task critics)."""
    model = MTSAC(
        "MlpPolicy",
        make_mt_env("toy-conflict", seed=0),
        learning_starts=1000,
        batch_size=64,
        learning_rate=1e-3,
        policy_kwargs={"net_arch": [64, 64]},
        overlap_env_step=True,
        seed=0,
        device="cpu",
    )
    model.learn(12_000)
    result = evaluate_success(model, make_mt_env("toy-conflict", seed=100), episodes_per_task=10)
    assert result.mean >= 0.75, result.as_dict()


def test_the_benchmark_times_both_orders_and_writes_its_report(tmp_path):
    """Its dry run, in a process of its own as from the command line (it tunes the process before torch loads)."""
    out = tmp_path / "overlap.json"
    arguments = ["--benchmark", "toy-conflict", "--warm-steps", "80", "--timed-steps", "40", "--rounds", "2"]
    arguments += ["--net-arch", "16", "16", "--batch-size", "8", "--out", str(out)]
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_overlap.py"), *arguments], check=True, cwd=ROOT)
    report = json.loads(out.read_text())
    assert set(report["orders"]) == {"plain", "overlap"}
    assert [len(result["all_env_steps_per_s"]) for result in report["orders"].values()] == [2, 2]
    assert report["command"] == " ".join(["python", "benchmarks/bench_overlap.py", *arguments])
    assert report["orders"]["overlap"]["over_plain"] > 0 and report["versions"]["torch"] == th.__version__


@CUDA
@pytest.mark.parametrize("cls", [MTSAC, MTSACTE])
def test_the_overlap_on_the_fast_path_samples_the_steps_before_each_update(cls):
    draws = {}
    for overlap in (False, True):
        model = build(cls, overlap, device="cuda", update_path="cuda_graph", replay_buffer_kwargs={"storage": "device"})
        draws[overlap] = record_draws(model)
        model.learn(120)
        assert all(th.isfinite(value).all() for value in all_parameters(model).values())
    assert [t for t, _ in draws[True]] == [t for t, _ in draws[False]]
    assert [s for _, s in draws[True]] == [s - 1 for _, s in draws[False]]
