"""scripts/studies/nt_gain_runs.py reads mu, C_s, w and the transfer matrix of a run folder as its docstring says: a
three-task run with hand-written matrices, each figure computed by hand."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from script_loader import load_script

nt_gain_runs = load_script("scripts/studies/nt_gain_runs.py")

T1 = [[1.0, -0.1, 0.2], [0.1, 2.0, -0.2], [-0.3, 0.3, 1.0]]
T2 = [[2.0, 0.4, 0.4], [0.4, 2.0, 0.4], [-0.4, -0.4, 2.0]]


def softmax_weights(mu: list[int]) -> list[float]:
    exps = [math.exp(len(mu) - m) for m in mu]
    return [e / sum(exps) for e in exps]


def write_run(folder: Path, policy_kwargs: object) -> Path:
    folder.mkdir(parents=True)
    names = ["a", "b", "c"]
    info = {"label": "Ours", "env_id": "toy-conflict", "seed": 4, "n_tasks": 3, "task_names": names}
    info["hyperparams"] = {"policy_kwargs": policy_kwargs}
    (folder / "run_info.json").write_text(json.dumps(info))
    lines = []
    iterations = [(T1, [1, 1, 1], [1, 1, 1])] + [(T2, [0, 0, 2], [1, 1, 0])] * 2
    for step, (matrix, mu, selected) in enumerate(iterations):
        record = {"timesteps": 150 * (step + 1), "mu": mu, "selected": selected, "weights": softmax_weights(mu)}
        record.update(transfer_matrix=matrix, task_probe_accuracy=0.6 + 0.1 * step)
        lines.append(json.dumps(record))
    (folder / "negative_transfer.jsonl").write_text("\n".join(lines) + "\n")
    (folder / "success.json").write_text(json.dumps({"per_task": {"a": 1.0, "b": 0.5, "c": 0.0}}))
    return folder


def test_run_summary_by_hand(tmp_path):
    write_run(tmp_path / "toy_gain1" / "toy-conflict_5", {"net_arch": [64, 64], "z_mean_init_gain": 1})
    result = nt_gain_runs.study([tmp_path / "toy_gain1"], {"toy-conflict": 2})
    (run,) = result["runs"]["toy-conflict, gain 1"]
    assert run["iterations"] == 3
    assert run["harmful_fraction"] == pytest.approx(7 / 18)  # 3 + 2 + 2 of 6 off-diagonal entries each
    assert run["harmful_fraction_first_quarter"] == pytest.approx(3 / 6)
    # mean |off-diagonal| / mean |diagonal|: T1 0.2 / (4/3) = 0.15, T2 0.4 / 2 = 0.2; median of (0.15, 0.2, 0.2)
    assert run["coupling"] == pytest.approx(0.2)
    assert run["coupling_first_quarter"] == pytest.approx(0.15)
    assert run["conflicting_row_mean"] == pytest.approx(-0.2)  # rows: 0 / (4/3), -0.4 / 2, -0.4 / 2
    assert run["conflicting_strictly_largest"] == pytest.approx(2 / 3)  # a tie, then largest twice
    assert run["weights_consecutive_correlation"] == pytest.approx(1.0)  # uniform w is skipped; then equal rows
    w = softmax_weights([0, 0, 2])
    distance = 0.5 * sum(abs(x - 1 / 3) for x in w)
    assert run["weights_distance"] == pytest.approx(2 / 3 * distance)
    assert run["weights_distance_first_quarter"] == pytest.approx(0.0, abs=1e-12)
    assert run["mean_mu"] == pytest.approx([1 / 3, 1 / 3, 5 / 3], abs=1e-4)
    assert run["selected_fraction"] == pytest.approx([1.0, 1.0, 1 / 3], abs=1e-4)
    assert run["most_harmful_task"] == 2
    assert run["probe_of_sampled_z"] == pytest.approx((0.6 + 0.7 + 0.8) / 3)
    assert run["final_success"] == pytest.approx(0.5)


def test_gain_of_each_form_of_policy_kwargs(tmp_path):
    write_run(tmp_path / "a" / "run_1", {"z_mean_init_gain": 1})
    write_run(tmp_path / "b" / "run_1", "dict(net_arch=[400, 400], z_mean_init_gain=3.5)")
    write_run(tmp_path / "c" / "run_1", "dict(net_arch=[64, 64])")
    result = nt_gain_runs.study([tmp_path / "a", tmp_path / "b", tmp_path / "c"], {})
    assert sorted(result["summary"]) == ["toy-conflict, gain 1", "toy-conflict, gain 3.5", "toy-conflict, gain 50"]
    assert "conflicting_row_mean" not in result["runs"]["toy-conflict, gain 1"][0]


def test_bad_conflicting_argument_names_the_form():
    with pytest.raises(SystemExit, match="BENCHMARK=TASK_INDEX"):
        nt_gain_runs.parse_conflicting(["toy-conflict"])


def test_markdown_table_row_of_one_seed(tmp_path):
    write_run(tmp_path / "toy_gain1" / "toy-conflict_5", {"z_mean_init_gain": 1})
    table = nt_gain_runs.markdown_table(nt_gain_runs.study([tmp_path / "toy_gain1"], {})["summary"])
    row = table.splitlines()[2]
    assert (
        row == "| toy-conflict, gain 1 | 4 | 39% | 50% | 0.200 | 0.150 | +1.00 | 0.18 | 0.70 | 50.0% |"
    )  # w: 2/3 of 0.27


def test_a_run_still_training_is_left_out(tmp_path, capsys):
    write_run(tmp_path / "runs" / "done_1", {"z_mean_init_gain": 1})
    running = write_run(tmp_path / "runs" / "running_1", {"z_mean_init_gain": 1})
    (running / "success.json").unlink()
    info = json.loads((running / "run_info.json").read_text())
    info["hyperparams"]["n_timesteps"] = 10_000
    (running / "run_info.json").write_text(json.dumps(info))
    result = nt_gain_runs.study([tmp_path / "runs"], {})
    assert [r["path"] for r in result["runs"]["toy-conflict, gain 1"]] == [str(tmp_path / "runs" / "done_1")]
    assert f"skipped {running}" in capsys.readouterr().err
    assert len(nt_gain_runs.study([tmp_path / "runs"], {}, running=True)["runs"]["toy-conflict, gain 1"]) == 2


def test_a_conflicting_task_other_than_the_last(tmp_path):
    """Task 0: its off-diagonal row is (-0.1 + 0.2) / 2 over 4/3, then 0.4 / 2 twice; never strictly largest."""
    write_run(tmp_path / "toy_gain1" / "toy-conflict_5", {"z_mean_init_gain": 1})
    (run,) = nt_gain_runs.study([tmp_path / "toy_gain1"], {"toy-conflict": 0})["runs"]["toy-conflict, gain 1"]
    assert run["conflicting_row_mean"] == pytest.approx(0.2)
    assert run["conflicting_strictly_largest"] == 0.0
    assert nt_gain_runs.strictly_largest(np.array([[3, 1, 2], [1, 1, 0]]), 0).tolist() == [True, False]
