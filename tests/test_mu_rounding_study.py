"""scripts/studies/mu_rounding.py: the old and the exact mu of saved checkpoints, and the study's rule."""

from __future__ import annotations

import pytest
import torch as th
from conftest import small_model_kwargs
from script_loader import load_script

from sb3_mtte import MTSACTE, make_mt_env

mu_rounding = load_script("scripts/studies/mu_rounding.py")


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Two checkpoints of a small toy run: as trained, and with every critic output moved by 1e4."""
    folder = tmp_path_factory.mktemp("mu_rounding")
    model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **small_model_kwargs())
    model.learn(400)
    paths = {}
    for name, shift in (("trained", 0.0), ("shifted", 1e4)):
        with th.no_grad():
            model.policy.critic.q_net.layers[-1].bias.add_(shift)
        model.save(folder / f"{name}.zip")
        model.save_replay_buffer(folder / f"{name}.pkl")
        paths[name] = (folder / f"{name}.zip", folder / f"{name}.pkl")
    return paths


def test_reports_each_batch_and_applies_the_rule(checkpoints, tmp_path):
    trained, shifted = checkpoints["trained"], checkpoints["shifted"]
    args = [*trained, *shifted, *shifted, "--batches", "3", "--batch-size", "8", "--markdown", str(tmp_path / "t.md")]
    result = mu_rounding.main([str(a) for a in args])
    reports = result["checkpoints"]
    assert [len(r["batches"]) for r in reports] == [3, 3, 3]
    for report in reports:
        for row in report["batches"]:
            differing = sum(a != b for a, b in zip(row["mu_old"], row["mu_exact"], strict=True))
            assert row["tasks_with_mu_differing"] == differing
        expected = sum(row["tasks_with_mu_differing"] >= 2 for row in report["batches"])
        assert report["batches_with_mu_differing"] == expected
        assert report["counts"] == (expected >= 2)
    # Q near 1e4: the float32 matrix's signs are rounding, the float64 matrix's are those of the trained model
    assert reports[1]["batches"][0]["mean_abs_q"] > 5e3 > reports[0]["batches"][0]["mean_abs_q"]
    assert sum(row["off_diagonal_signs_differing"] for row in reports[1]["batches"]) > 0
    assert [row["mu_exact"] for row in reports[1]["batches"]] == [row["mu_exact"] for row in reports[2]["batches"]]
    assert result["checkpoints_counting"] == sum(r["counts"] for r in reports)
    assert result["rule_holds"] == (result["checkpoints_counting"] >= 2)
    assert (tmp_path / "t.md").read_text().count("\n") == 2 + 3


def test_refuses_an_unpaired_path(checkpoints):
    with pytest.raises(SystemExit):
        mu_rounding.main([str(checkpoints["trained"][0])])
