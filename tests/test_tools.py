"""Tests of the experiment tools: evaluate CLI, plots and Table 1, run metadata, Ray sweep."""

from __future__ import annotations

import csv
import importlib.util
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import ENV, tiny_train
from matplotlib.colors import to_hex

from sb3_mtte.common.utils import task_log_key
from sb3_mtte.experiments.playback import evaluate_model as evaluate
from sb3_mtte.experiments.results import figures, plot, summary_figures
from sb3_mtte.experiments.results import records as records_cli
from sb3_mtte.experiments.results import runs as plot_runs
from sb3_mtte.experiments.run_info import (
    append_resume,
    collect_run_info,
    git_info,
    package_versions,
    read_run_info,
    update_run_info,
    write_run_info,
)
from sb3_mtte.experiments.variants import label_of as algo_label
from sb3_mtte.experiments.variants import variant_labels
from sb3_mtte.experiments.zoo import sweep
from sb3_mtte.experiments.zoo.sweep import env_id_for, plan_trials
from sb3_mtte.experiments.zoo.sweep_run import trial_command

TASKS = ["agree-0", "agree-1", "agree-2", "conflict"]


@pytest.fixture(scope="module")
def zoo_runs(tmp_path_factory):
    """Two real tiny runs (MTSACTE and SAC-MT) in the zoo layout."""
    root = tmp_path_factory.mktemp("runs")
    for algo in ("mtsacte", "mtsac_mt"):
        tiny_train(root, algo, "--seed", "1", "-params", "learning_starts:100")
    return root


# ================================================================================================ run_info
def test_run_info_roundtrip(tmp_path):
    info = collect_run_info(algo="mtsac_clip", env_id="MT10-smoke", benchmark="MT10", seed=4, hyperparams={"a": 1})
    assert info["label"] == "SAC-MT-with-clip" and info["seed"] == 4 and not info["finished"]
    assert {"python", "sb3_mtte", "torch", "stable_baselines3", "gymnasium", "metaworld", "numpy"} <= set(
        info["versions"]
    )
    write_run_info(tmp_path, info)
    update_run_info(tmp_path, finished=True, timesteps=np.int64(7))
    append_resume(tmp_path, checkpoint="rl_model_5_steps.zip", timesteps=5)
    loaded = read_run_info(tmp_path)
    assert loaded["finished"] and loaded["timesteps"] == 7 and loaded["resumes"][0]["timesteps"] == 5
    assert read_run_info(tmp_path / "nothing") is None
    assert package_versions()["sb3_mtte"]
    assert set(git_info()) == {"commit", "branch", "dirty"}


def test_algo_labels():
    assert algo_label("mtsacte_novae") == "Ours-VAE"
    assert algo_label("mtsac", {"policy": "MultiHeadPolicy"}) == "SAC-MT-MH"
    assert algo_label("mtsac", {"policy": "MlpPolicy", "q_loss_clip": 2000}) == "SAC-MT-with-clip"
    assert algo_label("mtsacte", {"q_loss_clip": None}) == "Ours"  # the row key wins
    assert algo_label("mtsacte_x", {"use_topk": False}) == "mtsacte_x"  # no family's key: no prefix matching


# ================================================================================================ evaluate
def test_evaluate_cli_writes_json(zoo_runs, capsys):
    run = zoo_runs / "mtsacte" / f"{ENV}_1"
    record = evaluate.main([str(run / f"{ENV}.zip"), "--episodes", "3"])
    out = capsys.readouterr().out
    assert "| mean" in out and "conflict" in out
    saved = json.loads((run / "success.json").read_text())
    assert saved == record
    assert saved["task_names"] == TASKS and len(saved["success_rate"]) == 4
    assert saved["algorithm"] == "MTSACTE" and saved["label"] == "Ours" and saved["env_id"] == ENV
    assert saved["seed"] == 1 and saved["episodes_per_task"] == 3 and saved["timesteps"] == 400
    assert 0.0 <= saved["mean"] <= 1.0
    # another file of the run, another json; explicit env and seed
    evaluate.main([str(run / "best_model.zip"), "--env", ENV, "--seed", "0", "--episodes", "1"])
    assert json.loads((run / "success_best_model.json").read_text())["algorithm"] == "MTSACTE"
    # the baseline class is detected from its zip
    evaluate.main([str(zoo_runs / "mtsac_mt" / f"{ENV}_1" / f"{ENV}.zip"), "--episodes", "1"])
    assert json.loads((zoo_runs / "mtsac_mt" / f"{ENV}_1" / "success.json").read_text())["algorithm"] == "MTSAC"


