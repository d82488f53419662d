"""Tests of the rl-zoo launcher (sb3-mtte train): train, sub-env i = task i, configs, resume, optuna (enjoy and video:
test_zoo_playback.py)."""

from __future__ import annotations

import csv
import inspect
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from conftest import ENV, QUIET_CPU, TINY, tiny_train
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.save_util import load_from_pkl

from sb3_mtte import MTSAC, MTSACTE
from sb3_mtte.common.utils import check_one_hot, get_task_names
from sb3_mtte.experiments.cli import main
from sb3_mtte.experiments.env_ids import MultiTaskVecEnvFactory, make_task_env, register_env_id, split_env_id
from sb3_mtte.experiments.run_info import read_run_info
from sb3_mtte.experiments.variants import VARIANTS, algo_classes
from sb3_mtte.experiments.zoo.configs import zoo_hyperparameters
from sb3_mtte.experiments.zoo.run_checkpoints import find_checkpoints, load_model

ALGO_KEYS = algo_classes()
ALGO_LABELS = {key: variant.label for key, variant in VARIANTS.items()}


class RaiseAt(BaseCallback):
    """Stands for a killed process: raise once ``timesteps`` env steps are reached."""

    def __init__(self, timesteps: int) -> None:
        super().__init__()
        self.timesteps = timesteps

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.timesteps:
            raise RuntimeError("simulated kill")
        return True


# ================================================================================================ the env hook
def test_env_ids_and_budget_suffix():
    assert split_env_id("MT10-smoke") == ("MT10", "smoke")
    assert split_env_id("toy-conflict-6") == ("toy-conflict-6", None)
    assert register_env_id("MT10-smoke") and register_env_id("toy-agree-3")
    assert not register_env_id("CartPole-v1")
    assert not register_env_id("no-such-benchmark")


def test_sub_env_i_is_task_i_through_rl_zoo_style_construction():
    """rl-zoo builds N identical constructors; the factory makes constructor i build task i."""
    register_env_id("toy-agree-3")
    spec = gym.spec("toy-agree-3")
    env = make_vec_env(lambda **kw: spec.make(**kw), n_envs=3, seed=0, vec_env_cls=MultiTaskVecEnvFactory(3, seed=0))
    try:
        assert get_task_names(env) == ["agree-0", "agree-1", "agree-2"]
        check_one_hot(env.reset(), 3)
    finally:
        env.close()
    with pytest.raises(ValueError, match="one sub-env per task"):
        make_vec_env(lambda **kw: spec.make(**kw), n_envs=2, vec_env_cls=MultiTaskVecEnvFactory(3))
    with pytest.raises(gym.error.Error, match="one sub-env per task"):
        spec.make()  # outside the factory, the task is unknown
    assert make_task_env("toy-agree-3", task_index=2).get_wrapper_attr("task_name") == "agree-2"


# ================================================================================================ configs
TABLE1 = {
    "mtsac_ind": ("IndependentPolicy", None),
    "mtsac_mt": ("MlpPolicy", None),
    "mtsac_mh": ("MultiHeadPolicy", None),
    "mtsac_softmod": ("SoftModularPolicy", None),
    "mtsac_moore": ("MOOREPolicy", None),
    "mtsac_paco": ("PaCoPolicy", None),
    "mtsac_clip": ("MlpPolicy", 2000),
    "mtsacte": ("MlpPolicy", 2000),
    "mtsacte_novae": ("MlpPolicy", 2000),
    "mtsacte_noclip": ("MlpPolicy", None),
    "mtsacte_nobestbatch": ("MlpPolicy", 2000),
}
ZOO_KEYS = {"n_timesteps", "policy", "policy_kwargs", "n_envs", "eval_freq", "eval_episodes", "save_freq"}


