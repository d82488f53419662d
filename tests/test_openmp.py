"""The OpenMP spin default is set on import, before torch loads, and never over a user's choice."""

from __future__ import annotations

import os
import subprocess
import sys

from sb3_mtte.openmp import SPIN_COUNT, USER_VARIABLES

PROBE = """
import os, warnings
{before}
from sb3_mtte import MTSAC, make_mt_env
import torch
torch.set_num_threads(2)
env = make_mt_env("toy-conflict", seed=0)
model = MTSAC("MlpPolicy", env, learning_starts=8, policy_kwargs=dict(net_arch=[8]), device="cpu")
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    model.learn(16)
caught = [w for w in caught if "GOMP_SPINCOUNT" in str(w.message)]
print(os.environ.get("GOMP_SPINCOUNT"), os.environ.get("OMP_WAIT_POLICY"), len(caught))
"""


def run_probe(before: str = "", **variables: str) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in USER_VARIABLES}
    env.update(variables)
    code = PROBE.format(before=before)
    return subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.split()


def test_import_sets_the_spin_default_before_torch_loads() -> None:
    assert run_probe() == [SPIN_COUNT, "None", "0"]


def test_a_users_choice_is_kept() -> None:
    assert run_probe(OMP_WAIT_POLICY="PASSIVE") == ["None", "PASSIVE", "0"]
    assert run_probe(GOMP_SPINCOUNT="300000") == ["300000", "None", "0"]


def test_torch_imported_first_is_left_alone_and_warned_about() -> None:
    assert run_probe(before="import torch") == ["None", "None", "1"]