def test_evaluate_reads_the_tasks_of_a_model_without_run_info(tmp_path, zoo_runs, capsys):
    model = tmp_path / "model.zip"
    model.write_bytes((zoo_runs / "mtsac_mt" / f"{ENV}_1" / f"{ENV}.zip").read_bytes())
    record = evaluate.main([str(model), "--episodes", "1", "--out", str(tmp_path / "r.json")])
    assert record["env_id"] == ENV and "the tasks of its checkpoint" in capsys.readouterr().err
    evaluate.main([str(model), "--env", ENV, "--episodes", "1", "--out", str(tmp_path / "r.json")])
    assert json.loads((tmp_path / "r.json").read_text())["benchmark"] == ENV


# ================================================================================================ plot
def _write_progress(path: Path, rows: list[dict[str, float]]) -> None:
    keys = sorted({key for row in rows for key in row})
    with open(path, "w", newline="") as file:
        writer = csv.DictWriter(file, keys)
        writer.writeheader()
        writer.writerows(rows)


def make_synthetic_run(root: Path, algo: str, label: str, seed: int, final: float, nt: bool, tb: bool = False) -> Path:
    """A run folder as the zoo writes it, with made-up curves (MT10-sized: 10 tasks, 500-step episodes)."""
    names = [f"task{i}-v3" for i in range(10)]
    run = root / algo / f"MT10_{seed + 1}"
    run.mkdir(parents=True)
    info = {"algo": algo, "label": label, "env_id": "MT10", "benchmark": "MT10", "seed": seed, "n_tasks": 10}
    write_run_info(run, {**info, "task_names": names, "episode_length": 500})
    steps = np.arange(1, 11) * 100_000
    rng = np.random.default_rng(seed)
    success = np.clip(np.linspace(0, final, 10)[:, None] + 0.05 * rng.standard_normal((10, 10)), 0, 1)
    np.savez(run / "evaluations.npz", timesteps=steps, success_rate=success, task_names=np.asarray(names))
    rows = []
    for t in range(1, 41):
        row = {"time/total_timesteps": t * 25_000, "rollout/success_rate": t / 40}
        for i, name in enumerate(names):
            row[task_log_key("train/critic_loss", i, name)] = float(1e3 * (1 + i) * np.exp(-t / 20))
            row[task_log_key("rollout/success", i, name)] = t / 40
        rows.append(row)
    if tb:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(run))
        for row in rows:
            for key, value in row.items():
                if key != "time/total_timesteps":
                    writer.add_scalar(key, value, row["time/total_timesteps"])
        writer.close()
    else:
        _write_progress(run / "progress.csv", rows)
    if nt:
        with open(run / "negative_transfer.jsonl", "w") as file:
            for r in range(60):
                mu = rng.integers(0, 10, size=10)
                selected = np.zeros(10, dtype=int)
                selected[np.argsort(mu, kind="stable")[:5]] = 1
                weights = np.exp(10 - mu) / np.exp(10 - mu).sum()
                matrix = rng.standard_normal((10, 10))
                record = {"timesteps": (r + 1) * 5000 * 3, "mu": mu.tolist(), "selected": selected.tolist()}
                record.update(weights=weights.tolist(), transfer_matrix=matrix.tolist())
                file.write(json.dumps(record) + "\n")
    return run