@pytest.mark.parametrize("algo", sorted(TABLE1))
def test_hyperparameter_file(algo):
    """Every row has the paper's settings (Appendix B) and only arguments its class accepts."""
    config = zoo_hyperparameters(algo)
    assert config is not None
    assert {"MT10", "MT20", "MT10-smoke", "MT20-smoke", "toy-conflict"} <= set(config)
    cls = ALGO_KEYS[algo]
    accepted = set(inspect.signature(cls.__init__).parameters)
    policy, clip = TABLE1[algo]
    for env, n_tasks in (("MT10", 10), ("MT20", 20)):
        full, smoke = config[env], config[f"{env}-smoke"]
        assert int(full["n_timesteps"]) == 5_000_000 * n_tasks
        assert full["batch_size"] == 128
        assert eval(full["policy_kwargs"])["net_arch"] == [400, 400]
        assert full["policy"] == policy and full["q_loss_clip"] == clip
        assert full["eval_episodes"] == 50
        assert int(smoke["n_timesteps"]) < int(full["n_timesteps"]) // 1000
        assert smoke["policy"] == policy and smoke["batch_size"] == 128  # same settings, smaller budget
        if cls is MTSACTE:
            assert full["n_select"] == n_tasks // 2 and full["top_k"] == 30
            assert full["use_vae"] == (algo != "mtsacte_novae")
            assert full["use_topk"] == (algo != "mtsacte_nobestbatch")
        for entry in (full, smoke, config["toy-conflict"]):
            assert set(entry) - ZOO_KEYS <= accepted, set(entry) - ZOO_KEYS - accepted


@pytest.mark.parametrize("algo", sorted(TABLE1))
def test_toy_entry_builds_its_model(algo):
    from sb3_mtte.envs import make_mt_env

    entry = dict(zoo_hyperparameters(algo)["toy-conflict"])
    for key in ZOO_KEYS - {"policy", "policy_kwargs"}:
        entry.pop(key, None)
    entry["policy_kwargs"] = eval(entry["policy_kwargs"])
    model = ALGO_KEYS[algo](env=make_mt_env(ENV), **entry)
    assert model.n_tasks == 4
    assert ALGO_LABELS[algo]


# ================================================================================================ train
def test_train_writes_model_run_info_and_logs(tmp_path):
    run = tiny_train(tmp_path, "mtsacte", "-params", "learning_starts:100")
    assert run == tmp_path / "mtsacte" / f"{ENV}_1"
    model = load_model(run / f"{ENV}.zip")
    assert isinstance(model, MTSACTE) and model.num_timesteps == 400
    info = read_run_info(run)
    assert info["algo"] == "mtsacte" and info["label"] == "Ours" and info["seed"] == 3
    assert info["n_tasks"] == 4 and info["task_names"][-1] == "conflict" and info["episode_length"] == 50
    assert info["finished"] and info["timesteps"] == 400 and info["n_timesteps"] == 400
    assert {"sb3_mtte", "torch", "stable_baselines3", "gymnasium", "metaworld", "numpy"} <= set(info["versions"])
    assert "commit" in info["git"] and info["hyperparams"]["n_select"] == 2
    config = yaml.load((run / ENV / "config.yml").read_text(), Loader=yaml.UnsafeLoader)
    assert config["n_envs"] == 4 and config["eval_freq"] == 200
    with np.load(run / "evaluations.npz") as data:
        assert list(data["timesteps"]) == [200, 400] and data["success_rate"].shape == (2, 4)
    with open(run / "progress.csv") as file:
        header = next(csv.reader(file))
    assert "train/critic_loss/03_conflict" in header and "eval/success_rate" in header
    assert list(run.glob("events.out.tfevents.*"))
    records = [json.loads(line) for line in (run / "negative_transfer.jsonl").read_text().splitlines()]
    assert records and len(records[0]["transfer_matrix"]) == 4
    assert (run / "best_model.zip").is_file()


def test_train_mtsac_row_and_checkpoints(tmp_path):
    run = tiny_train(tmp_path, "mtsac_mh", "--save-freq", "200", "--keep-buffers", "0", steps=600)
    model = load_model(run / f"{ENV}.zip")
    assert isinstance(model, MTSAC) and type(model.policy).__name__ == "MultiHeadPolicy"
    assert read_run_info(run)["label"] == "SAC-MT-MH"
    checkpoints = find_checkpoints(run)  # taken after the update of a step: none at the last step
    assert [c.timesteps for c in checkpoints] == [200, 400]
    assert all(c.meta["episode_boundary"] and c.replay_buffer is not None for c in checkpoints)


