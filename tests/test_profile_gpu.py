"""``benchmarks/profile_gpu.py``: the stages of a vector step are timed where ``learn()`` calls them, and with the
rest they make up the wall time."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import profile_gpu
from bench_updates import quiet, synthetic_env

from sb3_mtte import MTSAC


def warm_model(n_tasks: int = 3) -> MTSAC:
    model = quiet(MTSAC("MlpPolicy", synthetic_env(n_tasks), learning_starts=4 * n_tasks, buffer_size=200,
                        batch_size=8, policy_kwargs=dict(net_arch=[8]), device="cpu", seed=0))  # fmt: skip
    model.learn(model.learning_starts + 2 * n_tasks)
    return model


def test_every_stage_is_timed_once_per_vector_step(monkeypatch):
    model = warm_model()
    calls = {stage: 0 for stage in (*profile_gpu.STAGES, "env")}
    for stage, name in (*profile_gpu.STAGES.items(), ("env", "step")):
        owner = model.env if stage == "env" else model
        original = getattr(owner, name)

        def counted(*args, stage=stage, original=original, **kwargs):
            calls[stage] += 1
            return original(*args, **kwargs)

        monkeypatch.setattr(owner, name, counted)
    split = profile_gpu.split_vector_step(model, "cpu", vector_steps=5)
    assert calls == {"act": 5, "store": 5, "update": 5, "env": 5}
    per_step = split["ms_per_vector_step"]
    assert set(per_step) == {"act", "store", "update", "env", "rest"}
    assert all(ms > 0 for stage, ms in per_step.items() if stage != "rest") and per_step["rest"] > -0.01
    wall_ms = 1e3 * 5 * model.n_tasks / split["env_steps_per_s"]
    assert abs(sum(per_step.values()) - wall_ms / 5) < 0.05 * wall_ms / 5


def test_the_profile_reads_host_ops_and_no_device_on_the_cpu():
    report = profile_gpu.profile_learn(warm_model(), "cpu", vector_steps=3, rows=4)
    assert report["device_busy_share"] == 0 and report["top_by_device_us_per_vector_step"] == {}
    assert len(report["top_by_host_us_per_vector_step"]) == 4
    assert all(us > 0 for us in report["top_by_host_us_per_vector_step"].values())
