"""The meaning of ``-n`` in each command's help, the zoo entries of every toy, the nearest env id in ``sweep``'s
refusal, and what a record keeps of the envs and the device it trained on (kept apart in the tables)."""

from __future__ import annotations

import json
import shutil
import socket
from pathlib import Path

import pytest
from conftest import QUIET_CPU

from sb3_mtte.experiments import cli
from sb3_mtte.experiments.results import records
from sb3_mtte.experiments.results.runs import Run, device_type_of, group_runs, load_run
from sb3_mtte.experiments.results.tables import benchmark_statistics, table1
from sb3_mtte.experiments.zoo import sweep
from sb3_mtte.experiments.zoo.configs import missing_entries_message, zoo_hyperparameters
from sb3_mtte.experiments.zoo.parsers import TRAIN_STEPS_HELP, ZooParser

SAMPLES = Path(__file__).resolve().parent / "data" / "records"
ENVPOOL = {"backend": "envpool", "label": "EnvPool (fresh goals)", "benchmark_protocol": False}
METAWORLD = {"backend": "metaworld", "label": "Meta-World", "benchmark_protocol": True}


def help_text(capsys, argv: list[str]) -> str:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(argv)
    assert exit_info.value.code == 0
    return " ".join(capsys.readouterr().out.split())


# ================================================================================================ -n in the help
def test_only_trains_steps_help_says_env_steps_over_all_tasks(capsys):
    assert TRAIN_STEPS_HELP in help_text(capsys, ["train", "--help"])
    enjoy = help_text(capsys, ["enjoy", "--help"])
    assert TRAIN_STEPS_HELP not in enjoy and "vector steps" in enjoy
    for launcher_options, expected in ((True, TRAIN_STEPS_HELP), (False, "rl-zoo's own")):
        parser = ZooParser(launcher_options=launcher_options)
        assert parser.add_argument("-n", "--n-timesteps", help="rl-zoo's own").help == expected


# ================================================================================================ toy entries
@pytest.mark.parametrize("algo", ["mtsacte", "mtsac_mt"])
def test_every_toy_gets_toy_conflicts_entry_scaled_to_its_tasks(algo):
    entries = zoo_hyperparameters(algo, ["toy-agree", "toy-agree-1", "toy-conflict-6", "toy-conflict-1"])
    reference = entries["toy-conflict"]
    assert entries["toy-agree"] == reference  # the same 4 tasks
    for env_id, n_tasks in (("toy-agree-1", 1), ("toy-conflict-6", 6)):
        entry = entries[env_id]
        for key in ("n_timesteps", "buffer_size", "learning_starts", "eval_freq", "save_freq"):
            assert entry[key] == reference[key] * n_tasks // 4, (env_id, key)
        if algo == "mtsacte":
            assert entry["n_select"] == max(n_tasks // 2, 1)
    assert "toy-conflict-1" not in entries  # too few tasks: refused as an env id


def test_a_missing_entry_ends_with_a_full_sentence():
    message = missing_entries_message("mtsacte", ["toy-agree-smoke"])
    assert message.endswith(": pass -conf <file>.yml that has an entry for toy-agree-smoke."), message
    assert missing_entries_message("mtsacte", ["toy-agree-1", "toy-conflict-6"]) is None


@pytest.mark.filterwarnings("ignore:learn ended at")
def test_toys_of_any_task_count_train_and_are_recorded_with_their_device(tmp_path):
    tiny = ["-f", str(tmp_path), "--eval-freq", "-1", *QUIET_CPU]
    cli.main(["train", "--algo", "mtsac_mt", "--env", "toy-agree-1", "-n", "20", *tiny])
    cli.main(["train", "--algo", "mtsacte", "--env", "toy-conflict-6", "-n", "60", *tiny])
    run_dir = tmp_path / "mtsacte" / "toy-conflict-6_1"
    assert (run_dir / "toy-conflict-6.zip").is_file() and (tmp_path / "mtsac_mt" / "toy-agree-1_1").is_dir()
    record = records.run_record(load_run(run_dir))
    assert record["env_protocol"] is None  # a toy
    assert record["device"]["host"] == socket.gethostname() and record["device"]["trained_on"] == "cpu"
    assert records.record_path(record, tmp_path).parent.name == "toy-conflict-6"


def test_ours_on_a_single_task_is_refused_in_one_line(tmp_path):
    with pytest.raises(SystemExit, match=r"^mtsacte needs at least 2 tasks, and toy-agree-1 has 1: give a benchmark"):
        cli.main(["train", "--algo", "mtsacte", "--env", "toy-agree-1", "-n", "20", "-f", str(tmp_path)])
    assert not list(tmp_path.iterdir())


# ================================================================================================ sweep
@pytest.mark.parametrize(
    ("env", "hint"),
    [("MT10-smok", "did you mean MT10-smoke?"), ("toy-conflict-1", "toy-conflict has at least 2 tasks, not 1")],
)
def test_sweep_names_the_nearest_env_id(tmp_path, capsys, env, hint):
    with pytest.raises(SystemExit):
        sweep.main(["--algos", "mtsac_mt", "--envs", env, "--out", str(tmp_path / "out")])
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"unknown --envs {env}: {hint}" in last, last


# ================================================================================================ records
def test_the_device_a_run_trained_on():
    assert device_type_of({}) is None  # records before the field: CPU runs
    assert device_type_of({"device": {"cuda": True}, "zoo_args": {"device": "auto"}}) == "cuda"
    assert device_type_of({"device": {"cuda": False}, "zoo_args": {"device": "auto"}}) == "cpu"
    assert device_type_of({"device": {"cuda": True}, "zoo_args": {"device": "cpu"}}) == "cpu"
    assert device_type_of({"device": {"trained_on": "cuda:0"}}) == "cuda"


def test_a_record_keeps_the_env_protocol_host_and_device(tmp_path):
    info = {
        "env_id": "MT10-cpu",
        "task_names": ["reach-v3", "push-v3"],
        "env_protocol": ENVPOOL,
        "host": "node-7",
        "device": {"cpu_count": 16, "cuda": True, "cuda_device": "NVIDIA H200"},
        "zoo_args": {"device": "auto"},
    }
    record = records.run_record(Run(tmp_path, info))
    assert record["env_protocol"] == ENVPOOL
    assert record["device"] == {**info["device"], "host": "node-7", "trained_on": "cuda"}
    assert records.run_from_record(record, tmp_path).device_type == "cuda"
    assert "device" not in records.run_record(Run(tmp_path, {"task_names": ["reach-v3"]}))


def _copy(source: Path, record: dict, **changes) -> Path:
    """A copy of ``record`` with ``changes`` (another start: another run), written where ``record`` puts it."""
    record = {**record, **changes, "started": f"{record['started']}-{'-'.join(changes)}"}
    path = records.record_path(record, source)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record))
    return path