# ================================================================================================ resume
def _progress(run: Path) -> list[dict[str, str]]:
    with open(run / "progress.csv") as file:
        return list(csv.DictReader(file))


def test_resume_of_a_folder_that_is_not_a_run_names_the_fix(tmp_path):
    from sb3_mtte.experiments.cli import main

    with pytest.raises(SystemExit, match=r"not a run folder \(no run_info.json\); give <log folder>/<algo>/<env>_<id>"):
        main(["train", "--resume", str(tmp_path)])


def test_a_benchmark_without_hyperparameters_or_a_resume_without_a_run_names_the_fix(tmp_path):
    from sb3_mtte.experiments.cli import main

    with pytest.raises(SystemExit, match=r"mtsac_mt has no hyperparameters for MT50 \(its entries: .*MT10"):
        main(["train", "--algo", "mtsac_mt", "--env", "MT50", "-f", str(tmp_path)])
    with pytest.raises(SystemExit, match=r"No run of mtsac_mt on toy-conflict in .* to resume: give -f of your runs"):
        main(["train", "--algo", "mtsac_mt", "--env", "toy-conflict", "-f", str(tmp_path), "--resume"])


def test_a_second_run_into_the_folder_of_an_unfinished_run_names_resume(tmp_path):
    killer = f"callback:{{'{RaiseAt.__module__}.RaiseAt': dict(timesteps=60)}}"
    with pytest.raises(RuntimeError, match="simulated kill"):
        tiny_train(tmp_path, "mtsac_mt", "--exp-id", "1", "-params", killer, steps=100)
    run_dir = tmp_path / "mtsac_mt" / f"{ENV}_1"
    with pytest.raises(SystemExit, match=f"{run_dir} already holds a run: use --resume {run_dir}."):
        tiny_train(tmp_path, "mtsac_mt", "--exp-id", "1", steps=100)


def test_the_same_command_again_on_a_finished_run_does_nothing_and_exits_0(tmp_path, capsys):
    """The README's main job names its run folder (--exp-id 1): a second identical command says the run is finished
    and leaves it as it is; one with other settings is refused, naming the first difference."""
    run_dir = tiny_train(tmp_path, "mtsac_mt", "--exp-id", "1", "--save-freq", "100", steps=200)
    before = {path.name: path.stat().st_mtime_ns for path in run_dir.rglob("*")}
    capsys.readouterr()
    assert tiny_train(tmp_path, "mtsac_mt", "--exp-id", "1", "--save-freq", "100", steps=200) == run_dir
    assert f"{run_dir} holds this run, finished at 200 env steps: nothing to do" in capsys.readouterr().out
    assert {path.name: path.stat().st_mtime_ns for path in run_dir.rglob("*")} == before
    with pytest.raises(SystemExit, match=r"holds a finished run with other settings \(--seed: 3 there, 4 here\)"):
        tiny_train(tmp_path, "mtsac_mt", "--exp-id", "1", "--save-freq", "100", "--seed", "4", steps=200)
    with pytest.raises(SystemExit, match=r"other settings \(-params batch_size: 64 there, 16 here\): give another"):
        tiny_train(tmp_path, "mtsac_mt", "--exp-id", "1", "--save-freq", "100", "-params", "batch_size:16", steps=200)
    assert sorted(path.name for path in (tmp_path / "mtsac_mt").iterdir()) == [run_dir.name]


def test_resuming_a_finished_run_does_nothing(tmp_path, capsys):
    """No retraining of the last segment from the last checkpoint, no new final model, no resume recorded."""
    run_dir = tiny_train(tmp_path, "mtsac_mt", "--save-freq", "100", steps=200)
    before = {path.name: path.stat().st_mtime_ns for path in run_dir.rglob("*")}
    capsys.readouterr()
    main(["train", "--resume", str(run_dir)])
    assert f"{run_dir} is finished (200 of 200 env steps): nothing to do; -n above 200" in capsys.readouterr().out
    assert {path.name: path.stat().st_mtime_ns for path in run_dir.rglob("*")} == before
    assert read_run_info(run_dir)["resumes"] == []


