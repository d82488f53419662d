"""Tests of the run records, of the figures and Table 1 drawn from them, and of the aggregate statistics."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from sb3_mtte.experiments import variants
from sb3_mtte.experiments.results import plot, records, summary_figures
from sb3_mtte.experiments.results.bellman_table import bellman_table
from sb3_mtte.experiments.results.runs import Run, read_progress_csv
from sb3_mtte.experiments.results.statistics import (
    aggregate_estimates,
    curve_estimates,
    improvement_probabilities,
    performance_profiles,
)
from sb3_mtte.experiments.results.tables import runs_table

ROOT = Path(__file__).resolve().parent.parent
SAMPLES = Path(__file__).resolve().parent / "data" / "records"
REPS = 60


def sample_records(env_id: str) -> dict[str, list[dict]]:
    """label -> the committed sample records of ``env_id``."""
    by_label: dict[str, list[dict]] = {}
    for path in sorted((SAMPLES / env_id).glob("*.json")):
        record = json.loads(path.read_text())
        by_label.setdefault(record["label"], []).append(record)
    return by_label


def plain_iqm(values: np.ndarray) -> float:
    """Mean of the middle half of the sorted values (their count a multiple of 4)."""
    ordered = np.sort(values.ravel())
    return float(ordered[len(ordered) // 4 : 3 * len(ordered) // 4].mean())


def plain_improvement(x: np.ndarray, y: np.ndarray) -> float:
    """P(X > Y) per task over every pair of runs (ties count one half), averaged over tasks."""
    per_task = [
        np.mean((x[:, None, t] > y[None, :, t]) + 0.5 * (x[:, None, t] == y[None, :, t])) for t in range(x.shape[1])
    ]
    return float(np.mean(per_task))


# ================================================================================================ statistics
def test_mean_and_iqm_match_plain_numpy_and_intervals_are_over_runs():
    scores = np.array([[0.1, 0.9], [0.3, 0.2], [0.8, 0.5], [0.0, 1.0]])  # 4 runs x 2 tasks
    estimates = aggregate_estimates({"a": scores}, reps=REPS, seed=3)["a"]
    assert estimates["mean"].value == pytest.approx(scores.mean())
    assert estimates["iqm"].value == pytest.approx(plain_iqm(scores)) and plain_iqm(scores) != scores.mean()
    for estimate in estimates.values():
        assert estimate.low < estimate.value < estimate.high
    assert aggregate_estimates({"a": scores}, reps=REPS, seed=3)["a"] == estimates  # seeded: reproducible
    assert aggregate_estimates({"a": scores}, reps=REPS, seed=4)["a"] != estimates
    # runs are resampled within each task: identical runs leave no uncertainty even though the tasks differ
    same_runs = np.tile([[0.2, 0.6, 1.0, 0.0]], (3, 1))
    fixed = aggregate_estimates({"b": same_runs}, reps=REPS)["b"]["mean"]
    assert fixed.low == fixed.high == pytest.approx(same_runs.mean())


def test_a_methods_intervals_do_not_move_when_another_method_is_added():
    """Adding a row to the table (a method placed before it, more runs of another) leaves a row's numbers alone."""
    rng = np.random.default_rng(1)
    ours, other, new = rng.uniform(size=(3, 4)), rng.uniform(size=(2, 4)), rng.uniform(size=(5, 4))
    before = aggregate_estimates({"ours": ours}, reps=REPS)
    after = aggregate_estimates({"new": new, "ours": ours}, reps=REPS)
    assert after["ours"] == before["ours"]
    assert (
        improvement_probabilities(ours, {"new": new, "other": other}, reps=REPS)["other"]
        == (improvement_probabilities(ours, {"other": other}, reps=REPS)["other"])
    )
    profile, band = performance_profiles({"ours": ours}, reps=REPS)
    profile_after, band_after = performance_profiles({"new": new, "ours": ours}, reps=REPS)
    np.testing.assert_array_equal(band_after["ours"], band["ours"])
    np.testing.assert_array_equal(profile_after["ours"], profile["ours"])


