"""Tables and figures of runs that did not finish, of algorithms without variance, and how the figures read: a
stopped run is left out and named unless --include-unfinished marks it, Welch's t says when it is undefined, one
rounding of the critic loss, a line per file written, labelled panels, a profile drawn in steps, the seeds of a
heatmap."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from test_compare import hand_run
from test_plot_runs import BUDGET, TASKS, table_rows, write_critic_log, write_nt_log, write_run

from sb3_mtte.common.utils import task_log_key
from sb3_mtte.experiments.results import compare, figures, plot, records, summary_figures
from sb3_mtte.experiments.results.bellman_table import bellman_table
from sb3_mtte.experiments.results.compare import Comparison, comparison_report, comparison_summary, mean_difference


def stopped_run(root: Path, seed: int = 2, final: float = 0.9) -> Path:
    """A run stopped (Ctrl-C) at 400 of 800 env steps and evaluated since: ``success.json``, ``finished: false``."""
    return write_run(root, seed, [0.0, 0.1], final, finished=False, timesteps=400)


@pytest.fixture
def runs_with_a_stopped_one(tmp_path: Path) -> tuple[Path, Path]:
    """Seeds 0 and 1 finished at 50% and 30%; seed 2 was stopped halfway, then evaluated at 90%."""
    root = tmp_path / "runs"
    write_run(root, 0, [0.0, 0.1, 0.2, 0.3], 0.5, finished=True, timesteps=BUDGET)
    write_run(root, 1, [0.0, 0.1, 0.2, 0.3], 0.3, finished=True, timesteps=BUDGET)
    return root, stopped_run(root)


def left_out_line(run: Path, scope: str = "every figure and table", action: str = "counts") -> str:
    return (
        f"Left out of {scope}: {run} (toy-conflict, SAC-MT, seed 2) did not finish: it stopped at 400 of 800 env "
        f"steps; --include-unfinished {action} its final evaluation, marked unfinished"
    )


# ============================================================================================ runs that did not finish
def test_a_stopped_run_is_left_out_of_every_table_although_it_was_evaluated(runs_with_a_stopped_one, tmp_path, capsys):
    root, stopped = runs_with_a_stopped_one
    plot.main([str(root), "--out", str(tmp_path / "figures"), "--reps", "10"])
    assert capsys.readouterr().err.strip().splitlines() == [left_out_line(stopped)]
    row = table_rows(tmp_path / "figures" / "table1_toy-conflict.md")["SAC-MT"]
    assert row[1] == "2" and row[2].startswith("40.0 [")
    results = json.loads((tmp_path / "figures" / "results_toy-conflict.json").read_text())
    assert [record["seed"] for record in results] == [0, 1]


def test_include_unfinished_counts_a_stopped_run_and_the_tables_mark_it(runs_with_a_stopped_one, tmp_path, capsys):
    root, _ = runs_with_a_stopped_one
    plot.main([str(root), "--out", str(tmp_path / "figures"), "--reps", "10", "--include-unfinished"])
    assert "Left out" not in capsys.readouterr().err
    table = (tmp_path / "figures" / "table1_toy-conflict.md").read_text()
    assert table.splitlines()[2].endswith("| Unfinished |") and "Unfinished: a run that did not finish" in table
    row = table_rows(tmp_path / "figures" / "table1_toy-conflict.md")["SAC-MT"]
    assert row[1] == "3" and row[-1] == "seed 2"
    runs = (tmp_path / "figures" / "runs_toy-conflict.md").read_text()
    assert [line.split("|")[2].strip() for line in runs.splitlines() if line.startswith("| SAC-MT")] == [
        "0",
        "1",
        "2 (unfinished)",
    ]
    results = json.loads((tmp_path / "figures" / "results_toy-conflict.json").read_text())
    assert [record.get("unfinished", False) for record in results] == [False, False, True]


def test_a_finished_benchmark_has_no_unfinished_column(runs_with_a_stopped_one, tmp_path):
    root, stopped = runs_with_a_stopped_one
    info = json.loads((stopped / "run_info.json").read_text())
    (stopped / "run_info.json").write_text(json.dumps({**info, "finished": True, "timesteps": BUDGET}))
    plot.main([str(root), "--out", str(tmp_path / "figures"), "--reps", "10", "--include-unfinished"])
    table = (tmp_path / "figures" / "table1_toy-conflict.md").read_text()
    assert "Unfinished" not in table and table_rows(tmp_path / "figures" / "table1_toy-conflict.md")["SAC-MT"][1] == "3"


def test_only_stopped_runs_say_to_resume_or_include_them(tmp_path, capsys):
    stopped = stopped_run(tmp_path / "runs")
    with pytest.raises(SystemExit) as exit_info:
        plot.main([str(tmp_path / "runs"), "--out", str(tmp_path / "figures"), "--reps", "10"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0] == left_out_line(stopped)
    assert err[1].endswith(
        "every run stopped before its budget (each named above): resume them, or give "
        "--include-unfinished to draw them, marked unfinished"
    )


def test_record_skips_a_stopped_run_and_keeps_it_unfinished_when_asked(runs_with_a_stopped_one, tmp_path, capsys):
    """record names the stopped run and skips it; with --include-unfinished its record says it did not finish, so
    plot on the records leaves it out as it does from the run folder."""
    root, stopped = runs_with_a_stopped_one
    written = records.main([str(root), "--out", str(tmp_path / "records")])
    assert [path.name for path in written] == ["mtsac_mt_seed0.json", "mtsac_mt_seed1.json"]
    assert capsys.readouterr().err.strip().splitlines() == [left_out_line(stopped, "the records", "records")]
    written = records.main([str(root), "--out", str(tmp_path / "records"), "--include-unfinished"])
    assert json.loads(written[-1].read_text())["budget"] == {"n_timesteps": BUDGET, "timesteps": 400, "finished": False}
    capsys.readouterr()
    plot.main([str(tmp_path / "records"), "--out", str(tmp_path / "figures"), "--reps", "10"])
    assert capsys.readouterr().err.strip().splitlines() == [left_out_line(written[-1])]
    assert table_rows(tmp_path / "figures" / "table1_toy-conflict.md")["SAC-MT"][1] == "2"


def test_record_says_when_every_evaluated_run_is_unfinished(tmp_path, capsys):
    stopped_run(tmp_path / "runs")
    with pytest.raises(SystemExit) as exit_info:
        records.main([str(tmp_path / "runs"), "--out", str(tmp_path / "records")])
    assert exit_info.value.code == 2
    assert (
        capsys.readouterr()
        .err.strip()
        .splitlines()[-1]
        .endswith("resume them, or give --include-unfinished to record them as unfinished")
    )


def labelled_run(root: Path, algo: str, label: str, seed: int, final: float, **info: object) -> Path:
    """A two-evaluation run of ``label`` on toy-conflict with its final evaluation at ``final``."""
    run = write_run(root / algo, seed, [0.0, final], final, **{"finished": True, "timesteps": BUDGET, **info})
    fields = json.loads((run / "run_info.json").read_text())
    (run / "run_info.json").write_text(json.dumps({**fields, "algo": algo, "label": label}))
    return run


def test_compare_leaves_out_a_stopped_run_unless_asked(tmp_path, capsys):
    root = tmp_path / "runs"
    for seed, (ours, sac) in enumerate([(0.6, 0.3), (0.8, 0.4)]):
        labelled_run(root, "mtsacte", "Ours", seed, ours)
        labelled_run(root, "mtsac_mt", "SAC-MT", seed, sac)
    stopped = labelled_run(root, "mtsacte", "Ours", 2, 0.0, finished=False, timesteps=400)
    argv = [str(root), "--benchmark", "toy-conflict", "--reps", "10"]
    report = compare.main(argv)
    assert capsys.readouterr().err.strip().splitlines() == [
        f"Left out of the comparison: {stopped} (toy-conflict, Ours, seed 2) did not finish: it stopped at 400 of "
        "800 env steps; --include-unfinished counts its final evaluation, marked unfinished"
    ]
    assert "| all seeds | 2 | 2 | 70.0 / 35.0 |" in report
    report = compare.main([*argv, "--include-unfinished"])
    assert "| all seeds | 3 (1 unfinished) | 2 | 46.7 / 35.0 |" in report
    assert "| all seeds | Ours | 3 (1 unfinished) |" in report


def test_compare_and_plot_count_the_same_runs_by_one_rule(tmp_path, capsys):
    """A finished run not yet evaluated counts at its last periodic evaluation in both; a run with no evaluation at
    all is named, with the command that evaluates it, and counted in neither (not at its training episodes)."""
    root = tmp_path / "runs"
    for seed, (ours, sac) in enumerate([(0.6, 0.3), (0.8, 0.4)]):
        labelled_run(root, "mtsacte", "Ours", seed, ours)
        labelled_run(root, "mtsac_mt", "SAC-MT", seed, sac)
    not_evaluated = labelled_run(root, "mtsacte", "Ours", 2, 0.5)
    (not_evaluated / "success.json").unlink()  # its evaluations stay: the last one at 50%
    no_evaluation = labelled_run(root, "mtsac_mt", "SAC-MT", 3, 0.0)
    (no_evaluation / "success.json").unlink()
    (no_evaluation / "evaluations.npz").unlink()
    keys = [task_log_key("rollout/success", i, name) for i, name in enumerate(TASKS)]  # stochastic training episodes
    (no_evaluation / "progress.csv").write_text(f"time/total_timesteps,{','.join(keys)}\n800,0.062,0.062,0.062,0.062\n")
    left_out = (
        f"{no_evaluation} (toy-conflict, SAC-MT, seed 3) has no evaluation to score; evaluate its model with "
        "sb3-mtte evaluate"
    )
    report = compare.main([str(root), "--benchmark", "toy-conflict", "--reps", "10"])
    assert capsys.readouterr().err.strip().splitlines() == [f"Left out of the comparison: {left_out}"]
    assert "| all seeds | 3 | 2 | 63.3 / 35.0 |" in report
    assert "Counted at their last periodic evaluation, having no final one: Ours seed 2." in report
    plot.main([str(root), "--out", str(tmp_path / "figures"), "--reps", "10"])
    assert f"Left out of Table 1: {left_out}" in capsys.readouterr().err.splitlines()
    rows = table_rows(tmp_path / "figures" / "table1_toy-conflict.md")
    assert (rows["Ours"][1], rows["SAC-MT"][1]) == ("3", "2")
    assert rows["SAC-MT"][2].startswith("35.0 [")  # seed 3's training episodes (6.2%) are not a final success


# ================================================================================================= no variance
def test_welch_t_without_variance_is_undefined_and_warns_nothing():
    """Every run of both at 100%: the difference is 0 with a point interval, and Welch's t (a division by the
    runs' spread) is not computed: no RuntimeWarning, and the tables say why."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        diff = mean_difference(np.ones(3), np.ones(2))
        runs = [
            hand_run(label, seed, [[1, 1]] * 2, [[1.0, 1.0]], [1.0, 1.0])
            for label in ("Ours", "SAC-MT")
            for seed in (0, 1)
        ]
        report = comparison_report("MT2", runs, Comparison(), reps=10)
        summary = comparison_summary("MT2", runs, Comparison())
    assert (diff.value, diff.low, diff.high, diff.welch_defined) == (0.0, 0.0, 0.0, False)
    assert "| all seeds | 2 | 2 | 100.0 / 100.0 | 0.0 [0.0, 0.0] | undefined: no variance | - |" in report
    assert "+0.0 points [0.0, 0.0], Welch t undefined: no variance" in summary and "nan" not in report + summary


