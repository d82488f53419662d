"""Tests of plot on run folders: runs that stopped before their budget, and the times of the transfer-matrix
heatmaps."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from sb3_mtte.experiments.results import figures, plot, summary_figures

TASKS = ["agree-0", "agree-1", "agree-2", "conflict"]
BUDGET = 800  # env steps, all tasks


def write_run(root: Path, seed: int, evaluations: list[float], final: float | None, **info: object) -> Path:
    """A toy-conflict run folder of SAC-MT: evaluations every 200 env steps at the given mean success (every task
    alike), ``success.json`` when ``final`` is given, and ``run_info.json`` with ``info``."""
    run = root / "mtsac_mt" / f"toy-conflict_{seed + 1}"
    run.mkdir(parents=True)
    fields = {"algo": "mtsac_mt", "label": "SAC-MT", "env_id": "toy-conflict", "seed": seed, "task_names": TASKS}
    (run / "run_info.json").write_text(json.dumps({**fields, "n_tasks": 4, "n_timesteps": BUDGET, **info}))
    steps = 200 * np.arange(1, len(evaluations) + 1)
    rates = np.repeat(np.asarray(evaluations, dtype=float)[:, None], len(TASKS), axis=1)
    np.savez(run / "evaluations.npz", timesteps=steps, success_rate=rates, task_names=np.array(TASKS))
    if final is not None:
        (run / "success.json").write_text(json.dumps({"mean": final, "per_task": dict.fromkeys(TASKS, final)}))
    return run


def table_rows(path: Path) -> dict[str, list[str]]:
    rows = [[cell.strip() for cell in line.split("|")[1:-1]] for line in path.read_text().splitlines()]
    return {row[0]: row for row in rows[2:] if row}


@pytest.fixture
def runs_with_a_crash(tmp_path: Path) -> tuple[Path, Path]:
    """Seed 0 evaluated at the end (50%), seed 1 trained its budget with no final evaluation (last one 25%),
    seed 2 crashed at 200 of 800 env steps (one evaluation, 0%)."""
    root = tmp_path / "runs"
    write_run(root, 0, [0.0, 0.1, 0.2, 0.3], 0.5, finished=True, timesteps=BUDGET)
    write_run(root, 1, [0.0, 0.1, 0.2, 0.25], None, finished=True, timesteps=BUDGET)
    return root, write_run(root, 2, [0.0], None, finished=False)


def test_a_run_that_crashed_is_named_and_left_out_of_table_1(runs_with_a_crash, tmp_path, capsys):
    """A run with no final evaluation short of its budget is not a 0% seed: Table 1 and the runs table count the
    two others (a run that trained its whole budget counts at its last evaluation), and one line names it."""
    root, crashed = runs_with_a_crash
    plot.main([str(root), "--out", str(tmp_path / "figures"), "--reps", "10"])
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"Left out of every figure and table: {crashed} (toy-conflict, SAC-MT, seed 2) has no final evaluation and "
        "stopped at 200 "
        "of 800 env steps; --include-unfinished counts its last evaluation"
    ]
    row = table_rows(tmp_path / "figures" / "table1_toy-conflict.md")["SAC-MT"]
    assert row[1] == "2" and row[2].startswith("37.5 [")
    runs = (tmp_path / "figures" / "runs_toy-conflict.md").read_text()
    assert [line.split("|")[2].strip() for line in runs.splitlines() if line.startswith("| SAC-MT")] == ["0", "1"]
    results = json.loads((tmp_path / "figures" / "results_toy-conflict.json").read_text())
    assert [record["seed"] for record in results] == [0]


def test_include_unfinished_counts_a_crashed_run_at_its_last_evaluation(runs_with_a_crash, tmp_path, capsys):
    root, _ = runs_with_a_crash
    plot.main([str(root), "--out", str(tmp_path / "figures"), "--reps", "10", "--include-unfinished"])
    assert "Left out" not in capsys.readouterr().err
    row = table_rows(tmp_path / "figures" / "table1_toy-conflict.md")["SAC-MT"]
    assert row[1] == "3" and row[2].startswith("25.0 [")


def test_a_run_left_out_of_table_1_is_left_out_of_every_figure(runs_with_a_crash, tmp_path, kept_figures):
    """The crashed run is not drawn either: the success figure counts two seeds and its curves reach the end of the
    budget (not the crashed run's last evaluation); --include-unfinished draws all three."""
    root, _ = runs_with_a_crash
    for flags, n, end in (([], 2, BUDGET), (["--include-unfinished"], 3, 200)):
        plot.main([str(root), "--out", str(tmp_path / "figures"), "--reps", "10", *flags])
        axes = kept_figures["success_toy-conflict.png"].axes
        labels = {text.get_text() for ax in axes if ax.get_legend() for text in ax.get_legend().get_texts()}
        assert f"SAC-MT (n={n})" in labels, labels
        ends = {max(line.get_xdata()) * 4 for ax in axes for line in ax.get_lines() if len(line.get_xdata())}
        assert ends == {end}, ends


def test_only_unfinished_runs_end_with_one_line_naming_the_flag(tmp_path, capsys):
    write_run(tmp_path / "runs", 2, [0.0], None, finished=False)
    with pytest.raises(SystemExit) as exit_info:
        plot.main([str(tmp_path / "runs"), "--out", str(tmp_path / "figures"), "--reps", "10"])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.endswith("evaluate them, or give --include-unfinished to draw them at their last evaluation")


def write_nt_log(run: Path, per_task_steps: list[int]) -> None:
    """Recomputations at the given env steps per task (4 tasks), each with a transfer matrix of its own value."""
    records = [
        {
            "timesteps": 4 * steps,
            "mu": [0.0] * 4,
            "selected": [1.0] * 4,
            "weights": [0.25] * 4,
            "transfer_matrix": np.full((4, 4), -float(j + 1)).tolist(),
        }
        for j, steps in enumerate(per_task_steps)
    ]
    (run / "negative_transfer.jsonl").write_text("".join(json.dumps(record) + "\n" for record in records))


@pytest.fixture
def kept_figures(monkeypatch) -> dict:
    """The figures plot draws from the logs, by file name (none written)."""
    kept: dict = {}
    for module in (figures, summary_figures):
        monkeypatch.setattr(module, "save_figure", lambda fig, path, opts, written: kept.__setitem__(path.name, fig))
    return kept


def test_heatmaps_are_titled_with_the_recomputation_they_draw(tmp_path, kept_figures, capsys):
    """Each heatmap shows the recomputation nearest to its time and says which; a time past the log is skipped with
    a line; two times that draw the same recomputation give one heatmap."""
    run = write_run(tmp_path / "runs", 0, [0.0, 0.1, 0.2, 0.3], 0.5, finished=True, timesteps=BUDGET)
    write_nt_log(run, [5_010, 10_010])
    times = ["1e3", "9e3", "1.2e4", "1e5"]
    plot.main([str(tmp_path / "runs"), "--out", str(tmp_path / "figures"), "--reps", "10", "--matrix-times", *times])
    fig = kept_figures["nt_matrix_toy-conflict_SAC-MT.png"]
    heatmaps = [ax for ax in fig.axes if ax.images]
    assert [ax.get_title() for ax in heatmaps] == ["t = 5,010", "t = 10,010"]
    assert [float(ax.images[0].get_array().mean()) for ax in heatmaps] == [-1.0, -2.0]
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"nt_matrix_toy-conflict_SAC-MT.png: t = 100,000 is past the last recomputation of {run} (seed 0, t = 10,010): "
        "skipped"
    ]