def test_probability_of_improvement_matches_pairwise_counts():
    ours = np.array([[0.5, 0.2], [0.9, 0.2], [0.4, 0.3]])
    other = np.array([[0.1, 0.2], [0.7, 0.6]])
    result = improvement_probabilities(ours, {"other": other, "worse": np.zeros((2, 2))}, reps=REPS)
    assert result["other"].value == pytest.approx(plain_improvement(ours, other))
    assert result["worse"].value == pytest.approx(plain_improvement(ours, np.zeros((2, 2))))
    assert 0.0 <= result["other"].low <= result["other"].value <= result["other"].high <= 1.0


def test_curve_estimates_average_runs_and_tasks_at_every_time():
    rng = np.random.default_rng(0)
    curves = rng.uniform(size=(3, 2, 5))  # runs x tasks x times
    est = curve_estimates(curves, reps=REPS)
    np.testing.assert_allclose(est["mean"], curves.mean(axis=(0, 1)))
    np.testing.assert_allclose(est["task_mean"], curves.mean(axis=0))
    assert np.all(est["low"] <= est["mean"]) and np.all(est["mean"] <= est["high"]) and np.any(est["low"] < est["high"])
    one_run = curve_estimates(curves[:1], reps=REPS)
    np.testing.assert_allclose(one_run["low"], one_run["high"])


# ================================================================================================ plot from records
def readme_plot_command() -> list[str]:
    """The arguments of the documented command that redraws the figures from docs/records (the README's, else the
    docs')."""
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        lines = set(re.findall(r"^sb3-mtte plot docs/records .*$", path.read_text(), flags=re.MULTILINE))
        if lines:
            (line,) = lines
            return shlex.split(line)[2:]
    raise AssertionError("no line `sb3-mtte plot docs/records ...` in README.md or docs/")


def test_readme_command_draws_one_figure_set_and_table_per_benchmark_from_records(tmp_path, monkeypatch, capsys):
    """The README's command, run on the committed sample records: per benchmark one success figure, one per-task
    grid, one profile and one Table 1 with n, mean and IQM (plain numpy) and an interval beside every number."""
    args = readme_plot_command()
    assert args[:3] == ["docs/records", "--out", "docs/figures"]
    args = [str(SAMPLES), "--out", str(tmp_path), *args[3:], "--reps", str(REPS)]
    figs = {}
    real_save = summary_figures.save_figure

    def keep(fig, path, opts, written):
        figs[path.name] = fig
        real_save(fig, path, opts, written)

    monkeypatch.setattr(summary_figures, "save_figure", keep)
    written = plot.main(args)
    kinds = ("success_{}.png", "per_task_{}.png", "profile_{}.png", "table1_{}.md", "runs_{}.md", "results_{}.json")
    assert sorted(p.name for p in written) == sorted(k.format(b) for b in ("MT10-cpu", "toy-conflict") for k in kinds)
    for env_id in ("MT10-cpu", "toy-conflict"):
        by_label = sample_records(env_id)
        check_table((tmp_path / f"table1_{env_id}.md").read_text(), by_label)
        check_success_figure(figs[f"success_{env_id}.png"], by_label)
    assert (tmp_path / "table1_toy-conflict.md").read_text() in capsys.readouterr().out


def test_success_figure_draws_the_ablations_in_a_panel_of_their_own(tmp_path, monkeypatch):
    """With a Fig. 7 ablation among the records, Ours and its ablation share a second panel; SAC-MT stays in the
    first panel with Ours."""
    records_dir = tmp_path / "records" / "MT10-cpu"
    records_dir.mkdir(parents=True)
    by_label = sample_records("MT10-cpu")
    ablated = {**by_label["Ours"][0], "algo": "mtsacte_novae", "label": "Ours-VAE"}
    ablated["curve"] = {**ablated["curve"], "success_rate": np.asarray(ablated["curve"]["success_rate"]) / 2}
    for record in [*(r for runs in by_label.values() for r in runs), ablated]:
        path = records_dir / f"{record['algo']}_seed{record['seed']}.json"
        path.write_text(json.dumps(record, default=lambda a: a.tolist()))
    figs = {}
    monkeypatch.setattr(
        summary_figures, "save_figure", lambda fig, path, opts, written: figs.__setitem__(path.name, fig)
    )
    plot.main([str(tmp_path / "records"), "--out", str(tmp_path / "figures"), "--reps", str(REPS)])
    by_label["Ours-VAE"] = [json.loads(json.dumps(ablated, default=lambda a: a.tolist()))]
    check_success_figure(figs["success_MT10-cpu.png"], by_label)
    assert [ax.get_title() for ax in figs["success_MT10-cpu.png"].axes] == ["Table 1 and peers", "ablations (Fig. 7)"]
    per_task = figs["per_task_MT10-cpu.png"]
    assert {line.get_label() for line in per_task.axes[0].get_lines()} == {"SAC-MT", "Ours"}
    assert "Fig. 7's ablations: success figure" in per_task.get_suptitle()


