"""rl-zoo3 through its public seams: every private reach is where the adapter expects it, and nowhere else.

A release of rl-zoo3 that moves a private name fails here, naming it, instead of breaking a command silently.
"""

from __future__ import annotations

import argparse
import configparser
import re
from pathlib import Path
from types import SimpleNamespace

import pytest
import rl_zoo3
from rl_zoo3.exp_manager import ExperimentManager

from sb3_mtte.experiments.zoo import adapter
from sb3_mtte.experiments.zoo.manager import MultiTaskExperimentManager

ROOT = Path(__file__).resolve().parents[1]


def test_every_private_reach_is_in_the_installed_rl_zoo3():
    missing = adapter.missing_attributes(adapter.PRIVATE_ATTRIBUTES)
    assert not missing, (
        f"rl-zoo3 {rl_zoo3.__version__} moved {', '.join(missing)}: sb3_mtte.experiments.zoo.adapter was written for "
        f"rl-zoo3 {', '.join(adapter.TESTED_RL_ZOO3)}"
    )


def test_every_public_seam_is_in_the_installed_rl_zoo3():
    missing = adapter.missing_attributes(adapter.PUBLIC_SEAMS)
    assert not missing, f"rl-zoo3 {rl_zoo3.__version__} has no {', '.join(missing)}"


def test_rl_zoo3_still_uses_what_the_swaps_replace():
    missing = adapter.missing_uses()
    assert not missing, f"rl-zoo3 {rl_zoo3.__version__} no longer uses {'; '.join(missing)}"


def test_the_private_instance_attributes_are_set_by_rl_zoo3(tmp_path):
    manager = ExperimentManager(argparse.Namespace(), "ppo", "CartPole-v1", str(tmp_path))
    missing = [name for name in adapter.PRIVATE_INSTANCE_ATTRIBUTES if not hasattr(manager, name)]
    assert not missing, f"rl-zoo3 {rl_zoo3.__version__}'s ExperimentManager no longer sets {', '.join(missing)}"


@pytest.mark.parametrize("manager_class", [adapter.ZooExperimentManager, MultiTaskExperimentManager])
def test_the_managers_override_public_methods_only(manager_class):
    """A method of the package's managers that rl-zoo also has is one of the listed public overrides, or the
    adapter's own private override: a new private method of rl-zoo's of the same name would be shadowed silently."""
    allowed = {*adapter.PUBLIC_OVERRIDES, *(name for _, name in adapter.PRIVATE_ATTRIBUTES)}
    own = {name for name in vars(manager_class) if not (name.startswith("__") and name != "__init__")}
    shadowed = sorted(name for name in own - allowed if hasattr(ExperimentManager, name))
    assert not shadowed, f"{manager_class.__name__} shadows rl-zoo3's {', '.join(shadowed)}"
    if manager_class is MultiTaskExperimentManager:
        assert "_save_config" not in vars(manager_class) and "objective" not in vars(manager_class)


def test_the_zoo_extra_pins_the_tested_minor_release():
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    (line,) = [entry for entry in config["options.extras_require"]["zoo"].splitlines() if entry.startswith("rl_zoo3")]
    low, high = re.match(r"rl_zoo3>=(\d+\.\d+),<(\d+\.\d+)", line).groups()
    assert low == adapter.TESTED_RL_ZOO3[0] and high == adapter._next_minor(adapter.TESTED_RL_ZOO3[-1]), line
    installed = ".".join(rl_zoo3.__version__.split(".")[:2])
    assert installed in adapter.TESTED_RL_ZOO3, f"rl-zoo3 {rl_zoo3.__version__} is not a tested release"


def test_a_swap_of_a_moved_attribute_ends_with_one_line_naming_it():
    with pytest.raises(SystemExit) as exit_info, adapter.swapped(SimpleNamespace(), "argparse", None):
        pass
    message = str(exit_info.value)
    assert "argparse" in message and adapter.TESTED_RL_ZOO3[0] in message and "\n" not in message


def test_a_swap_is_undone_after_the_block():
    owner = SimpleNamespace(name="rl-zoo's")
    with adapter.swapped(owner, "name", "ours"):
        assert owner.name == "ours"
    assert owner.name == "rl-zoo's"


def test_the_package_patches_nothing_with_unittest_mock():
    users = [
        str(path.relative_to(ROOT))
        for path in (ROOT / "sb3_mtte").rglob("*.py")
        if re.search(r"^\s*(from unittest import mock|import unittest|from unittest\.mock)", path.read_text(), re.M)
    ]
    assert not users, f"unittest.mock in {', '.join(users)}"