def test_plot_synthetic_runs_writes_every_figure_and_table(tmp_path, capsys):
    runs = tmp_path / "runs"
    for seed, final in ((0, 0.8), (1, 0.9)):
        make_synthetic_run(runs, "mtsacte", "Ours", seed, final, nt=True)
        make_synthetic_run(runs, "mtsac_mt", "SAC-MT", seed, final - 0.2, nt=False, tb=seed == 1)
    make_synthetic_run(runs, "mtsacte_novae", "Ours-VAE", 0, 0.5, nt=True)
    names = [f"task{i}-v3" for i in range(10)]
    final_ours = {"mean": 0.85, "per_task": dict.fromkeys(names, 0.85)}
    (runs / "mtsacte" / "MT10_1" / "success.json").write_text(json.dumps(final_ours))
    out = tmp_path / "docs"
    argv = [str(runs), "--out", str(out), "--tasks", "task0", "task3", "--matrix-times", "1e4", "9e4", "--reps", "50"]
    written = plot.main(argv)
    expected = {
        "success_MT10.png",
        "per_task_MT10.png",
        "profile_MT10.png",
        "bellman_MT10_Ours.png",
        "bellman_MT10_SAC-MT.png",
        "bellman_MT10_Ours-VAE.png",
        "bellman_avg_MT10.png",
        "train_frequency_MT10_Ours.png",
        "nt_MT10_Ours.png",
        "nt_matrix_MT10_Ours.png",
        "train_frequency_MT10_Ours-VAE.png",
        "nt_MT10_Ours-VAE.png",
        "nt_matrix_MT10_Ours-VAE.png",
        "table1_MT10.md",
        "runs_MT10.md",
        "bellman_MT10.md",
        "results_MT10.json",
    }
    assert {p.name for p in written} == expected
    bellman_rows = [line for line in (out / "bellman_MT10.md").read_text().splitlines() if line.startswith("| ")]
    assert [row.split("|")[1].strip() for row in bellman_rows[1:]] == ["SAC-MT"] * 2 + ["Ours"] * 2 + ["Ours-VAE"]
    for path in written:
        assert path.stat().st_size > (1000 if path.suffix == ".png" else 100), path
    table = (out / "table1_MT10.md").read_text()
    assert table in capsys.readouterr().out
    rows = {line.split("|")[1].strip(): line.split("|")[2:-1] for line in table.splitlines() if line.startswith("| ")}
    assert list(rows)[1:] == ["SAC-MT", "Ours", "Ours-VAE"]
    ours = np.mean([0.85, final_eval(runs / "mtsacte" / "MT10_2")])  # success.json, else the last evaluation
    assert rows["Ours"][0].strip() == "2" and rows["Ours"][1].strip().startswith(f"{100 * ours:.1f} [")
    assert rows["Ours-VAE"][0].strip() == "1" and rows["Ours"][-1].strip() == "89.3"  # the paper's value beside


def test_every_algorithm_keeps_one_distinct_style_in_every_figure(tmp_path, monkeypatch):
    labels = [*variant_labels(), "Mine"]
    groups = {
        label: [plot_runs.load_run(make_synthetic_run(tmp_path, f"algo{i}", label, 0, 0.5, nt=False))]
        for i, label in enumerate(labels)
    }
    figs = {}
    monkeypatch.setattr(
        summary_figures, "save_figure", lambda fig, path, opts, written: figs.__setitem__(path.name, fig)
    )
    opts = figures.PlotOptions(out=tmp_path, reps=10)
    summary_figures.plot_success("MT10", summary_figures.curve_bands(groups, opts), opts, [])
    some = {label: groups[label] for label in labels[5:]}
    summary_figures.plot_per_task("MT10", summary_figures.curve_bands(some, opts), TASKS, opts, [])
    scores = {label: np.full((1, 10), 0.5) for label in labels}
    summary_figures.plot_profile("MT10", scores, opts, [])
    assert set(figs) == {"success_MT10.png", "per_task_MT10.png", "profile_MT10.png"}
    seen = {}
    for name, fig in figs.items():
        drawn = {}
        for line in (line for ax in fig.axes for line in ax.get_lines()):
            label = line.get_label().split(" (n=")[0]
            style = (to_hex(line.get_color()), line.get_linestyle())
            assert drawn.setdefault(label, style) == style, (name, label)
            assert seen.setdefault(label, style) == style, (name, label)  # the same look in every figure
        assert len(set(drawn.values())) == len(drawn), name  # no two algorithms alike
    assert set(seen) == set(labels)