@pytest.mark.slow  # long: .ci/run runs it after the default suite
def test_committed_tables_are_what_the_readme_command_draws_from_the_committed_records(tmp_path):
    """docs/figures holds, for every benchmark with records in docs/records, the Table 1, the runs table, the
    aggregate numbers and (where there is one) the comparison fixed before the runs that the README's command draws
    from them now, and the results page includes each Table 1."""
    args = readme_plot_command()
    plot.main([str(ROOT / args[0]), "--out", str(tmp_path), *args[3:]])
    results_page = (ROOT / "docs" / "results.md").read_text()
    benchmarks = sorted(path.name for path in (ROOT / "docs" / "records").iterdir() if path.is_dir())
    assert benchmarks
    for env_id in benchmarks:
        drawn = [f"table1_{env_id}.md", f"runs_{env_id}.md", f"results_{env_id}.json"]
        drawn += [f"bellman_{env_id}.md", f"compare_{env_id}.md"]
        for name in drawn[-2:]:
            assert (ROOT / args[2] / name).exists() == (tmp_path / name).exists(), name
        for name in filter(lambda name: (tmp_path / name).exists(), drawn):
            committed = (ROOT / args[2] / name).read_text()
            assert committed == (tmp_path / name).read_text(), f"{name}: redraw with the README's command"
        assert f"```{{include}} figures/table1_{env_id}.md" in results_page, env_id


def test_an_empty_folder_gets_one_line_naming_the_fix(tmp_path, capsys):
    """record and plot on a folder without runs, and plot with an unknown task, exit with one line that says what to
    give or run."""
    with pytest.raises(SystemExit) as exit_info:
        records.main([str(tmp_path), "--out", str(tmp_path / "records")])
    assert exit_info.value.code == 2
    message = capsys.readouterr().err
    assert message.count("\n") == 1 and "no run folder (run_info.json)" in message and "give train's -f" in message
    unevaluated = tmp_path / "runs" / "mtsac_mt" / "MT10_1"
    unevaluated.mkdir(parents=True)
    (unevaluated / "run_info.json").write_text(json.dumps({"algo": "mtsac_mt", "env_id": "MT10", "seed": 0}))
    with pytest.raises(SystemExit) as exit_info:
        records.main([str(tmp_path / "runs"), "--out", str(tmp_path / "records")])
    skipped, message = capsys.readouterr().err.splitlines()  # the run it skipped and why, then what to do
    assert skipped.startswith(f"Skipped {unevaluated} (MT10, mtsac_mt, seed 0)")
    assert "sb3-mtte evaluate <run folder>" in message
    (tmp_path / "nothing").mkdir()
    with pytest.raises(SystemExit) as exit_info:
        plot.main([str(tmp_path / "nothing"), "--out", str(tmp_path / "figures")])
    assert exit_info.value.code == 2
    message = capsys.readouterr().err
    assert message.count("\n") == 1 and "docs/records" in message and "Traceback" not in message
    with pytest.raises(SystemExit) as exit_info:
        plot.main([str(SAMPLES), "--out", str(tmp_path / "figures"), "--tasks", "reach", "rech"])
    assert exit_info.value.code == 2
    message = capsys.readouterr().err
    assert message.count("\n") == 1 and "--tasks rech: no task of these runs; their tasks: " in message
    assert "drawer-close" in message and not (tmp_path / "figures").exists()


@pytest.mark.parametrize("name", ["mtsac_mt/MT10_1/run_info.json", "MT10/mtsac_mt_seed0.json"])
def test_a_file_that_is_not_json_is_named(tmp_path, name):
    path = tmp_path / name
    path.parent.mkdir(parents=True)
    path.write_text('{"algo": "mtsac_mt",')
    with pytest.raises(SystemExit, match=f"{re.escape(str(path))} is not valid JSON .*: fix or remove it"):
        plot.main([str(tmp_path), "--out", str(tmp_path / "figures")])


