"""``sb3-mtte train --env-kwargs backend:"'envpool'"``: trains on EnvPool's Meta-World, evaluates on Meta-World's own
envs and records the protocol; without EnvPool, one line and no run folder."""

from __future__ import annotations

import importlib.util
import sys
from typing import Any

import numpy as np
import pytest

from sb3_mtte.envs import EnvPoolVecEnv
from sb3_mtte.experiments.cli import main
from sb3_mtte.experiments.run_info import read_run_info
from sb3_mtte.experiments.zoo.manager import MultiTaskExperimentManager

needs_envpool = pytest.mark.skipif(
    importlib.util.find_spec("envpool") is None, reason='needs EnvPool: pip install "sb3-mtte[envpool]"'
)
ENV = "reach-v3_push-v3-smoke"
ALGO = "mtsac_mt"
ENVPOOL = ["--env-kwargs", "backend:'envpool'", "max_episode_steps:50"]
TINY = [
    *("-n", "200", "--eval-freq", "200", "--eval-episodes", "1", "--verbose", "0", "--no-progress"),
    *("--vec-env", "dummy", "-params", "learning_starts:100"),
]


def _train(tmp_path, *flags: str) -> None:
    main(["train", "--algo", ALGO, "--env", ENV, "-f", str(tmp_path), *TINY, *flags])


@needs_envpool
def test_a_zoo_run_trains_on_envpool_and_evaluates_on_metaworld(tmp_path, monkeypatch):
    seen: dict[str, Any] = {}
    learn = MultiTaskExperimentManager.learn

    def watched(manager: MultiTaskExperimentManager, model: Any) -> None:
        seen["train"] = type(model.get_env())
        seen["eval_kwargs"] = dict(manager.eval_env_kwargs)
        learn(manager, model)

    monkeypatch.setattr(MultiTaskExperimentManager, "learn", watched)
    _train(tmp_path, *ENVPOOL)
    run = tmp_path / ALGO / f"{ENV}_1"
    assert seen["train"] is EnvPoolVecEnv  # each pool's step is sent before any is received
    assert seen["eval_kwargs"] == {"max_episode_steps": 50}  # Meta-World's own envs: EnvPool refuses evaluation
    with np.load(run / "evaluations.npz") as data:
        assert list(data["timesteps"]) == [200] and data["success_rate"].shape == (1, 2)
    info = read_run_info(run)
    assert info["finished"] and info["env_protocol"]["backend"] == "envpool"
    assert not info["env_protocol"]["benchmark_protocol"] and len(info["env_protocol"]["differences"]) == 3


@needs_envpool
def test_envpool_as_the_evaluation_backend_is_refused_in_one_line(tmp_path):
    with pytest.raises(SystemExit) as refused:
        _train(tmp_path, *ENVPOOL, "--eval-env-kwargs", "backend:'envpool'")
    assert "leave backend out of it" in str(refused.value.code) and "\n" not in str(refused.value.code)
    assert not list(tmp_path.iterdir())


def test_a_metaworld_run_records_the_benchmark_protocol(tmp_path):
    _train(tmp_path, "--env-kwargs", "max_episode_steps:50", "--eval-freq", "-1")
    protocol = read_run_info(tmp_path / ALGO / f"{ENV}_1")["env_protocol"]
    assert protocol["backend"] == "metaworld" and protocol["benchmark_protocol"] and protocol["differences"] == []


def test_without_envpool_one_line_and_no_run_folder(tmp_path, monkeypatch):
    for name in [name for name in sys.modules if name == "envpool" or name.startswith("envpool.")]:
        monkeypatch.setitem(sys.modules, name, None)  # an import of EnvPool now fails, as when it is not installed
    monkeypatch.setitem(sys.modules, "envpool", None)
    monkeypatch.setitem(sys.modules, "envpool.mujoco.metaworld.registration", None)
    with pytest.raises(SystemExit) as refused:
        _train(tmp_path, *ENVPOOL)
    assert str(refused.value.code) == '--env-kwargs: backend="envpool" needs EnvPool: pip install "sb3-mtte[envpool]".'
    assert not list(tmp_path.iterdir())