def test_times_past_a_single_recomputation_draw_no_heatmap(tmp_path, kept_figures, capsys):
    """A log with its only recomputation at 5,010 env steps per task: 1e5 and 2.5e6 are both past it, so no heatmap
    is drawn (not two copies of the 5,010 matrix titled 100,000 and 2,500,000)."""
    run = write_run(tmp_path / "runs", 0, [0.0, 0.1, 0.2, 0.3], 0.5, finished=True, timesteps=BUDGET)
    write_nt_log(run, [5_010])
    plot.main(
        [str(tmp_path / "runs"), "--out", str(tmp_path / "figures"), "--reps", "10", "--matrix-times", "1e5", "2.5e6"]
    )
    assert "nt_matrix_toy-conflict_SAC-MT.png" not in kept_figures and "nt_toy-conflict_SAC-MT.png" in kept_figures
    err = capsys.readouterr().err.strip().splitlines()
    assert [re.sub(r"t = [\d,]+ is", "t = T is", line) for line in err] == [
        f"nt_matrix_toy-conflict_SAC-MT.png: t = T is past the last recomputation of {run} (seed 0, t = 5,010): skipped"
    ] * 2


def test_a_time_past_one_seed_s_log_names_that_seed(tmp_path, kept_figures, capsys):
    """Of two seeds, the one whose log stops first limits the heatmaps' times: the line names it."""
    write_nt_log(write_run(tmp_path / "runs", 0, [0.1], 0.5, finished=True), [5_010, 10_010, 15_010])
    short = write_run(tmp_path / "runs", 1, [0.1], 0.5, finished=True)
    write_nt_log(short, [5_010, 10_010])
    plot.main([str(tmp_path / "runs"), "--out", str(tmp_path / "figures"), "--reps", "10", "--matrix-times", "1e5"])
    assert capsys.readouterr().err.strip() == (
        f"nt_matrix_toy-conflict_SAC-MT.png: t = 100,000 is past the last recomputation of {short} (seed 1, "
        "t = 10,010): skipped"
    )


