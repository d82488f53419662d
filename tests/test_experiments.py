"""Tests of the variant registry, the composed hyperparameters and the ``sb3-mtte`` command."""

from __future__ import annotations

import configparser
import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import ENV, tiny_train

from sb3_mtte.experiments import cli
from sb3_mtte.experiments.playback import evaluate_model as evaluate
from sb3_mtte.experiments.results import plot
from sb3_mtte.experiments.results.runs import label_order
from sb3_mtte.experiments.run_info import read_run_info
from sb3_mtte.experiments.variants import (
    VARIANTS,
    Build,
    Variant,
    algo_classes,
    paper_table1,
    register_variant,
    unregister_variant,
    variant_labels,
)
from sb3_mtte.experiments.zoo.configs import zoo_hyperparameters

ROOT = Path(__file__).resolve().parent.parent
FROZEN = Path(__file__).resolve().parent / "data" / "zoo_hyperparameters.json"


def test_composed_hyperparameters_equal_the_former_per_variant_files():
    """Family file + overrides gives every key, for every env entry, exactly the values its own file held."""
    frozen = json.loads(FROZEN.read_text())
    assert set(frozen) == set(VARIANTS)
    for algo, entries in frozen.items():
        assert zoo_hyperparameters(algo) == entries, algo


def test_family_files_are_package_data_read_from_any_folder(tmp_path, monkeypatch):
    """zoo_configs/ ships inside the package as sb3_mtte.zoo_configs (a wheel installs it), every subpackage of
    sb3_mtte is listed in setup.cfg's packages, and the family files are found from any working folder."""
    import sb3_mtte
    from sb3_mtte.experiments.zoo.configs import find_config_dir

    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    listed = config["options"]["packages"].split()
    package_dir = Path(sb3_mtte.__file__).resolve().parent
    inits = package_dir.rglob("*/__init__.py")
    subpackages = {".".join(("sb3_mtte", *init.parent.relative_to(package_dir).parts)) for init in inits}
    assert set(listed) == {"sb3_mtte", "sb3_mtte.zoo_configs", *subpackages}
    assert config["options"]["package_dir"].split() == ["sb3_mtte.zoo_configs", "=", "zoo_configs"]
    shipped = config["options.package_data"]["sb3_mtte.zoo_configs"].split()
    monkeypatch.chdir(tmp_path)
    config_dir = find_config_dir().resolve()
    assert config_dir == ROOT / "zoo_configs"
    families = sorted(Path(path.name) for path in config_dir.glob("*.yml"))
    assert families and all(any(path.match(pattern) for pattern in shipped) for path in families)
    assert zoo_hyperparameters("mtsac_mh")[ENV]["policy"] == "MultiHeadPolicy"


def test_registry_gives_keys_labels_and_order():
    assert set(algo_classes()) == {"mtsac", *VARIANTS}
    assert variant_labels()[:6] == ["SAC-Ind", "SAC-MT", "SAC-MT-MH", "SAC-soft-modular", "SAC-MT-with-clip", "Ours"]
    assert paper_table1()["Ours"] == {"MT10": 89.3, "MT20": 70.1}
    assert label_order(["zzz", "Ours", "SAC-MT"]) == ["SAC-MT", "Ours", "zzz"]
    with pytest.raises(ValueError, match="exists"):
        register_variant(Variant("mtsac_mt", "SAC-MT", Build("mtsac")))
    with pytest.raises(ValueError, match="Unknown family"):
        register_variant(Variant("other", "Other", Build("no-family")))


def test_user_config_file_is_read_as_in_rl_zoo(tmp_path):
    entry = dict(zoo_hyperparameters("mtsac_mt")[ENV], batch_size=16, tau=0.02)
    config = tmp_path / "my.yml"
    config.write_text(yaml.safe_dump({ENV: entry}))
    run = tiny_train(tmp_path, "mtsac_mt", "-conf", str(config), steps=200)
    saved = yaml.load((run / ENV / "config.yml").read_text(), Loader=yaml.UnsafeLoader)
    assert saved["batch_size"] == 16 and saved["tau"] == 0.02