def test_gpu_and_envpool_records_are_drawn_apart_and_the_caption_names_the_protocol(tmp_path):
    source = tmp_path / "records"
    shutil.copytree(SAMPLES, source)
    cpu = json.loads((SAMPLES / "MT10-cpu" / "mtsac_mt_seed0.json").read_text())
    gpu = _copy(source, cpu, device={"cuda": True, "host": "gpu-node", "trained_on": "cuda"})
    envpool = _copy(source, cpu, env_protocol=ENVPOOL)
    metaworld = _copy(source, cpu, env_protocol=METAWORLD, seed=7)
    assert (gpu.parent.name, envpool.parent.name, metaworld.parent.name) == (
        "MT10-cpu-gpu",
        "MT10-cpu-envpool",
        "MT10-cpu",
    )
    groups = group_runs(records.load_runs([source]))
    assert set(groups) == {"MT10-cpu", "MT10-cpu-gpu", "MT10-cpu-envpool", "toy-conflict"}
    assert len(groups["MT10-cpu"]["SAC-MT"]) == 3 and len(groups["MT10-cpu-gpu"]["SAC-MT"]) == 1
    for bench, named in (("MT10-cpu", False), ("MT10-cpu-envpool", True), ("MT10-cpu-gpu", False)):
        table = table1(bench, benchmark_statistics(groups[bench], reps=5), reps=5)
        assert table.startswith(f"{bench}: final success")
        assert (" Trained on EnvPool (fresh goals), not Meta-World's benchmark protocol" in table) == named, bench


def test_exact_mu_records_are_drawn_apart_beside_the_baselines(tmp_path):
    """Ours with the float64 transfer matrix groups apart from Ours before it; SAC-MT, without mu, stands in both."""
    source = tmp_path / "records"
    shutil.copytree(SAMPLES, source)
    sac = json.loads((SAMPLES / "MT10-cpu" / "mtsac_mt_seed0.json").read_text())
    ours = {**sac, "algo": "mtsacte", "label": "Ours", "mu_computation": "float32"}
    old = _copy(source, ours, seed=11)
    new = _copy(source, ours, mu_computation="float64", seed=12)
    assert (old.parent.name, new.parent.name) == ("MT10-cpu", "MT10-cpu-exact-mu")
    groups = group_runs(records.load_runs([source]))
    assert 11 in [run.seed for run in groups["MT10-cpu"]["Ours"]]
    assert 12 not in [run.seed for run in groups["MT10-cpu"]["Ours"]]
    assert [run.seed for run in groups["MT10-cpu-exact-mu"]["Ours"]] == [12]
    assert groups["MT10-cpu-exact-mu"]["SAC-MT"] == groups["MT10-cpu"]["SAC-MT"]


def test_the_precision_mu_was_counted_in():
    assert Run(Path("."), {}).mu_computation is None  # no transfer matrix: SAC-MT
    assert Run(Path("."), {}, nt_records=[{"mu": [0]}]).mu_computation == "float32"  # before the field
    exact = [{"transfer_matrix_dtype": "float64"}] * 2
    assert Run(Path("."), {}, nt_records=exact).mu_computation == "float64"
    assert Run(Path("."), {}, nt_records=[{}, *exact]).mu_computation == "mixed"
    assert records.run_from_record({"mu_computation": "float64"}, Path(".")).mu_computation == "float64"
