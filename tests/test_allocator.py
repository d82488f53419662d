"""tune_process() keeps freed tensor memory in the process: an update stops page-faulting its tensors back."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from sb3_mtte import process

TRAINING_STEPS = """
import ctypes, resource, sys
ctypes.CDLL(None).prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE: count 4 KiB faults also where THP is "always"
import sb3_mtte
if sys.argv[1] == "tuned":
    sb3_mtte.tune_process()
import torch as th
th.manual_seed(0)
layers = lambda: [th.nn.Linear(49, 400), th.nn.ReLU(), th.nn.Linear(400, 400), th.nn.ReLU(), th.nn.Linear(400, 1)]
nets = [th.nn.Sequential(*layers()) for _ in range(3)]
optimizer = th.optim.Adam([p for net in nets for p in net.parameters()])
x = th.randn(2560, 49)
def step():
    loss = sum(net(x).square().mean() for net in nets)
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
for _ in range(10):
    step()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    step()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10)
"""


def faults_per_step(mode: str, **variables: str) -> float:
    env = {k: v for k, v in os.environ.items() if k not in (*process.MALLOC_VARIABLES, process.MALLOC_OPT_OUT)}
    env.update(variables)
    out = subprocess.run([sys.executable, "-c", TRAINING_STEPS, mode], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return float(out.stdout)


# glibc's defaults (128 KiB each), pinned: set explicitly, they also turn off glibc's dynamic threshold, which raises
# the mmap threshold to the size of a freed mapped block and so avoids the faults in some runs but not in others.
GLIBC_STATIC_DEFAULTS = {"MALLOC_MMAP_THRESHOLD_": "131072", "MALLOC_TRIM_THRESHOLD_": "131072"}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc tunables")
def test_tune_process_removes_most_page_faults_of_a_training_step() -> None:
    plain = faults_per_step("imported", **GLIBC_STATIC_DEFAULTS)
    tuned = faults_per_step("tuned")
    users_choice = faults_per_step("tuned", **GLIBC_STATIC_DEFAULTS)  # tune_process leaves the user's values alone
    assert plain > 500  # glibc's static defaults map and zero-fill freed blocks again at every step
    assert tuned < 0.25 * plain
    assert users_choice > 0.5 * plain


@pytest.mark.parametrize("variable, value", [("MALLOC_TRIM_THRESHOLD_", "131072"), (process.MALLOC_OPT_OUT, "default")])
def test_a_users_choice_is_kept(monkeypatch: pytest.MonkeyPatch, variable: str, value: str) -> None:
    monkeypatch.setenv(variable, value)
    assert process.keep_freed_memory() is False
    assert process.tune_process(spin_count=False) == (False, False)