def hand_run(label: str, seed: int | None, final: dict | None, last: list[float] | None, git: dict | None) -> Run:
    """A run of three tasks with one periodic evaluation at 0 and a last one at ``last`` (no curve when None)."""
    info = {"label": label, "seed": seed, "task_names": ["a-v3", "b", "c-v2"], "git": git}
    curve = None if last is None else {"timesteps": np.array([1.0, 2.0]), "success_rate": np.array([[0.0] * 3, last])}
    return Run(Path(label), info, evaluations=curve, final=None if final is None else {"per_task": final})


def test_runs_table_lists_every_seed_with_its_final_success_and_tasks_above_zero():
    """One row per run in label order then seed: the final evaluation's mean (the last evaluation's without one),
    the last in-training mean, the tasks above 0 highest first (ties by name, short names) and the short commit;
    unknowns are -."""
    clean = {"dirty": False}
    groups = {
        "Ours": [
            hand_run(
                "Ours", 1, {"a-v3": 0.5, "b": 0.0, "c-v2": 1.0}, [0.2, 0.1, 0.6], {"commit": "abcdef123", **clean}
            ),
            hand_run(
                "Ours", 0, {"a-v3": 0.0, "b": 0.0, "c-v2": 0.0}, [0.0, 0.0, 0.0], {"commit": "1234567aa", **clean}
            ),
            hand_run("Ours", None, {"a-v3": 0.0, "b": 0.2, "c-v2": 0.0}, None, {"commit": "9876543bb", "dirty": True}),
        ],
        "SAC-MT": [
            hand_run("SAC-MT", 2, None, [0.4, 0.4, 0.1], {"commit": "fedcba987", **clean}),
            hand_run("SAC-MT", 3, None, None, None),
        ],
    }
    table = runs_table("MT3", groups)
    rows = [[cell.strip() for cell in line.split("|")[1:-1]] for line in table.splitlines() if line.startswith("| ")]
    assert rows[1:] == [
        ["SAC-MT", "2", "30.0", "30.0", "a 40, b 40, c 10", "fedcba9"],
        ["SAC-MT", "3", "-", "-", "-", "-"],
        ["Ours", "-", "6.7", "-", "b 20", "9876543 (dirty)"],
        ["Ours", "0", "0.0", "0.0", "none", "1234567"],
        ["Ours", "1", "50.0", "30.0", "c 100, a 50", "abcdef1"],
    ]


def check_table(table: str, by_label: dict[str, list[dict]]) -> None:
    header, _, *rows = [line.split("|")[1:-1] for line in table.splitlines() if line.startswith("|")]
    assert [h.strip() for h in header][:5] == ["Algorithm", "n", "Mean success (%)", "IQM (%)", "P(Ours > X)"]
    ours = np.array([[r["final"]["per_task"][t] for t in r["task_names"]] for r in by_label["Ours"]])
    assert len(rows) == len(by_label)
    for row in rows:
        label, n, mean, iqm, improvement = (cell.strip() for cell in row[:5])
        scores = np.array([[r["final"]["per_task"][t] for t in r["task_names"]] for r in by_label[label]])
        assert int(n) == len(by_label[label])
        cells = [(mean, 100 * scores.mean(), 1), (iqm, 100 * plain_iqm(scores), 1)]
        if label != "Ours":
            cells.append((improvement, plain_improvement(ours, scores), 2))
        for cell, expected, digits in cells:
            value, low, high = map(float, re.fullmatch(r"(\S+) \[(\S+), (\S+)\]", cell).groups())
            assert value == pytest.approx(round(expected, digits), abs=10**-digits / 2 + 1e-9), (label, cell)
            assert low <= value <= high and low < high, (label, cell)