def test_one_spread_is_enough_for_welch_t():
    """a = (0.4, 0.6), b = (1, 1): se^2 = 0.02 / 2 + 0, t = -0.5 / 0.1 = -5 with df = 1, without a warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        diff = mean_difference(np.array([0.4, 0.6]), np.ones(2))
    assert diff.welch_defined and (diff.t, diff.df) == pytest.approx((-5.0, 1.0))


# ================================================================================================= one rounding
def test_the_largest_window_loss_reads_the_same_in_compare_and_in_plot_s_table():
    """A window mean of 0.0776 is 0.0776 in the Bellman table and in the comparison's runaway table (not 0.1)."""
    runs = [hand_run(label, 0, [[0.0776, 0.01]] * 6, [[0.5, 0.5]] * 3, [0.5, 0.5]) for label in ("Ours", "SAC-MT")]
    table = bellman_table("MT2", {"Ours": runs[:1], "SAC-MT": runs[1:]})
    report = comparison_report("MT2", runs, Comparison(), reps=10)
    assert "| Ours | 0 | 0.0776 reach | 0.0776 reach | 0.0776 reach | 0.0776 reach | - |" in table
    assert "| Ours | 0 | 0.0776 reach | no | - | 50.0 |" in report


# ===================================================================================================== progress
def test_plot_names_each_benchmark_and_each_file_as_it_goes(runs_with_a_stopped_one, tmp_path, capsys):
    root, _ = runs_with_a_stopped_one
    written = plot.main([str(root), "--out", str(tmp_path / "figures"), "--reps", "10", "--include-unfinished"])
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "toy-conflict (1 of 1): 3 runs of 1 algorithm"
    assert [line for line in out if line.startswith("  wrote ")] == [f"  wrote {path}" for path in written]


