"""The pre-registered comparison (sb3_mtte.experiments.results.compare) against hand computations and plain loops."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from sb3_mtte.experiments.results.compare import (
    PREREGISTERED,
    Comparison,
    MeanDifference,
    comparison_report,
    comparison_summary,
    fixed_reading,
    main,
    mean_difference,
    runaway,
)
from sb3_mtte.experiments.results.figures import PlotOptions
from sb3_mtte.experiments.results.plot import _write_table1
from sb3_mtte.experiments.results.runs import Run
from sb3_mtte.experiments.results.tables import benchmark_statistics

TASKS = ["reach-v3", "push-v3"]


def student_t_two_sided_p(t: float, df: float, points: int = 200_000) -> float:
    """Two-sided p of Student's t by the midpoint rule on its density (no library)."""
    norm = math.gamma((df + 1) / 2) / (math.sqrt(df * math.pi) * math.gamma(df / 2))
    upper = abs(t) + 2000.0
    width = (upper - abs(t)) / points
    total = sum(norm * (1 + ((abs(t) + (k + 0.5) * width) ** 2) / df) ** (-(df + 1) / 2) for k in range(points))
    return 2 * total * width


def test_welch_t_and_its_degrees_of_freedom_match_a_hand_computation():
    """a = (0.3, 0.4, 0.5), b = (0.1, 0.2, 0.4): means 0.4 and 0.2333, sample variances 0.01 and 0.023333, so
    se^2 = 0.01/3 + 0.023333/3 = 0.011111, t = 0.16667 / 0.10541 = 1.5811 and
    df = 0.011111^2 / ((0.01/3)^2 / 2 + (0.023333/3)^2 / 2) = 3.4483."""
    diff = mean_difference(np.array([0.3, 0.4, 0.5]), np.array([0.1, 0.2, 0.4]))
    assert diff.value == pytest.approx(0.4 - 0.7 / 3)
    assert diff.t == pytest.approx(1.5811, abs=1e-4)
    assert diff.df == pytest.approx(3.4483, abs=1e-4)
    assert diff.p == pytest.approx(student_t_two_sided_p(1.5811388, 3.4482759), abs=1e-4)


def test_bootstrap_interval_matches_the_exact_bootstrap_distribution():
    """With four runs of one and three of the other, the bootstrap distribution is 4^4 x 3^3 equally likely
    resamples: enumerated, about 2.5% of it lies below the interval and 2.5% above (10,000 random resamples estimate
    its quantiles)."""
    a, b = np.array([0.2, 0.3, 0.35, 0.6]), np.array([0.1, 0.15, 0.5])
    exact = np.array(
        [sum(ra) / 4 - sum(rb) / 3 for ra in itertools.product(a, repeat=4) for rb in itertools.product(b, repeat=3)]
    )
    diff = mean_difference(a, b)
    assert 0.015 < np.mean(exact < diff.low - 1e-9) < 0.035
    assert 0.015 < np.mean(exact > diff.high + 1e-9) < 0.035
    assert diff.low < diff.value < diff.high


def test_runs_without_spread_give_a_point_interval():
    diff = mean_difference(np.array([0.4, 0.4]), np.array([0.1, 0.1, 0.1]))
    assert (diff.low, diff.value, diff.high) == pytest.approx((0.3, 0.3, 0.3))


def hand_run(label: str, seed: int, losses: list[list[float]], success: list[list[float]], final: list[float]) -> Run:
    """Two tasks; critic losses ``(points, 2)`` logged every 5k env steps per task (10k over both); evaluations
    ``success`` ``(evaluations, 2)`` every 10k per task; the final evaluation ``final``."""
    steps = np.arange(1, len(losses) + 1) * 10_000.0
    values = np.asarray(losses, dtype=float)
    scalars = {f"train/critic_loss/{i:02d}_{name[:-3]}": (steps, values[:, i]) for i, name in enumerate(TASKS)}
    evals = {"timesteps": np.arange(1, len(success) + 1) * 20_000.0, "success_rate": np.asarray(success, float)}
    info = {"label": label, "seed": seed, "task_names": TASKS, "env_id": "MT2", "finished": True}
    return Run(Path(f"{label}{seed}"), info, evals, scalars, final={"per_task": dict(zip(TASKS, final, strict=True))})