def test_a_registered_variant_trains_evaluates_and_plots(tmp_path):
    """Adding a variant is one registration: zoo key, hyperparameters, label and order follow."""
    variant = Variant("mtsac_probe", "SAC-MT-probe", Build("mtsac", "MultiHeadPolicy", overrides={"tau": 0.02}))
    register_variant(variant)
    try:
        assert zoo_hyperparameters("mtsac_probe")[ENV]["tau"] == 0.02
        run = tiny_train(tmp_path / "runs", "mtsac_probe", "-params", "learning_starts:100", steps=200)
        info = read_run_info(run)
        assert info["label"] == "SAC-MT-probe" and info["hyperparams"]["policy"] == "MultiHeadPolicy"
        record = evaluate.main([str(run / f"{ENV}.zip"), "--episodes", "1"])
        assert record["label"] == "SAC-MT-probe"
        written = plot.main([str(tmp_path / "runs"), "--out", str(tmp_path / "figures"), "--reps", "10"])
        assert tmp_path / "figures" / f"success_{ENV}.png" in written
        assert "| SAC-MT-probe |" in (tmp_path / "figures" / f"table1_{ENV}.md").read_text()
    finally:
        unregister_variant("mtsac_probe")
    assert "mtsac_probe" not in VARIANTS


def test_console_script_is_declared_and_dispatches(capsys):
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    scripts = config["options.entry_points"]["console_scripts"].strip()
    assert scripts == "sb3-mtte = sb3_mtte.experiments.cli:console_main"
    assert set(cli.COMMANDS) == {"train", "enjoy", "record_video", "evaluate", "record", "plot", "compare", "sweep"}
    for command in cli.COMMANDS:
        with pytest.raises(SystemExit) as exit_info:
            cli.main([command, "--help"])
        assert exit_info.value.code == 0, command
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["unknown"])
    assert exit_info.value.code == 2 and "sb3-mtte: unknown command 'unknown'" in capsys.readouterr().err


def module_main(argv):
    """The commands as ``python -m sb3_mtte`` runs them."""
    return cli.main(argv, prog="python -m sb3_mtte")


@pytest.mark.parametrize(("run", "prog"), [(cli.main, "sb3-mtte"), (module_main, "python -m sb3_mtte")])
def test_a_misspelled_command_ends_with_one_line_naming_the_nearest(capsys, run, prog):
    with pytest.raises(SystemExit) as exit_info:
        run(["enjoi", "--env", "MT10"])
    out, err = capsys.readouterr()
    assert exit_info.value.code == 2 and out == ""
    assert err.startswith(f"{prog}: unknown command 'enjoi' (did you mean 'enjoy'?); commands: train, enjoy, ")
    assert len(err.splitlines()) == 1


def test_console_script_exits_0_after_a_command_that_returns_a_value(monkeypatch):
    """The script's wrapper runs ``sys.exit(<entry point>())``: a returned dict would exit 1 and print itself."""
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    module, function = config["options.entry_points"]["console_scripts"].split("=")[1].strip().split(":")
    monkeypatch.setitem(cli.COMMANDS, "evaluate", lambda argv: {"mean": 0.5})
    monkeypatch.setattr("sys.argv", ["sb3-mtte", "evaluate", "model.zip"])
    entry_point = getattr(__import__(module, fromlist=[function]), function)
    with pytest.raises(SystemExit) as exit_info:
        raise SystemExit(entry_point())
    assert exit_info.value.code is None


@pytest.fixture(scope="module")
def toy_model_zip(tmp_path_factory):
    from sb3_mtte import MTSAC, make_mt_env

    path = tmp_path_factory.mktemp("model") / "toy.zip"
    model = MTSAC("MlpPolicy", make_mt_env("toy-conflict"), learning_starts=10, buffer_size=100, batch_size=16, seed=0)
    model.save(path)
    return path