# ====================================================================================================== figures
@pytest.fixture
def kept_figures(monkeypatch) -> dict:
    kept: dict = {}
    for module in (figures, summary_figures):
        monkeypatch.setattr(module, "save_figure", lambda fig, path, opts, written: kept.__setitem__(path.name, fig))
    return kept


def test_every_panel_grid_has_axis_labels(tmp_path, kept_figures):
    """Per task (success), per task soft Bellman error and train frequency: each panel with none below it names the x
    axis, the first column the success axis, the last column the right axis (the four tasks fill one row)."""
    for seed in (0, 1):
        run = write_run(tmp_path / "runs", seed, [0.1, 0.2], 0.2, finished=True, timesteps=BUDGET)
        write_critic_log(run, None)
        write_nt_log(run, [5_010, 10_010])
    plot.main([str(tmp_path / "runs"), "--out", str(tmp_path / "figures"), "--reps", "10"])
    right = {
        "bellman_toy-conflict_SAC-MT.png": "soft Bellman error J^Q",
        "train_frequency_toy-conflict_SAC-MT.png": "train frequency",
        "per_task_toy-conflict.png": None,
    }
    for name, right_label in right.items():
        panels = [ax for ax in kept_figures[name].axes if ax.get_title()]
        assert len(panels) == len(TASKS), name
        assert {ax.get_xlabel() for ax in panels} == {"environment steps per task"}, name
        assert [ax.get_ylabel() for ax in panels] == ["success rate (%)", "", "", ""], name  # one row of four
        twins = [ax for ax in kept_figures[name].axes if not ax.get_title() and ax.get_ylabel()]
        assert [ax.get_ylabel() for ax in twins] == ([right_label] if right_label else []), name


