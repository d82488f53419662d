"""``benchmarks/profile_gpu.py``: the stages of a vector step are timed where ``learn()`` calls them, and with the
rest they make up the wall time."""

from __future__ import annotations

from script_loader import load_script

from sb3_mtte import MTSAC

bench_updates = load_script("benchmarks/bench_updates.py")
profile_gpu = load_script("benchmarks/profile_gpu.py")


def warm_model(n_tasks: int = 3) -> MTSAC:
    env = bench_updates.synthetic_env(n_tasks)
    model = bench_updates.quiet(MTSAC("MlpPolicy", env, learning_starts=4 * n_tasks, buffer_size=200, batch_size=8,
                                      policy_kwargs=dict(net_arch=[8]), device="cpu", seed=0))  # fmt: skip
    model.learn(model.learning_starts + 2 * n_tasks)
    return model


def test_every_stage_is_timed_once_per_vector_step_and_the_wrappers_go_on_exit(monkeypatch):
    model = warm_model()
    calls = {stage: 0 for stage in (*profile_gpu.STAGES, "env")}
    for stage, name in (*profile_gpu.STAGES.items(), ("env", "step")):
        owner = model.env if stage == "env" else model
        original = getattr(owner, name)

        def counted(*args, stage=stage, original=original, **kwargs):
            calls[stage] += 1
            return original(*args, **kwargs)

        monkeypatch.setattr(owner, name, counted)
    counters = {name: vars(model)[name] for name in profile_gpu.STAGES.values()}
    with profile_gpu.timed_stages(model, "cpu") as seconds:
        model.learn(5 * model.n_tasks, reset_num_timesteps=False)
    assert calls == {"act": 5, "store": 5, "update": 5, "env": 5}
    assert set(seconds) == {"act", "store", "update", "env"} and all(s > 0 for s in seconds.values())
    assert {name: vars(model)[name] for name in counters} == counters and vars(model.env)["step"].__name__ == "counted"
    fresh = warm_model()
    with profile_gpu.timed_stages(fresh, "cpu"):
        pass
    assert not {*profile_gpu.STAGES.values()} & set(vars(fresh)) and "step" not in vars(fresh.env)


def test_the_stages_and_the_rest_make_up_the_timed_learn():
    model = warm_model()
    split = profile_gpu.split_vector_step(model, "cpu", vector_steps=5)
    per_step = split["ms_per_vector_step"]
    assert set(per_step) == {"act", "store", "update", "env", "rest"} and per_step["rest"] > -0.01
    wall_ms = 1e3 * model.n_tasks / split["env_steps_per_s"]
    assert abs(sum(per_step.values()) - wall_ms) < 0.02 * wall_ms
    assert split["untimed_env_steps_per_s"] > 0 and model.num_timesteps == model.learning_starts + 12 * model.n_tasks


def test_the_profile_reads_host_ops_and_no_device_on_the_cpu():
    report = profile_gpu.profile_learn(warm_model(), "cpu", vector_steps=3, rows=4)
    assert report["device_busy_share"] == 0 and report["top_by_device_us_per_vector_step"] == {}
    assert report["profiled_env_steps_per_s"] > 0
    assert len(report["top_by_host_us_per_vector_step"]) == 4
    assert all(us > 0 for us in report["top_by_host_us_per_vector_step"].values())