def check_success_figure(fig, by_label: dict[str, list[dict]]) -> None:
    """One line per method, labelled with its n, on the mean over seeds and tasks of the recorded curves; an
    ablation (Fig. 7) is drawn in a panel of its own beside the method it ablates, every other method in the first."""
    fig7 = variants.ablation_labels()
    has_ablations = any(label in fig7[1:] for label in by_label)
    panels = [{line.get_label(): line for line in ax.get_lines()} for ax in fig.axes]
    assert len(panels) == 1 + has_ablations
    name = {label: f"{label} (n={len(runs)})" for label, runs in by_label.items()}
    assert set(panels[0]) == {name[label] for label in by_label if label not in fig7[1:]}
    if has_ablations:
        assert set(panels[1]) == {name[label] for label in by_label if label in fig7}
    bands = [sum(len(runs) > 1 for label, runs in by_label.items() if name[label] in panel) for panel in panels]
    assert [len(ax.collections) for ax in fig.axes] == bands  # a band per method with more than one run
    for panel in panels:
        for label, runs in by_label.items():
            if name[label] in panel:
                expected = 100 * np.mean([r["curve"]["success_rate"] for r in runs], axis=(0, 2))
                np.testing.assert_allclose(panel[name[label]].get_ydata(), expected, atol=1e-9)


# ================================================================================================ records
def loss_run(label: str, seed: int, losses: list[list[float]], clip: list[float] | None, evals: list | None) -> Run:
    """Two tasks (reach, push) whose critic losses ``(points, 2)`` are logged every 10k env steps (5k per task),
    evaluated at ``evals`` env steps (all tasks; None: no evaluation, only training episodes' success)."""
    steps = np.arange(1, len(losses) + 1) * 10_000.0
    values = np.asarray(losses, dtype=float)
    scalars = {f"train/critic_loss/{i:02d}_{name}": (steps, values[:, i]) for i, name in enumerate(["reach", "push"])}
    scalars["rollout/success_rate"] = (steps, np.zeros(len(steps)))
    if clip is not None:
        scalars["train/q_loss_clip_fraction"] = (steps[: len(clip)], np.asarray(clip))
    curve = None if evals is None else {"timesteps": np.asarray(evals), "success_rate": np.zeros((len(evals), 2))}
    info = {"label": label, "seed": seed, "task_names": ["reach-v3", "push-v3"]}
    return Run(Path(label), info, evaluations=curve, scalars=scalars)


def test_bellman_table_names_the_task_with_the_largest_mean_critic_loss_between_evaluations():
    """Per window between evaluations (per task: (0, 20k], (20k, 40k], those of the run evaluated furthest, not of
    the one evaluated most often) the task whose mean critic loss over the window's points is the largest, and that
    mean; the peak over the run; the clip's mean and largest share (%). A point with a missing loss is left out; a
    run without evaluations or critic losses has no row."""
    ours = [[1, 2], [2, 2], [3, 2], [4, 2], [10, 1], [10, 1], [10, 1], [10, 51]]
    short = [[1, 3], [np.nan, 90], [1, 3], [1, 3]]  # logged up to 20k per task only, one reach loss missing
    groups = {
        "Ours": [loss_run("Ours", 0, ours, [0.001, 0.001, 0.004], [0.0, 40_000.0, 80_000.0])],
        "SAC-MT": [
            loss_run("SAC-MT", 1, short, None, [40_000.0]),
            loss_run("SAC-MT", 2, short, None, None),
            loss_run("SAC-MT", 4, [[2, 1]] * 4, None, [20_000.0, 40_000.0, 60_000.0]),
            Run(Path("x"), {"label": "SAC-MT", "seed": 3, "task_names": ["reach-v3", "push-v3"]}),
        ],
    }
    note, table = bellman_table("MT2", groups).split("\n\n")
    assert note.startswith("MT2: the soft Bellman error")
    assert table.splitlines()[0] == "| Algorithm | Seed | 0-20k | 20k-40k | Peak | Clip dropped (mean / max, %) |"
    assert table.splitlines()[2:] == [
        "| SAC-MT | 1 | 3 push | - | 3 push | - |",
        "| SAC-MT | 4 | 2 reach | - | 2 reach | - |",
        "| Ours | 0 | 2.5 reach | 13.5 push | 51 push | 0.20 / 0.40 |",
    ]
    assert bellman_table("MT2", {"SAC-MT": groups["SAC-MT"][3:]}) is None


def test_a_record_of_a_newer_format_is_refused(tmp_path):
    record = json.loads(next(SAMPLES.rglob("*.json")).read_text())
    (tmp_path / "r.json").write_text(json.dumps({**record, "record_version": records.RECORD_VERSION + 1}))
    with pytest.raises(SystemExit, match="update sb3-mtte"):
        plot.main([str(tmp_path), "--reps", "5"])