EDGES = [10_000.0, 20_000.0, 30_000.0]
CALM = [[5, 1]] * 6  # every window mean below 100


def test_a_run_runs_away_when_a_window_mean_passes_the_criterion_and_its_task_fell_with_it():
    """Push's window means: (1, 1), (99, 103) -> 101 in window 2 (above 100): ran away from window 2 on push; its
    best in-training success up to 20k per task is 0.75 (not the 1.0 after), its final 0.5: 0.25 lower, so it fell
    by a criterion of 0.25 (at least that much lower) and not by one of 0.26."""
    losses = [[5, 1], [5, 1], [5, 99], [5, 103], [5, 1], [5, 1]]
    run = hand_run("SAC-MT", 0, losses, [[0, 0.75], [0, 0.5], [0, 1.0]], [0, 0.5])
    found = runaway(run, EDGES, 100.0)
    assert (found.peak, found.task, found.window) == (101.0, 1, 1)
    assert (found.best_before, found.final) == (0.75, 0.5)
    assert found.fell(0.25) and not found.fell(0.26)
    assert runaway(run, EDGES, 101.0).window is None  # strictly above the criterion


def test_a_run_below_the_criterion_did_not_run_away():
    found = runaway(hand_run("Ours", 0, CALM, [[0.5, 0.5]] * 3, [0.5, 0.5]), EDGES, 100.0)
    assert (found.peak, found.task, found.window) == (5.0, 0, None)
    assert not found.fell(0.0)


def four_runs() -> list[Run]:
    """Seeds 0 and 3 of each; final means Ours 0.5 and 0.6, SAC-MT 0.2 and 0.4; SAC-MT's reach ran away in window 2
    in both, from a best of 0.9 before it to 0.4 and 0.8."""
    away = [[5, 1], [5, 1], [200, 1], [200, 1], [5, 1], [5, 1]]
    return [
        hand_run("Ours", 0, CALM, [[0.5, 0.5]] * 3, [0.5, 0.5]),
        hand_run("Ours", 3, CALM, [[0.5, 0.5]] * 3, [0.6, 0.6]),
        hand_run("SAC-MT", 0, away, [[0.9, 0.0]] * 3, [0.4, 0.0]),
        hand_run("SAC-MT", 3, away, [[0.9, 0.0]] * 3, [0.8, 0.0]),
    ]


def test_the_report_gives_the_difference_the_aggregates_and_fishers_test(tmp_path):
    """Seeds 0 and 3 of each, the replication seed 3 alone (n = 1: no test). Final means: Ours 0.5 and 0.6, SAC-MT
    0.2 and 0.4: difference 0.55 - 0.3 = 0.25; with two runs each, a resample's mean difference is 0.1 to 0.4, the
    extremes with chance 1/16 each, so the 95% interval is [0.1, 0.4]. SAC-MT's reach ran away in window 2 in both
    runs, from a best of 0.9 before it to 0.4 (fell) and 0.8 (did not). Fisher's p for [[0, 2], [2, 0]] is
    1/6 + 1/6 = 0.333. P(Ours > SAC-MT) is 0.75."""
    runs = four_runs()
    report = comparison_report("MT2", runs, Comparison(replication_seeds=(3,)), reps=50)
    assert "| seeds 3 | 1 | 1 | - | - | - | - |" in report
    row = next(line for line in report.splitlines() if line.startswith("| all seeds | 2 | 2 |"))
    assert row.split(" | ")[3:5] == ["55.0 / 30.0", "25.0 [10.0, 40.0]"]
    assert "| SAC-MT | 0 | 200.0 reach | yes, from window 2 | yes (90.0 -> 40.0) | 20.0 |" in report
    assert "| SAC-MT | 3 | 200.0 reach | yes, from window 2 | no (90.0 -> 80.0) | 40.0 |" in report
    assert "all seeds: Ours 0 of 2, SAC-MT 2 of 2 runs ran away; Fisher's exact test (two-sided) p = 0.333." in report
    # P(Ours > SAC-MT): reach 2 of 4 pairs (0.5, 0.6 against 0.4, 0.8), push 4 of 4: (0.5 + 1) / 2
    rliable_row = next(line for line in report.splitlines() if line.startswith("| all seeds | SAC-MT | 2 |"))
    assert rliable_row.split(" | ")[3].startswith("30.0 [") and rliable_row.split(" | ")[5].startswith("0.75 [")