def final_eval(run: Path) -> float:
    with np.load(run / "evaluations.npz") as data:
        return float(data["success_rate"][-1].mean())


def test_tensorboard_fallback_matches_csv(tmp_path):
    csv_run = plot_runs.load_run(make_synthetic_run(tmp_path / "a", "mtsac_mt", "SAC-MT", 0, 0.5, nt=False))
    tb_run = plot_runs.load_run(make_synthetic_run(tmp_path / "b", "mtsac_mt", "SAC-MT", 0, 0.5, nt=False, tb=True))
    key = task_log_key("train/critic_loss", 3, "task3-v3")
    assert np.array_equal(csv_run.scalars[key][0], tb_run.scalars[key][0])
    assert np.allclose(csv_run.scalars[key][1], tb_run.scalars[key][1], rtol=1e-6)


def test_train_frequency_window():
    run = plot_runs.Run(Path("."), {"n_tasks": 2, "task_names": ["a", "b"]})
    run.nt_records = [{"timesteps": 10 * (j + 1), "selected": [j % 2, 1]} for j in range(6)]
    steps, freq = plot_runs.train_frequency(run, window_steps=20)  # the last 2 recomputations
    assert list(steps) == [10, 20, 30, 40, 50, 60]
    assert np.allclose(freq[:, 0], [0, 0.5, 0.5, 0.5, 0.5, 0.5]) and np.allclose(freq[:, 1], 1)


def test_mean_std_over_seeds_interpolates():
    x, mean, std = plot_runs.mean_std([(np.array([0, 2]), np.array([0.0, 2.0])), (np.array([0, 1, 2]), np.ones(3))])
    assert list(x) == [0, 1, 2] and np.allclose(mean, [0.5, 1.0, 1.5]) and np.allclose(std, [0.5, 0.0, 0.5])


def test_plot_real_tiny_runs(zoo_runs, tmp_path):
    written = plot.main([str(zoo_runs), "--out", str(tmp_path), "--reps", "10"])
    names = {p.name for p in written}
    bench = f"{ENV}-exact-mu"  # Ours counts mu in float64; SAC-MT stands beside it, and no table holds SAC-MT alone
    assert {f"success_{bench}.png", f"per_task_{bench}.png", f"nt_matrix_{bench}_Ours.png"} <= names
    assert f"table1_{bench}.md" in names
    assert {f"bellman_{bench}_SAC-MT.png", f"train_frequency_{bench}_Ours.png", f"nt_{bench}_Ours.png"} <= names
    assert not any(name.startswith(f"table1_{ENV}.") for name in names)


def test_plot_writes_beside_the_runs_by_default(zoo_runs, tmp_path, monkeypatch):
    runs = tmp_path / "runs"
    shutil.copytree(zoo_runs, runs)
    monkeypatch.chdir(tmp_path)
    written = plot.main([str(runs), "--reps", "10"])
    assert written and all(path.parent == runs for path in written)
    assert not (tmp_path / "docs").exists()