@pytest.mark.parametrize(
    "case, message",
    [
        ("wrong benchmark", "was trained on 4 tasks; toy-conflict-6 has 6: pass --env"),
        ("one meta-world task", "was trained on 4 tasks; reach-v3 has 1: pass --env"),
        ("unknown env", "Unknown Meta-World v3 env name 'nothing-v3' (nearest: "),
        ("missing file", "No model at"),
        ("missing file without --env", "No model at"),
        ("truncated", "is not a complete SB3 checkpoint"),
        ("other benchmark", "trained on the tasks agree-0, agree-1, agree-2, conflict, not toy-agree: pass the --env"),
    ],
)
def test_evaluate_refuses_bad_input_with_one_line(toy_model_zip, tmp_path, capsys, case, message):
    """Each mistake ends with exit status 2 and one line naming the fix, never a traceback from a library."""
    model, env = str(toy_model_zip), "toy-conflict"
    if case == "wrong benchmark":
        env = "toy-conflict-6"
    elif case == "one meta-world task":
        env = "reach-v3"
    elif case == "unknown env":
        env = "nothing-v3"
    elif case.startswith("missing file"):
        model = str(tmp_path / "absent.zip")
    elif case == "truncated":
        data = toy_model_zip.read_bytes()
        (tmp_path / "cut.zip").write_bytes(data[: len(data) // 2])
        model = str(tmp_path / "cut.zip")
    elif case == "other benchmark":
        env = "toy-agree"
    with pytest.raises(SystemExit) as exit_info:
        evaluate.main([model, *([] if case.endswith("without --env") else ["--env", env]), "--episodes", "1"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err


def test_evaluate_on_another_benchmark_when_asked_warns_and_keeps_the_final_evaluation(toy_model_zip, capsys):
    """--other-benchmark evaluates a toy-conflict model on toy-agree with one warning line naming both, into a file
    of its own: never success.json, which a run's results read as its final evaluation."""
    record = evaluate.main([str(toy_model_zip), "--env", "toy-agree", "--episodes", "1", "--other-benchmark"])
    (warning,) = capsys.readouterr().err.strip().splitlines()
    assert "trained on the tasks agree-0, agree-1, agree-2, conflict; evaluating it on toy-agree" in warning
    assert record["benchmark"] == "toy-agree" and record["task_names"][-1] == "agree-3"
    assert (toy_model_zip.parent / "success_toy_on_toy-agree.json").is_file()
    assert not (toy_model_zip.parent / "success.json").exists()


@pytest.mark.parametrize("flags", [[], ["--no-progress"]])
def test_evaluate_shows_a_progress_bar_per_task(toy_model_zip, tmp_path, capsys, flags):
    evaluate.main([str(toy_model_zip), "--episodes", "3", "--env", ENV, "--out", str(tmp_path / "s.json"), *flags])
    out = capsys.readouterr().out
    bars = [match[1] for match in re.finditer(r"^(\S+) +━+ 3/3 ", out, re.MULTILINE)]
    assert bars == ([] if flags else ["agree-0", "agree-1", "agree-2", "conflict"]), out


def test_evaluate_names_the_reward_functions_in_its_header():
    record = {"label": "Ours", "benchmark": "MT10", "seed": 0, "timesteps": 5, "episodes_per_task": 50}
    assert evaluate.evaluation_title({**record, "reward_function_version": "v1"}).endswith(
        "50 episodes per task, Meta-World reward functions v1"
    )
    assert evaluate.evaluation_title({**record, "reward_function_version": None}).endswith("50 episodes per task")


def test_record_names_each_run_it_skips(tmp_path, capsys):
    from sb3_mtte.experiments.results import records

    run = tmp_path / "runs" / "mtsac_mt" / f"{ENV}_1"
    run.mkdir(parents=True)
    info = {"algo": "mtsac_mt", "label": "SAC-MT", "env_id": ENV, "seed": 4, "task_names": ["a", "b"], "n_tasks": 2}
    (run / "run_info.json").write_text(json.dumps(info))
    (run / f"{ENV}.zip").write_bytes(b"")  # its final model, not evaluated yet
    with pytest.raises(SystemExit):
        records.main([str(tmp_path / "runs"), "--out", str(tmp_path / "records")])
    assert capsys.readouterr().err.splitlines()[0] == (
        f"Skipped {run} ({ENV}, SAC-MT, seed 4): no final evaluation (success.json); evaluate it first: sb3-mtte "
        f"evaluate {run / (ENV + '.zip')} --episodes 50"
    )


def test_top_level_help_is_plain_text(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["--help"])
    out = capsys.readouterr().out
    assert exit_info.value.code == 0 and "sb3-mtte train --algo mtsacte" in out
    assert "``" not in out and ":mod:" not in out and "::\n" not in out
    assert "sb3_mtte.experiments" not in out and not any(f"({name})" in out for name in ("configs", "env_ids"))


def test_train_help_is_argparse_help_with_the_launcher_options(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["train", "--help"])
    out = capsys.readouterr().out
    assert exit_info.value.code == 0 and out.startswith("usage: ")
    assert "rl-zoo3's train on a benchmark of sb3_mtte" in out and "\nsb3_mtte options:\n" in out
    assert "--resume [RUN_DIR]    continue the latest checkpoint of RUN_DIR" in out
    assert "--no-progress         no progress bar" in out and "if toggled" not in out.split("--progress")[1]
    assert "display a progress bar with tqdm and rich (on by" in out
    choices = out.split("--algo {")[1].split("}")[0].split(",")
    assert choices == list(algo_classes()) and "ppo" not in choices


def test_sweep_help_describes_every_option(capsys):
    from sb3_mtte.experiments.zoo import sweep

    with pytest.raises(SystemExit):
        sweep.main(["--help"])
    out = capsys.readouterr().out
    assert "CPUs Ray reserves for each run" in out and "GPUs Ray reserves for each run" in out


@pytest.mark.parametrize("module", ["evaluate", "plot", "compare", "sweep"])
@pytest.mark.parametrize("called_as", ["console script", "module"])
def test_usage_lines_name_the_entry_point_that_was_called(monkeypatch, capsys, module, called_as):
    from sb3_mtte.experiments.results import compare
    from sb3_mtte.experiments.zoo import sweep

    main = {"evaluate": evaluate.main, "plot": plot.main, "compare": compare.main, "sweep": sweep.main}[module]
    argv0 = "/venv/bin/sb3-mtte" if called_as == "console script" else "/src/sb3_mtte/__main__.py"
    monkeypatch.setattr("sys.argv", [argv0])
    with pytest.raises(SystemExit):
        main(["--help"])
    expected = f"sb3-mtte {module}" if called_as == "console script" else f"python -m sb3_mtte {module}"
    assert capsys.readouterr().out.startswith(f"usage: {expected} ")


def test_enjoy_help_lists_the_package_keys(capsys):
    with pytest.raises(SystemExit):
        cli.main(["enjoy", "--help"])
    out = capsys.readouterr().out
    assert all(key in out for key in ("mtsacte", "mtsac_mt", "mtsacte_novae", "mtsac_paco"))
    assert "rl-zoo3's enjoy on a run of sb3_mtte" in out and "ppo" not in out


def test_record_of_a_finished_run(tmp_path):
    """A trained and evaluated run leaves one small JSON record with its curve, final per-task success, settings
    and commit; runs without a final evaluation leave none."""
    from sb3_mtte.experiments.results import records

    run = tiny_train(tmp_path / "runs", "mtsacte", "-params", "learning_starts:100", "--eval-freq", "100", steps=200)
    with pytest.raises(SystemExit):
        records.main([str(tmp_path / "runs"), "--out", str(tmp_path / "records")])  # not evaluated yet
    final = evaluate.main([str(run / f"{ENV}.zip"), "--episodes", "2"])
    (path,) = records.main([str(tmp_path / "runs"), "--out", str(tmp_path / "records")])
    record = json.loads(path.read_text())
    info = read_run_info(run)
    assert path == tmp_path / "records" / f"{ENV}-exact-mu" / f"mtsacte_seed{info['seed']}.json"  # mu in float64
    sample = json.loads(next((ROOT / "tests" / "data" / "records").rglob("mtsacte_seed0.json")).read_text())
    newer_fields = {"env_protocol", "device", "mu_computation"}  # absent from the samples: recorded before them
    assert set(record) == set(sample) | newer_fields and set(record["final"]) == set(sample["final"])
    # the samples predate weights_distance, harmful_fraction and coupling, which records made before them lack
    newer = {"weights_distance", "harmful_fraction", "coupling"}
    assert set(record["representation"]) == set(sample["representation"]) | newer
    assert set(record["curve"]) == set(sample["curve"])
    assert record["curve"]["episodes_per_task"] == info["hyperparams"]["eval_episodes"]
    assert record["budget"] == {"n_timesteps": 200, "timesteps": 200, "finished": True}
    assert record["started"] == info["started"] and record["algo"] == "mtsacte" and record["n_tasks"] == 4
    assert record["final"]["per_task"] == final["per_task"] and record["final"]["episodes_per_task"] == 2
    assert record["hyperparams"] == info["hyperparams"] and record["git"] == info["git"]
    evaluations = np.load(run / "evaluations.npz")
    assert record["curve"]["env_steps"] == evaluations["timesteps"].tolist()
    np.testing.assert_allclose(record["curve"]["success_rate"], evaluations["success_rate"], atol=1e-6)
    nt_lines = (run / "negative_transfer.jsonl").read_text().splitlines()
    assert len(record["representation"]["task_probe_accuracy"]) == len(nt_lines)
    assert records.read_records(tmp_path / "records") == [(path, record)]
