"""Tests of Meta-World's own options: its reward functions, its MT25 and any list of its tasks, from make_mt_env to
the zoo's runs, records and Table 1."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import TINY

from sb3_mtte.envs import MT10_TASKS, MT25_TASKS, get_task_names, make_env_fns, make_mt_env
from sb3_mtte.experiments.cli import main
from sb3_mtte.experiments.env_ids import benchmark_help, env_id_n_tasks, make_task_env, register_env_id
from sb3_mtte.experiments.results import records
from sb3_mtte.experiments.results.runs import Run, group_runs
from sb3_mtte.experiments.results.tables import benchmark_statistics, table1
from sb3_mtte.experiments.run_info import read_run_info
from sb3_mtte.experiments.variants import VARIANTS
from sb3_mtte.experiments.zoo.configs import PER_TASK_KEYS, zoo_hyperparameters
from sb3_mtte.experiments.zoo.run_checkpoints import load_model

PAIR = ["reach-v3", "push-v3"]
SAMPLES = Path(__file__).resolve().parent / "data" / "records"


def _rewards(env, n_steps: int) -> np.ndarray:
    """Rewards of ``n_steps`` vector steps of seeded random actions, after a reset."""
    rng = np.random.default_rng(0)
    env.reset()
    actions = rng.uniform(-1, 1, size=(n_steps, env.num_envs, 4)).astype(np.float32)
    return np.stack([env.step(action)[1] for action in actions])


# ================================================================================================ reward functions
def test_reward_function_version_reaches_metaworld_and_changes_the_rewards():
    """Every Meta-World env gets the version (v2 by default); the same seed and actions give other rewards under v1."""
    rewards = {}
    for version in ("v2", "v1", None):
        kwargs = {} if version is None else {"reward_function_version": version}
        env = make_mt_env(PAIR, seed=0, max_episode_steps=10, **kwargs)
        assert env.get_attr("reward_function_version") == [version or "v2"] * 2
        rewards[version] = _rewards(env, 10)
        env.close()
    np.testing.assert_array_equal(rewards[None], rewards["v2"])
    assert not np.allclose(rewards["v1"], rewards["v2"])


def test_a_reward_function_meta_world_lacks_is_refused_naming_the_valid_ones():
    with pytest.raises(ValueError, match=r"^reward_function_version='v3' is not a Meta-World v3 reward function: use "):
        make_env_fns(PAIR, reward_function_version="v3")
    with pytest.raises(ValueError, match=r"'v2' or 'v1' \(the default is 'v2'\)\.$"):
        make_env_fns("MT10", reward_function_version=2)
    with pytest.raises(ValueError, match="reward_function_version is a Meta-World option: leave it out for 'toy"):
        make_env_fns("toy-conflict", reward_function_version="v1")


# ================================================================================================ MT25 and task lists
def test_mt25_is_metaworlds_list_and_an_env_id():
    from metaworld.env_dict import MT25_V3

    assert MT25_TASKS == list(MT25_V3) and MT25_TASKS[:10] == MT10_TASKS
    assert register_env_id("MT25-smoke") and env_id_n_tasks("MT25-smoke") == 25
    assert "MT25" in benchmark_help()


@pytest.mark.slow
def test_mt25_builds_one_sub_env_and_one_hot_entry_per_task():
    """Meta-World draws MT25's goal variations in about 30 s on 2 cores."""
    env = make_mt_env("MT25", seed=0)
    obs = env.reset()
    assert env.num_envs == 25 and get_task_names(env) == MT25_TASKS
    assert obs.shape == (25, 39 + 25)
    np.testing.assert_array_equal(obs[:, 39:], np.eye(25, dtype=np.float32))
    env.close()


def test_a_task_list_is_names_joined_by_underscores_and_an_unknown_name_names_the_nearest():
    assert len(make_env_fns("reach-v3_push-v3")) == 2 and len(make_env_fns("reach-v3")) == 1
    assert register_env_id("reach-v3_push-v3-smoke") and env_id_n_tasks("reach-v3_push-v3-smoke") == 2
    assert not register_env_id("rech-v3_push-v3")
    with pytest.raises(ValueError, match=r"^Unknown Meta-World v3 env name 'rech-v3' \(nearest: reach-v3, reach-wall"):
        make_env_fns("rech-v3_push-v3")
    with pytest.raises(ValueError, match="distinct"):
        make_env_fns("reach-v3_reach-v3")


# ================================================================================================ zoo entries
@pytest.mark.parametrize("algo", sorted(VARIANTS))
def test_mt25_entries_are_mt20s_settings_per_task(algo):
    """MT25 and MT25-smoke: MT20's entries with every quantity per task kept (25 tasks instead of 20), M = N // 2."""
    entries = zoo_hyperparameters(algo)
    for mt25, mt20 in (("MT25", "MT20"), ("MT25-smoke", "MT20-smoke")):
        expected = {key: value * 25 / 20 if key in PER_TASK_KEYS else value for key, value in entries[mt20].items()}
        if "n_select" in expected:
            expected["n_select"] = 12
        assert entries[mt25] == expected