def test_results_summary_per_run(zoo_runs, tmp_path):
    runs = tmp_path / "runs"
    shutil.copytree(zoo_runs, runs)
    for algo, mean in (("mtsacte", 0.25), ("mtsac_mt", 0.75)):
        final = {"mean": mean, "per_task": dict.fromkeys(TASKS, mean), "timesteps": 123, "episodes_per_task": 10}
        (runs / algo / f"{ENV}_1" / "success.json").write_text(json.dumps(final))
    plot.main(
        [str(runs), "--out", str(tmp_path / "figures"), "--results-dir", str(tmp_path / "results"), "--reps", "9"]
    )
    records = json.loads((tmp_path / "results" / f"{ENV}-exact-mu.json").read_text())
    assert [(r["algo"], r["label"], r["benchmark"], r["seed"], r["env_steps"]) for r in records] == [
        ("mtsac_mt", "SAC-MT", ENV, 1, 123),
        ("mtsacte", "Ours", ENV, 1, 123),
    ]
    assert [r["success"] for r in records] == [
        {"mean": 0.75, "per_task": dict.fromkeys(TASKS, 0.75)},
        {"mean": 0.25, "per_task": dict.fromkeys(TASKS, 0.25)},
    ]


def test_records_redraw_the_table_and_success_curves_of_their_run_folders(tmp_path, monkeypatch):
    """Records of run folders give the same Table 1 and success figures as the folders, and a record beside its
    run folder is not counted twice."""
    runs = tmp_path / "runs"
    names = [f"task{i}-v3" for i in range(10)]
    for algo, label, seed, final in (
        ("mtsacte", "Ours", 0, 0.8),
        ("mtsacte", "Ours", 1, 0.6),
        ("mtsac_mt", "SAC-MT", 0, 0.5),
    ):
        run = make_synthetic_run(runs, algo, label, seed, final, nt=algo == "mtsacte")
        rates = np.round(np.linspace(0, final, 10), 2).tolist()
        (run / "success.json").write_text(json.dumps({"mean": final, "per_task": dict(zip(names, rates, strict=True))}))
    monkeypatch.chdir(tmp_path)
    paths = records_cli.main([str(runs)])  # default --out: docs/records/<env id>/<algo>_seed<k>.json
    assert sorted(str(p) for p in paths) == [
        f"docs/records/MT10/{a}_seed{k}.json" for a, k in (("mtsac_mt", 0), ("mtsacte", 0), ("mtsacte", 1))
    ]
    assert len(records_cli.load_runs([runs, tmp_path / "docs"])) == 3
    figs = {}
    monkeypatch.setattr(
        summary_figures, "save_figure", lambda fig, path, opts, written: figs.setdefault(str(path), fig)
    )
    for source in (runs, tmp_path / "docs"):
        plot.main([str(source), "--out", str(tmp_path / source.name), "--reps", "20"])
    assert (tmp_path / "runs" / "table1_MT10.md").read_text() == (tmp_path / "docs" / "table1_MT10.md").read_text()
    from_runs, from_records = (
        figs[str(tmp_path / "runs" / "success_MT10.png")],
        figs[str(tmp_path / "docs" / "success_MT10.png")],
    )
    for line_a, line_b in zip(from_runs.axes[0].get_lines(), from_records.axes[0].get_lines(), strict=True):
        assert line_a.get_label() == line_b.get_label()
        np.testing.assert_allclose(line_a.get_xydata(), line_b.get_xydata(), atol=1e-4)


def test_two_runs_sharing_a_record_file_are_refused(tmp_path):
    for folder in ("a", "b"):
        run = make_synthetic_run(tmp_path / "runs" / folder, "mtsac_mt", "SAC-MT", 0, 0.5, nt=False)
        (run / "success.json").write_text(json.dumps({"mean": 0.5}))
    with pytest.raises(SystemExit, match=r"a/mtsac_mt/MT10_1 and .*b/mtsac_mt/MT10_1 would both be recorded"):
        records_cli.main([str(tmp_path / "runs"), "--out", str(tmp_path / "records")])
    assert not (tmp_path / "records").exists()