def test_a_resume_without_config_names_it_and_leaves_the_folder_as_it_was(tmp_path):
    run_dir = tiny_train(tmp_path, "mtsac_mt", "--save-freq", "100", steps=200)
    (run_dir / ENV / "config.yml").unlink()
    before = sorted(path.name for path in run_dir.iterdir())
    with pytest.raises(SystemExit, match=r"Cannot resume: .*config.yml not found"):
        tiny_train(tmp_path, "mtsac_mt", "--resume", str(run_dir))
    assert sorted(path.name for path in run_dir.iterdir()) == before  # no monitor file set aside


def test_resume_after_kill_matches_uninterrupted_run(tmp_path):
    """Kill a run after its checkpoint at 400 steps, resume it: everything equals the uninterrupted run."""
    args = ["--save-freq", "200", "--save-replay-buffer", "-params", "learning_starts:100"]
    run_a = tiny_train(tmp_path / "a", "mtsacte", *args, steps=800)
    killer = f"{RaiseAt.__module__}.RaiseAt"
    with pytest.raises(RuntimeError, match="simulated kill"):
        tiny_train(tmp_path / "b", "mtsacte", *args, f"callback:{{'{killer}': dict(timesteps=560)}}", steps=800)
    run_b = tmp_path / "b" / "mtsacte" / f"{ENV}_1"
    assert [c.timesteps for c in find_checkpoints(run_b)] == [400]  # killed after the checkpoint at 400
    assert not (run_b / f"{ENV}.zip").exists()
    # the state at the checkpoint is the uninterrupted run's state at that step
    ckpt_a, ckpt_b = load_model(run_a / "rl_model_400_steps.zip"), load_model(run_b / "rl_model_400_steps.zip")
    assert ckpt_a.num_timesteps == ckpt_b.num_timesteps == 400 and ckpt_a._n_updates == ckpt_b._n_updates
    for key, value in ckpt_a.policy.state_dict().items():
        assert th.equal(value, ckpt_b.policy.state_dict()[key]), key

    # the kill came from a hyperparameter, which the resumed run would read back from config.yml: drop it
    resume = ["train", "--algo", "mtsacte", "--env", ENV, "-f", str(tmp_path / "b"), "--resume", *QUIET_CPU]
    main([*resume, "-params", "callback:None"])
    model_a, model_b = load_model(run_a / f"{ENV}.zip"), load_model(run_b / f"{ENV}.zip")
    assert model_a.num_timesteps == model_b.num_timesteps == 800
    assert model_a._n_updates == model_b._n_updates
    for key, value in model_a.policy.state_dict().items():  # the next updates were the same, to the last bit
        assert th.equal(value, model_b.policy.state_dict()[key]), key
    buffer_a, buffer_b = load_from_pkl(run_a / "replay_buffer.pkl"), load_from_pkl(run_b / "replay_buffer.pkl")
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        assert np.array_equal(getattr(buffer_a, name), getattr(buffer_b, name)), name
    assert np.array_equal(buffer_a.n_episodes, buffer_b.n_episodes)
    for task in range(4):  # the top-K store lives in the buffer and is restored with it
        assert np.array_equal(buffer_a.top_k_returns(task), buffer_b.top_k_returns(task))
    # the logs continue as if never interrupted
    assert (run_a / "negative_transfer.jsonl").read_text() == (run_b / "negative_transfer.jsonl").read_text()
    with np.load(run_a / "evaluations.npz") as ea, np.load(run_b / "evaluations.npz") as eb:
        assert np.array_equal(ea["timesteps"], eb["timesteps"])
        assert np.array_equal(ea["success_rate"], eb["success_rate"])
    rows_a, rows_b = _progress(run_a), _progress(run_b)
    assert [r["time/total_timesteps"] for r in rows_a] == [r["time/total_timesteps"] for r in rows_b]
    for row_a, row_b in zip(rows_a, rows_b, strict=True):
        for key, value in row_a.items():
            if not key.startswith("time/"):
                assert row_b.get(key) == value, (row_a["time/total_timesteps"], key)
    info = read_run_info(run_b)
    assert info["finished"] and [r["timesteps"] for r in info["resumes"]] == [400]
    assert list(run_b.glob("*.seg1.monitor.csv"))


