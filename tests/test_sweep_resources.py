"""What ``sb3-mtte sweep`` reserves for each trial on Ray, and the cores each trial is pinned to."""

from __future__ import annotations

import os

import pytest

from sb3_mtte.experiments.zoo import sweep
from sb3_mtte.experiments.zoo.sweep import TRIALS_PER_GPU, trial_resources
from sb3_mtte.experiments.zoo.sweep_trial import pin_to_cores, trial_cores


def test_a_cpu_only_machine_requests_no_gpu():
    assert trial_resources(2, None, cuda_count=0) == {"cpu": 2.0}
    assert trial_resources(1, 0, cuda_count=2) == {"cpu": 1.0}


def test_a_cuda_machine_shares_each_gpu_between_trials_by_default():
    assert trial_resources(4, None, cuda_count=1) == {"cpu": 4.0, "gpu": 1 / TRIALS_PER_GPU}
    assert trial_resources(4, 0.5, cuda_count=1) == {"cpu": 4.0, "gpu": 0.5}


def test_the_default_asks_torch_for_the_cuda_count(monkeypatch):
    monkeypatch.setattr(sweep, "cuda_device_count", lambda: 3)
    assert trial_resources(1, None, sweep.cuda_device_count())["gpu"] == 1 / TRIALS_PER_GPU


@pytest.mark.parametrize(
    ("index", "cpus", "cores", "expected"),
    [
        (0, 2, range(8), [0, 1]),
        (1, 2, range(8), [2, 3]),
        (3, 2, range(8), [6, 7]),
        (4, 2, range(8), [0, 1]),  # past the last slot: the first again
        (1, 1.5, [4, 6, 5], [5]),  # whole cores, in order
        (0, 4, range(2), [0, 1]),  # fewer cores than one trial asks for: all of them
    ],
)
def test_trials_split_the_cores_evenly_by_index(index, cpus, cores, expected):
    assert trial_cores(index, cpus, cores) == expected


def test_concurrent_trials_get_disjoint_cores():
    slots = [set(trial_cores(i, 2, range(16))) for i in range(8)]
    assert set().union(*slots) == set(range(16)) and sum(map(len, slots)) == 16


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="pinning needs os.sched_setaffinity")
def test_a_trial_pins_its_process(monkeypatch):
    pinned = {}
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    monkeypatch.setattr(os, "sched_setaffinity", lambda pid, cores: pinned.setdefault(pid, list(cores)))
    assert pin_to_cores(1, 2) == [2, 3] and pinned == {0: [2, 3]}


def test_sweep_refuses_a_negative_gpu_share(tmp_path, capsys):
    with pytest.raises(SystemExit):
        sweep.main(["--algos", "mtsac_mt", "--envs", "toy-conflict", "--out", str(tmp_path), "--gpus-per-trial", "-1"])
    assert "--gpus-per-trial -1.0: give 0 or more" in capsys.readouterr().err.splitlines()[-1]
    assert not list(tmp_path.iterdir())
