"""tune_process() sets the OpenMP spin count before torch loads, never over a user's choice, and warns when too late."""

from __future__ import annotations

import os
import subprocess
import sys

from sb3_mtte.process import MALLOC_OPT_OUT, MALLOC_VARIABLES, SPIN_COUNT, SPIN_VARIABLES

PROBE = """
import os, warnings
{before}
import sb3_mtte
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    tuning = sb3_mtte.tune_process()
from sb3_mtte import MTSAC, make_mt_env
import torch
torch.set_num_threads(2)
env = make_mt_env("toy-conflict", seed=0)
model = MTSAC("MlpPolicy", env, learning_starts=8, policy_kwargs=dict(net_arch=[8]), device="cpu")
model.learn(16)
caught = [w for w in caught if "GOMP_SPINCOUNT" in str(w.message)]
print(os.environ.get("GOMP_SPINCOUNT"), os.environ.get("OMP_WAIT_POLICY"), tuning.spin_count, len(caught))
"""


def run_probe(before: str = "", **variables: str) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in SPIN_VARIABLES}
    env.update(variables)
    code = PROBE.format(before=before)
    return subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.split()


def test_tune_process_sets_the_spin_count_before_torch_loads() -> None:
    assert run_probe() == [str(SPIN_COUNT), "None", "True", "0"]


def test_a_users_choice_is_kept() -> None:
    assert run_probe(OMP_WAIT_POLICY="PASSIVE") == ["None", "PASSIVE", "False", "0"]
    assert run_probe(GOMP_SPINCOUNT="300000") == ["300000", "None", "False", "0"]


def test_torch_imported_first_is_left_alone_and_warned_about() -> None:
    assert run_probe(before="import torch") == ["None", "None", "False", "1"]


COMMAND = """
import os, runpy, sys
sys.argv = ["sb3-mtte", "evaluate", "--help"]
try:
    runpy.run_module("sb3_mtte", run_name="__main__", alter_sys=True)
except SystemExit:
    pass
from sb3_mtte.process import applied_settings
print(os.environ.get("GOMP_SPINCOUNT"), *applied_settings())
"""


def test_the_commands_apply_both_settings_before_torch_loads() -> None:
    """``python -m sb3_mtte <command>`` (and the console script, which runs the same function) tunes the process."""
    env = {k: v for k, v in os.environ.items() if k not in (*SPIN_VARIABLES, *MALLOC_VARIABLES, MALLOC_OPT_OUT)}
    out = subprocess.run([sys.executable, "-c", COMMAND], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.splitlines()[-1].split() == [str(SPIN_COUNT), "True", "True"]