def test_the_profile_drops_in_steps(runs_with_a_stopped_one, tmp_path, kept_figures):
    root, _ = runs_with_a_stopped_one
    plot.main([str(root), "--out", str(tmp_path / "figures"), "--reps", "10"])
    lines = kept_figures["profile_toy-conflict.png"].axes[0].get_lines()
    assert lines and {line.get_drawstyle() for line in lines} == {"steps-post"}


@pytest.mark.parametrize(("seeds", "said"), [((0,), "seed 0"), ((0, 1, 2), "mean over seeds 0, 1 and 2")])
def test_the_transfer_matrix_says_which_seeds_it_draws(tmp_path, kept_figures, seeds, said):
    for seed in seeds:
        write_nt_log(write_run(tmp_path / "runs", seed, [0.1], 0.5, finished=True), [5_010, 10_010])
    plot.main([str(tmp_path / "runs"), "--out", str(tmp_path / "figures"), "--reps", "10"])
    title = " ".join(kept_figures["nt_matrix_toy-conflict_SAC-MT.png"].get_suptitle().split())
    assert title.startswith(f"toy-conflict, SAC-MT, {said}: J_i(theta^k) - J_i(theta)")


def test_record_on_a_stopped_run_names_resume_and_its_last_checkpoint(tmp_path, capsys):
    run = write_run(tmp_path / "runs", 0, [0.0], None, finished=False, timesteps=400)
    for steps in (200, 400):
        (run / f"rl_model_{steps}_steps.zip").write_bytes(b"")
    with pytest.raises(SystemExit):
        records.main([str(tmp_path / "runs"), "--out", str(tmp_path / "records")])
    skipped = [line for line in capsys.readouterr().err.splitlines() if line.startswith("Skipped")]
    assert skipped == [
        f"Skipped {run} (toy-conflict, SAC-MT, seed 0): no final evaluation (success.json); it has no final model: "
        f"finish it with sb3-mtte train --resume {run}, or evaluate its last checkpoint: sb3-mtte evaluate "
        f"{run / 'rl_model_400_steps.zip'} --episodes 50"
    ]