def test_a_run_with_one_evaluation_is_drawn_as_a_dot(tmp_path, kept_figures):
    """A curve of a single evaluation is a point, which a line alone leaves invisible: it gets a marker, and a
    curve of several evaluations stays a plain line."""
    for name, evaluations in (("one", [0.3]), ("four", [0.0, 0.1, 0.2, 0.3])):
        write_run(tmp_path / name, 0, evaluations, None, finished=False)
        plot.main([str(tmp_path / name), "--out", str(tmp_path / name), "--reps", "10", "--include-unfinished"])
        for figure in ("success_toy-conflict.png", "per_task_toy-conflict.png"):
            lines = [line for ax in kept_figures[figure].axes for line in ax.get_lines()]
            assert lines and all(len(line.get_xdata()) == len(evaluations) for line in lines), figure
            assert {line.get_marker() for line in lines} == {"o" if len(evaluations) == 1 else "None"}, figure


def write_critic_log(run: Path, clip_fractions: list[float] | None) -> None:
    """A progress.csv with every task's critic loss at 200, 400, ... env steps and, when given, the clip's share."""
    columns = ["time/total_timesteps"] + [f"train/critic_loss/{i:02d}_{name}" for i, name in enumerate(TASKS)]
    rows = [[200 * (k + 1)] + [1.0] * len(TASKS) for k in range(len(clip_fractions or [0.0, 0.0]))]
    if clip_fractions is not None:
        columns.append("train/q_loss_clip_fraction")
        rows = [[*row, share] for row, share in zip(rows, clip_fractions, strict=True)]
    lines = [",".join(columns)] + [",".join(str(value) for value in row) for row in rows]
    (run / "progress.csv").write_text("\n".join(lines) + "\n")


def test_the_task_average_bellman_figure_names_the_share_the_clip_dropped(tmp_path, kept_figures):
    """Fig. 6's panel of a clipped run says the mean and largest share of samples the clip dropped over its logging
    windows; a run without the clip says nothing of it."""
    write_critic_log(write_run(tmp_path / "clip", 0, [0.1, 0.2], 0.2, finished=True), [0.001, 0.0, 0.005])
    write_critic_log(write_run(tmp_path / "none", 0, [0.1, 0.2], 0.2, finished=True), None)
    titles = {}
    for name in ("clip", "none"):
        plot.main([str(tmp_path / name), "--out", str(tmp_path / name), "--reps", "10"])
        titles[name] = [ax.get_title() for ax in kept_figures["bellman_avg_toy-conflict.png"].axes if ax.get_title()]
    assert titles["clip"] == [
        "SAC-MT: average over tasks; samples the clip dropped per logging window: mean 0.20%, max 0.50%"
    ]
    assert titles["none"] == ["SAC-MT: average over tasks"]


def test_plot_says_when_it_writes_no_results_file(tmp_path, capsys):
    root = tmp_path / "runs"
    write_run(root, 0, [0.0, 0.2], None, finished=True, timesteps=BUDGET)  # evaluated in training only
    plot.main([str(root), "--out", str(tmp_path / "figures"), "--reps", "10"])
    out = capsys.readouterr().out
    assert "No results file for toy-conflict: none of its runs has a final evaluation" in out
    assert not (tmp_path / "figures" / "results_toy-conflict.json").exists()