def test_the_summary_under_table_1_gives_each_subsets_difference_and_runaway_count():
    """The runs of the report above. All seeds: difference 0.25 [0.1, 0.4]; Welch: variances 0.005 and 0.02, so
    se^2 = 0.0025 + 0.01 and t = 0.25 / sqrt(0.0125) = 2.236. Seed 3 alone: one run each, no difference and no
    reading."""
    summary = comparison_summary("MT2", four_runs(), Comparison(replication_seeds=(3,)))
    assert (
        "Seeds 3 (n = 1 and 1): too few runs for the difference; ran away: 0 of 1 and 1 of 1. Reading fixed before the "
        "runs, on seeds 3: too few runs for an interval. All seeds" in summary
    )
    assert "All seeds (n = 2 and 2): +25.0 points [10.0, 40.0], Welch t 2.24, p " in summary
    assert summary.endswith(
        "; ran away: 0 of 2 and 2 of 2. In full: compare_MT2.md, written beside table1_MT2.md (`sb3-mtte plot`, or "
        "`sb3-mtte compare` alone)."
    )


def test_plot_puts_the_summary_under_table_1_and_writes_the_comparison(tmp_path, monkeypatch):
    """A benchmark with a comparison fixed before its runs gets both; one without, Table 1 alone."""
    runs = four_runs()
    by_label = {"Ours": runs[:2], "SAC-MT": runs[2:]}
    stats = benchmark_statistics(by_label, reps=50)
    opts = PlotOptions(out=tmp_path, reps=50)
    _write_table1("MT2", stats, runs, opts, [])
    assert not (tmp_path / "compare_MT2.md").exists()
    plain = (tmp_path / "table1_MT2.md").read_text()
    cmp = Comparison(replication_seeds=(3,))
    monkeypatch.setitem(PREREGISTERED, "MT2", cmp)
    _write_table1("MT2", stats, runs, opts, [])
    assert (tmp_path / "table1_MT2.md").read_text() == plain + "\n" + comparison_summary("MT2", runs, cmp) + "\n"
    assert (tmp_path / "compare_MT2.md").read_text() == comparison_report("MT2", runs, cmp, reps=50)


@pytest.mark.parametrize(
    ("cmp", "reading"),
    [
        (Comparison(replication_seeds=(0, 3)), "on seeds 0 3: yes, Ours is ahead."),
        (Comparison(a="SAC-MT", b="Ours", replication_seeds=(0, 3)), "on seeds 0 3: Ours is ahead."),
        (
            Comparison(replication_seeds=(0, 3, 5)),
            "on seeds 0 3 5: yes, Ours is ahead; Ours has finished 2 of its 3 runs and SAC-MT 2, so this is not the "
            "answer yet.",
        ),
        (Comparison(replication_seeds=(3,)), "on seeds 3: too few runs for an interval."),
    ],
)
def test_the_fixed_reading_follows_the_replications_interval(cmp, reading):
    """Seeds 0 and 3 of each: Ours minus SAC-MT is 0.25 [0.1, 0.4] (the report above), an interval above 0, so Ours
    is ahead; with the labels swapped the interval is [-0.4, -0.1], below 0, and the second algorithm (Ours) is
    ahead. A replication with a seed not run yet is provisional; one run of each is too few."""
    sentence = f"Reading fixed before the runs, {reading}"
    assert sentence in comparison_summary("MT2", four_runs(), cmp)
    assert sentence in comparison_report("MT2", four_runs(), cmp, reps=20)