def test_resume_of_a_finished_run_with_a_larger_budget(tmp_path):
    run = tiny_train(tmp_path, "mtsac_mt", "--save-freq", "200", "--save-replay-buffer", steps=200)
    main(["train", "--resume", str(run), "-n", "400", *QUIET_CPU])  # algo and env from the run folder
    assert read_run_info(run)["resumes"][0]["timesteps"] == 200  # from the final model and its buffer
    assert load_model(run / f"{ENV}.zip").num_timesteps == 400
    with np.load(run / "evaluations.npz") as data:
        assert list(data["timesteps"]) == [200, 400]


def test_a_resumed_run_keeps_its_progress_bar_setting(tmp_path, monkeypatch):
    from sb3_mtte.experiments.zoo import launcher

    run = tiny_train(tmp_path, "mtsac_mt", steps=100)  # started with --no-progress
    argvs = []
    monkeypatch.setattr(launcher, "run_zoo_train", lambda argv, launch: argvs.append(argv))
    main(["train", "--resume", str(run)])
    main(["train", "--resume", str(run), "-P"])
    info = read_run_info(run)
    info["zoo_args"]["progress"] = True  # a run started with the bar
    (run / "run_info.json").write_text(json.dumps(info))
    main(["train", "--resume", str(run)])
    main(["train", "--resume", str(run), "--no-progress"])
    assert ["-P" in argv for argv in argvs] == [False, True, True, False]


def test_best_model_is_the_latest_of_equal_evaluations(tmp_path, monkeypatch):
    """Every evaluation at 0 success: best_model.zip is the model of the last evaluation, not of the first."""
    from sb3_mtte import evaluation
    from sb3_mtte.envs import make_mt_env
    from sb3_mtte.experiments.zoo.training_callbacks import ZooEvalCallback

    def no_success(model, env, episodes_per_task, deterministic):
        return evaluation.SuccessResult(get_task_names(env), np.zeros(4), episodes_per_task=episodes_per_task)

    monkeypatch.setattr(evaluation, "evaluate_success", no_success)
    model = MTSAC("MlpPolicy", make_mt_env(ENV), learning_starts=20, buffer_size=200, batch_size=32, seed=0)
    callback = ZooEvalCallback(make_mt_env(ENV), eval_freq=25, best_model_save_path=tmp_path)
    model.learn(300, callback=callback)
    assert callback.evaluations_timesteps == [100, 200, 300]
    assert MTSAC.load(tmp_path / "best_model.zip").num_timesteps == 300


def test_the_last_evaluation_and_best_model_are_one_update_behind_the_final_model(tmp_path, monkeypatch):
    """SB3's order: a vector step's callbacks run before that step's update, so the evaluation at the final step
    (and best_model.zip saved by it) sees the model before its last gradient step (docs/guide/train.md, "The run
    folder")."""
    from sb3_mtte import evaluation
    from sb3_mtte.envs import make_mt_env
    from sb3_mtte.experiments.zoo.training_callbacks import ZooEvalCallback

    seen = []

    def no_success(model, env, episodes_per_task, deterministic):
        seen.append((model.num_timesteps, model._n_updates))
        return evaluation.SuccessResult(get_task_names(env), np.zeros(4), episodes_per_task=episodes_per_task)

    monkeypatch.setattr(evaluation, "evaluate_success", no_success)
    model = MTSAC("MlpPolicy", make_mt_env(ENV), learning_starts=20, buffer_size=200, batch_size=32, seed=0)
    model.learn(300, callback=ZooEvalCallback(make_mt_env(ENV), eval_freq=25, best_model_save_path=tmp_path))
    assert seen[-1] == (300, model._n_updates - model.gradient_steps) and model.gradient_steps == 1
    assert MTSAC.load(tmp_path / "best_model.zip")._n_updates == model._n_updates - 1