@pytest.mark.parametrize("algo", sorted(VARIANTS))
def test_a_task_list_takes_mt10s_entry_scaled_to_its_tasks(algo):
    env_ids = ["reach-v3_push-v3_door-open-v3", "reach-v3_push-v3-cpu", "toy-conflict-3-smoke"]
    entries = zoo_hyperparameters(algo, env_ids)
    assert "toy-conflict-3-smoke" not in entries  # toy-conflict has no -smoke entry to scale
    for env_id, reference, n_tasks in ((env_ids[0], "MT10", 3), (env_ids[1], "MT10-cpu", 2)):
        entry, base = entries[env_id], entries[reference]
        for key in PER_TASK_KEYS:
            assert entry[key] == base[key] * n_tasks / 10 and type(entry[key]) is type(base[key])
        if "n_select" in base:
            assert entry.pop("n_select") == n_tasks // 2 and base.pop("n_select") == 5
        assert {k: v for k, v in entry.items() if k not in PER_TASK_KEYS} == {
            k: v for k, v in base.items() if k not in PER_TASK_KEYS
        }


# ================================================================================================ train
def test_a_task_list_trains_on_v1_rewards_with_the_scaled_entry(tmp_path):
    """An env id of Meta-World names trains one sub-env per task; --env-kwargs reward_function_version reaches the
    envs (rl-zoo hands env_kwargs to the registered entry point) and run_info.json."""
    sub_env = make_task_env("reach-v3_push-v3", task_index=1, reward_function_version="v1")
    assert sub_env.unwrapped.reward_function_version == "v1"
    env_id = "reach-v3_push-v3-smoke"
    argv = ["train", "--algo", "mtsac_mt", "--env", env_id, "-f", str(tmp_path), "-n", "200", "--eval-freq", "0"]
    small = ["learning_starts:160", "policy_kwargs:dict(net_arch=[64, 64])"]
    main([*argv, "--env-kwargs", "reward_function_version:'v1'", "-params", *small, *TINY])
    run = tmp_path / "mtsac_mt" / f"{env_id}_1"
    info = read_run_info(run)
    assert info["task_names"] == PAIR and info["n_tasks"] == 2 and info["reward_function_version"] == "v1"
    assert info["hyperparams"]["buffer_size"] == 20_000 and info["hyperparams"]["save_freq"] == 1000
    model = load_model(run / f"{env_id}.zip")
    assert model.n_tasks == 2 and model.num_timesteps == 200 and model._n_updates == 20


@pytest.mark.parametrize(
    ("env_id", "env_kwargs", "message"),
    [
        ("MT10-smoke", "reward_function_version:'v3'", "--env-kwargs: reward_function_version='v3' is not a Meta"),
        ("toy-conflict", "reward_function_version:'v1'", "--env-kwargs: reward_function_version is a Meta-World"),
        ("rech-v3_push-v3", None, "'rech-v3_push-v3' is not a benchmark of sb3_mtte: Unknown Meta-World v3 env name "),
    ],
)
def test_train_refuses_a_bad_option_in_one_line_before_any_folder(tmp_path, env_id, env_kwargs, message):
    argv = ["train", "--algo", "mtsac_mt", "--env", env_id, "-f", str(tmp_path), *TINY]
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, *(["--env-kwargs", env_kwargs] if env_kwargs else [])])
    assert str(exit_info.value.code).startswith(message) and "\n" not in str(exit_info.value.code)
    assert not list(tmp_path.iterdir())


# ================================================================================================ records and tables
def test_reward_functions_are_recorded_and_named_in_the_caption_and_never_share_a_table(tmp_path):
    """A record without the field counts as v2 (every record before it was made on Meta-World's default); a run on v1
    rewards is recorded under <env id>-reward-v1/ and drawn as a benchmark of its own; a toy's caption names none."""
    meta_world = Run(tmp_path, {"task_names": PAIR, "reward_function_version": "v1"})
    assert records.run_record(meta_world)["reward_function_version"] == "v1"
    assert Run(tmp_path, {"task_names": PAIR}).reward_function_version == "v2"
    assert Run(tmp_path, {"task_names": ["agree-0", "conflict"]}).reward_function_version is None
    source = tmp_path / "records"
    shutil.copytree(SAMPLES, source)
    v1 = json.loads((SAMPLES / "MT10-cpu" / "mtsac_mt_seed0.json").read_text())
    v1.update(reward_function_version="v1", started="2030-01-01T00:00:00+00:00")
    path = records.record_path(v1, source)
    assert path.parent.name == "MT10-cpu-reward-v1"
    path.parent.mkdir()
    path.write_text(json.dumps(v1))
    groups = group_runs(records.load_runs([source]))
    assert set(groups) == {"MT10-cpu", "MT10-cpu-reward-v1", "toy-conflict"}
    assert records.run_from_record(v1, path).reward_function_version == "v1"
    for bench, caption, n_sac_mt in (("MT10-cpu", "v2", 2), ("MT10-cpu-reward-v1", "v1", 1), ("toy-conflict", None, 3)):
        table = table1(bench, benchmark_statistics(groups[bench], reps=5), reps=5)
        assert f"| SAC-MT | {n_sac_mt} |" in table
        assert (f" Meta-World reward function {caption}. " in table) if caption else "reward function" not in table