# ================================================================================================ sweep
def test_sweep_plan_and_budget(tmp_path):
    assert env_id_for("MT10", "smoke") == "MT10-smoke" and env_id_for("MT10", "full") == "MT10"
    (tmp_path / "mtsacte" / "MT10-smoke_1").mkdir(parents=True)
    trials = plan_trials(tmp_path, ["mtsacte", "mtsac_mt"], ["MT10"], [0, 1], "smoke", resume=False)
    assert [(t["algo"], t["seed"], t["exp_id"]) for t in trials] == [
        ("mtsacte", 0, 2),
        ("mtsacte", 1, 3),
        ("mtsac_mt", 0, 1),
        ("mtsac_mt", 1, 1 + 1),
    ]
    assert trials[0]["run_dir"] == str(tmp_path / "mtsacte" / "MT10-smoke_2")
    argv = trial_command(trials[0], tmp_path, ["-n", "10"], cpus=2)
    assert argv[argv.index("--exp-id") + 1] == "2" and argv[-2:] == ["-n", "10"] and "--num-threads" in argv


@pytest.mark.parametrize(
    ("flag", "value", "message"),
    [
        ("--algos", "mtsac_nope", "unknown --algos mtsac_nope: choose from .*mtsacte"),
        ("--envs", "MT11", "unknown --envs MT11: did you mean MT10\\? The env ids: MT10"),
        (
            "--envs",
            "MT50",
            "mtsac_mt has no hyperparameters for MT50 \\(its entries: MT10 .* toy-conflict\\): pass -- -conf",
        ),
    ],
)
def test_sweep_refuses_an_unknown_algorithm_or_benchmark_before_starting_ray(tmp_path, capsys, flag, value, message):
    args = {"--algos": "mtsac_mt", "--envs": "toy-conflict", flag: value}
    with pytest.raises(SystemExit):
        sweep.main([*(part for pair in args.items() for part in pair), "--out", str(tmp_path)])
    error = capsys.readouterr().err
    assert re.search(message, error.strip().splitlines()[-1]) and "Traceback" not in error, error
    assert not list(tmp_path.iterdir())


@pytest.mark.slow  # long (Ray starts): .ci/run runs it after the default suite
@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason='needs the ray extra: pip install "ray[tune]"')
def test_sweep_tiny_grid_on_local_ray(tmp_path):
    import ray

    out = tmp_path / "runs"
    extra = ["-n", "200", "--eval-freq", "200", "--eval-episodes", "1", "--verbose", "0"]
    args = ["--algos", "mtsac_mt", "mtsacte", "--envs", ENV, "--seeds", "0", "--out", str(out)]
    try:
        trials = sweep.main(
            [*args, "--num-cpus", "2", "--ray-verbose", "0", "--", *extra, "-params", "learning_starts:100"]
        )
        assert [t["status"] for t in trials] == ["done", "done"]
        for algo in ("mtsac_mt", "mtsacte"):
            info = read_run_info(out / algo / f"{ENV}_1")
            assert info["finished"] and info["timesteps"] == 200 and info["seed"] == 0
        plan = json.loads((out / "sweep.json").read_text())
        assert len(plan["trials"]) == 2 and all(t["finished"] for t in plan["trials"])
        # resuming the sweep skips the finished trials
        again = sweep.main([*args, "--resume", "--num-cpus", "2", "--ray-verbose", "0", "--", *extra])
        assert [t["run_dir"] for t in again] == [t["run_dir"] for t in trials]
        assert len(read_run_info(out / "mtsacte" / f"{ENV}_1")["resumes"]) == 0
    finally:
        ray.shutdown()
    written = plot.main([str(out), "--out", str(tmp_path), "--reps", "10"])
    bench = f"{ENV}-exact-mu"  # mtsacte counts mu in float64; mtsac_mt stands beside it
    assert {f"success_{bench}.png", f"table1_{bench}.md"} <= {p.name for p in written}