# ================================================================================================ optuna
def test_optuna_search_runs_through_the_zoo_and_scores_success(tmp_path, monkeypatch):
    """A trial's value is the mean success over tasks of Meta-World's protocol (here a stand-in evaluation that
    scores 0.625 with the run's episodes per task), not rl-zoo's mean return."""
    from sb3_mtte.evaluation import SuccessResult
    from sb3_mtte.experiments.zoo import training_callbacks as callbacks

    calls = []

    def stand_in(model, env, episodes_per_task, deterministic):
        calls.append(episodes_per_task)
        return SuccessResult(get_task_names(env), np.array([1.0, 0.5, 0.5, 0.5]), episodes_per_task=episodes_per_task)

    monkeypatch.setattr(callbacks, "evaluate_success", stand_in)
    main(
        [
            "train",
            "--algo",
            "mtsac_mt",
            "--env",
            ENV,
            "-f",
            str(tmp_path),
            "-optimize",
            "--n-trials",
            "1",
            "-n",
            "200",
            "--n-evaluations",
            "1",
            "--eval-episodes",
            "1",
            "--no-optim-plots",
            "--sampler",
            "random",
            "--pruner",
            "none",
            *TINY,
        ]
    )
    (report,) = (tmp_path / "mtsac_mt").glob("report_*.csv")
    with open(report) as file:
        (trial,) = csv.DictReader(file)
    assert calls == [1] and float(trial["value"]) == 0.625


def test_meta_world_steps_one_process_per_task_from_four_cores_up_to_four_tasks_a_core():
    from sb3_mtte.experiments.env_ids import default_vec_env

    assert default_vec_env("MT10", cpu_count=4) == default_vec_env("MT10-cpu", cpu_count=11) == "subproc"
    assert default_vec_env("MT50", cpu_count=16) == default_vec_env("MT50", cpu_count=13) == "subproc"  # 5.9x on 16
    assert default_vec_env("MT10", cpu_count=3) == default_vec_env("MT50", cpu_count=2) == "dummy"
    assert default_vec_env("MT50", cpu_count=12) == "dummy"  # more than four tasks a core
    assert default_vec_env("reach-v3", cpu_count=16) == "dummy"  # one task: nothing to step in parallel
    assert default_vec_env("toy-conflict", cpu_count=64) == "dummy"


def test_a_run_stepped_in_subprocesses_resumes_to_the_numbers_of_one_stepped_in_one_process(tmp_path):
    """SubprocVecEnv (killed after its checkpoint at 200 steps and resumed) ends where DummyVecEnv ends, bit for bit."""
    args = ["--save-freq", "200", "--save-replay-buffer", "-params", "learning_starts:100"]
    dummy = tiny_train(tmp_path / "a", "mtsac_mt", "--vec-env", "dummy", *args, steps=400)
    killer = f"{RaiseAt.__module__}.RaiseAt"
    with pytest.raises(RuntimeError, match="simulated kill"):
        tiny_train(
            tmp_path / "b",
            "mtsac_mt",
            "--vec-env",
            "subproc",
            *args,
            f"callback:{{'{killer}': dict(timesteps=300)}}",
            steps=400,
        )
    resume = ["train", "--algo", "mtsac_mt", "--env", ENV, "-f", str(tmp_path / "b"), "--resume", *QUIET_CPU]
    main([*resume, "-params", "callback:None"])
    run = tmp_path / "b" / "mtsac_mt" / f"{ENV}_1"
    assert "subproc" in (run / ENV / "args.yml").read_text()  # the resumed run kept its processes
    a, b = load_model(dummy / f"{ENV}.zip"), load_model(run / f"{ENV}.zip")
    assert a.num_timesteps == b.num_timesteps == 400 and read_run_info(run)["resumes"]
    assert all(th.equal(value, b.policy.state_dict()[key]) for key, value in a.policy.state_dict().items())