@pytest.mark.parametrize(
    ("a", "b", "found"),
    [
        ("Ours", "SAC-MT", "yes, Ours is ahead; Ours has finished 3 of its 3 runs and SAC-MT 2"),
        ("SAC-MT", "Ours", "Ours is ahead; SAC-MT has finished 2 of its 3 runs and Ours 3"),
    ],
)
def test_the_reading_is_provisional_while_either_algorithm_lacks_a_replication_seed(a, b, found):
    """Ours has seeds 0, 3 and 5 (finals 0.5, 0.6, 0.55), SAC-MT seeds 0 and 3 (0.2, 0.4): every resampled difference
    is at least 0.5 - 0.4 = 0.1, so Ours is ahead (in either order), but SAC-MT's seed 5 has not finished."""
    runs = [*four_runs(), hand_run("Ours", 5, CALM, [[0.5, 0.5]] * 3, [0.55, 0.55])]
    summary = comparison_summary("MT2", runs, Comparison(a=a, b=b, replication_seeds=(0, 3, 5)))
    assert f"Reading fixed before the runs, on seeds 0 3 5: {found}, so this is not the answer yet." in summary


def test_a_seed_counts_once_however_many_of_its_runs_finished():
    """Two finished runs of Ours' seed 3 do not stand in for its seed 5."""
    runs = [*four_runs(), hand_run("Ours", 3, CALM, [[0.5, 0.5]] * 3, [0.55, 0.55])]
    summary = comparison_summary("MT2", runs, Comparison(replication_seeds=(0, 3, 5)))
    assert "Ours has finished 2 of its 3 runs and SAC-MT 2, so this is not the answer yet." in summary


@pytest.mark.parametrize(
    ("low", "high", "found"),
    [
        (0.0, 0.1, "not shown (the interval holds 0)"),
        (-0.1, 0.0, "not shown (the interval holds 0)"),
        (0.01, 0.1, "yes, Ours is ahead"),
        (-0.1, -0.01, "SAC-MT is ahead"),
    ],
)
def test_an_interval_that_ends_at_0_holds_it(low, high, found):
    assert fixed_reading(MeanDifference((low + high) / 2, low, high, 1.0, 4.0, 0.5), Comparison()) == found


def test_a_comparison_without_a_replication_has_no_reading():
    assert "Reading" not in comparison_summary("MT2", four_runs(), Comparison())
    assert "Reading" not in comparison_report("MT2", four_runs(), Comparison(), reps=20)


@pytest.mark.parametrize(("a", "b"), [("Ours", "SAC-MT"), ("SAC-MT", "Ours")])
def test_an_interval_that_holds_0_shows_nothing(a, b):
    """Seeds 0 and 3 of each with SAC-MT's finals at 0.4 and 0.6: the difference is +0.05, but a resample's is below
    0 with chance 3/16 (Ours 0.5 or 0.55 against SAC-MT 0.6: 1/4 * 1/4 + 1/2 * 1/4), so the interval holds 0, and
    so it does for SAC-MT minus Ours (-0.05)."""
    runs = four_runs()
    runs[2] = hand_run("SAC-MT", 0, CALM, [[0.5, 0.5]] * 3, [0.4, 0.4])
    runs[3] = hand_run("SAC-MT", 3, CALM, [[0.5, 0.5]] * 3, [0.6, 0.6])
    summary = comparison_summary("MT2", runs, Comparison(a=a, b=b, replication_seeds=(0, 3)))
    assert "Reading fixed before the runs, on seeds 0 3: not shown (the interval holds 0)." in summary


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["missing_folder", "--benchmark", "MT10-100k"], "missing_folder is not a folder"),
        (["{tmp}", "--benchmark", "MT10-100k", "--a", "Nobody"], "no runs of Nobody on MT10-100k"),
        (["{tmp}", "--benchmark", "MT10-100k", "--reps", "0"], "--reps 0: give a number of resamples of at least 1"),
    ],
)
def test_bad_input_gets_one_line(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit):
        main([arg.format(tmp=tmp_path) for arg in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1] and "Traceback" not in "".join(err)


def test_the_committed_records_give_seeds_0_to_2s_runaway_count(capsys):
    """The criterion's source: in MT10-100k seeds 0-2, SAC-MT seeds 0 and 2 ran away on reach, no run of Ours."""
    report = main(["docs/records", "--benchmark", "MT10-100k", "--replication-seeds", "0", "1", "2", "--reps", "20"])
    assert "seeds 0 1 2: Ours 0 of 3, SAC-MT 2 of 3 runs ran away" in report
    assert "| SAC-MT | 2 | 1,692.2 reach | yes, from window 2 | yes (70.0 -> 4.0) | 22.0 |" in report
