"""The measurement of the process defaults: its summary of the runs, its rotation of the cells, its bad input."""

from __future__ import annotations

import argparse

import pytest
from script_loader import load_script

process_defaults = load_script("benchmarks/process_defaults.py")


def test_summary_gives_medians_ratios_and_the_runs_together() -> None:
    pair = {c: [] for c in process_defaults.COMBINATIONS}
    for round_index, rates in enumerate([(10.0, 12.0), (20.0, 22.0), (30.0, 26.0)]):
        for combination, factor in zip(process_defaults.COMBINATIONS, (1, 2, 3, 4), strict=True):
            pair[combination] += [{"env_steps_per_s": rate * factor, "round": round_index} for rate in rates]
    cell = process_defaults.summary({"pair": pair})["pair"]
    assert cell[process_defaults.BASELINE]["median_env_steps_per_s_per_run"] == 21.0
    assert cell[process_defaults.BASELINE]["median_env_steps_per_s_of_the_runs_together"] == 42.0
    assert cell["spin on, malloc on"]["over_baseline"] == 4.0
    assert cell["spin on, malloc on"]["all_env_steps_per_s"] == [40.0, 48.0, 80.0, 88.0, 120.0, 104.0]


def test_each_round_runs_every_cell_once_in_a_rotated_order(monkeypatch: pytest.MonkeyPatch) -> None:
    order = []

    def start_runs(args, scenario, combination):
        order.append((scenario, combination))
        return [{"env_steps_per_s": 1.0} for _ in range(process_defaults.SCENARIOS[scenario])]

    monkeypatch.setattr(process_defaults, "start_runs", start_runs)
    runs = process_defaults.measure(argparse.Namespace(repeats=2))
    cells = len(process_defaults.SCENARIOS) * len(process_defaults.COMBINATIONS)
    assert sorted(order[:cells]) == sorted(order[cells:]) and order[1:cells] == order[cells : 2 * cells - 1]
    assert [len(reports) for reports in runs["pair"].values()] == [4] * len(process_defaults.COMBINATIONS)


@pytest.mark.parametrize("argv", [["--repeats", "0"], ["--warm-steps", "1"], ["--timed-steps", "0"]])
def test_bad_sizes_are_refused(argv: list[str], capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit):
        process_defaults.parse_args(argv)
    assert "at least" in capsys.readouterr().err