def test_committed_samples_have_the_current_format():
    for path in SAMPLES.rglob("*.json"):
        record = json.loads(path.read_text())
        assert record["record_version"] == records.RECORD_VERSION
        assert path == records.record_path(record, SAMPLES)


def test_a_record_keeps_the_per_task_critic_loss_and_clip_fraction_of_its_log(tmp_path):
    """``training`` keeps the per-task critic loss and the clip fraction at up to TRAINING_POINTS evenly spaced dumps
    of progress.csv, and a run read back from the record has them as scalars (Figs. 3 and 6 draw from records)."""
    names = ["reach-v3", "push-v3"]
    steps = np.arange(1, 501) * 10
    keys = [f"train/critic_loss/{i:02d}_{name.removesuffix('-v3')}" for i, name in enumerate(names)]
    lines = ["time/total_timesteps," + ",".join(keys) + ",train/q_loss_clip_fraction"]
    lines += [f"{t},{t * 0.5},{t * 2.0},{t / 1e4}" for t in steps]
    (tmp_path / "progress.csv").write_text("\n".join(lines) + "\n")
    run = Run(tmp_path, {"task_names": names}, scalars=read_progress_csv(tmp_path / "progress.csv"))
    assert run.scalar(keys[1]) is not None, "the test's keys must be the package's"
    training = records.run_record(run)["training"]
    kept = training["env_steps"]
    assert len(kept) == records.TRAINING_POINTS and kept[0] == 10 and kept[-1] == 5000
    assert training["critic_loss"] == [[t * 0.5, t * 2.0] for t in kept]
    assert training["q_loss_clip_fraction"] == [t / 1e4 for t in kept]
    back = records.run_from_record(json.loads(json.dumps(records.run_record(run))), tmp_path / "r.json")
    np.testing.assert_array_equal(back.scalar(keys[1])[1], [t * 2.0 for t in kept])
    np.testing.assert_array_equal(back.scalar("train/q_loss_clip_fraction")[0], kept)


def test_a_record_keeps_how_far_w_was_from_uniform_at_every_recomputation():
    """Total variation distance: uniform w -> 0; (0.7, 0.1, 0.1, 0.1) -> (0.45 + 3 x 0.15) / 2 = 0.45;
    (1, 0, 0, 0) -> (0.75 + 3 x 0.25) / 2 = 0.75 = 1 - 1/N."""
    weights = [[0.25] * 4, [0.7, 0.1, 0.1, 0.1], [1.0, 0.0, 0.0, 0.0]]
    nt = [{"timesteps": 10 * k, "mu": [0] * 4, "selected": [1] * 4, "weights": w} for k, w in enumerate(weights)]
    run = Run(Path("x"), {"task_names": ["a", "b", "c", "d"]}, nt_records=nt)
    representation = records.run_record(run)["representation"]
    assert representation["weights_distance"] == pytest.approx([0.0, 0.45, 0.75])
    assert representation["mean_weights"] == pytest.approx([0.65, 0.35 / 3, 0.35 / 3, 0.35 / 3], abs=1e-6)


def test_a_record_keeps_the_transfer_matrix_harmful_share_and_coupling():
    """T1 = [[1, -1], [2, -4]]: one of two off-diagonal entries below zero; |off| mean 1.5 over |diagonal| mean 2.5
    -> coupling 0.6. T2 = [[2, 0.5], [0.5, -2]]: none harmful; 0.5 / 2 = 0.25."""
    matrices = [[[1.0, -1.0], [2.0, -4.0]], [[2.0, 0.5], [0.5, -2.0]]]
    nt = [
        {"timesteps": 10 * k, "mu": [0, 0], "selected": [1, 1], "weights": [0.5, 0.5], "transfer_matrix": m}
        for k, m in enumerate(matrices)
    ]
    run = Run(Path("x"), {"task_names": ["a", "b"]}, nt_records=nt)
    representation = records.run_record(run)["representation"]
    assert representation["harmful_fraction"] == pytest.approx([0.5, 0.0])
    assert representation["coupling"] == pytest.approx([0.6, 0.25])
    nt[1].pop("transfer_matrix")  # a log that predates the matrix: no field rather than a wrong one
    assert "coupling" not in records.run_record(run)["representation"]
