"""scripts/studies/mu_rounding.py: the old and the exact mu of saved checkpoints, and the study's rule."""

from __future__ import annotations

import pytest
from conftest import small_model_kwargs
from script_loader import load_script

from sb3_mtte import MTSACTE, make_mt_env

mu_rounding = load_script("scripts/studies/mu_rounding.py")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A model and its replay buffer after a small toy run."""
    folder = tmp_path_factory.mktemp("mu_rounding")
    model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **small_model_kwargs())
    model.learn(400)
    model.save(folder / "model.zip")
    model.save_replay_buffer(folder / "buffer.pkl")
    return folder / "model.zip", folder / "buffer.pkl"


def test_reports_each_batch_and_applies_the_rule(checkpoint, tmp_path):
    args = [*checkpoint, *checkpoint, "--batches", "3", "--batch-size", "8", "--shifts", "1e4"]
    result = mu_rounding.main([str(a) for a in [*args, "--markdown", tmp_path / "t.md"]])
    reports = result["checkpoints"]
    assert [len(r["batches"]) for r in reports] == [3, 3]
    for report in reports:
        for row in [*report["batches"], *(r["shifted"]["10000.0"] for r in report["batches"])]:
            differing = sum(a != b for a, b in zip(row["mu_old"], row["mu_exact"], strict=True))
            assert row["tasks_with_mu_differing"] == differing
        expected = sum(row["tasks_with_mu_differing"] >= 2 for row in report["batches"])
        assert report["batches_with_mu_differing"] == expected
        assert report["counts"] == (expected >= 2)
    assert result["checkpoints_counting"] == sum(r["counts"] for r in reports)
    assert result["rule_holds"] == (result["checkpoints_counting"] >= 2)
    # Q moved to 1e4: the float32 signs turn to rounding, the exact mu stays that of the saved model
    rows = reports[0]["batches"]
    shifted = [row["shifted"]["10000.0"] for row in rows]
    assert all(s["mean_abs_q"] > 5e3 > row["mean_abs_q"] for s, row in zip(shifted, rows, strict=True))
    assert [s["mu_exact"] for s in shifted] == [row["mu_exact"] for row in rows]
    assert sum(s["off_diagonal_signs_differing"] for s in shifted) > sum(
        row["off_diagonal_signs_differing"] for row in rows
    )
    assert (tmp_path / "t.md").read_text().count("\n") == 2 + 2 + 1 + 2 + 2


def test_refuses_an_unpaired_path(checkpoint):
    with pytest.raises(SystemExit):
        mu_rounding.main([str(checkpoint[0])])
