"""A command that lacks an extra stops with one line naming the install, and the table agrees with setup.cfg."""

from __future__ import annotations

import configparser
import subprocess
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from sb3_mtte.experiments import extras
from sb3_mtte.experiments.cli import COMMAND_TARGETS
from sb3_mtte.experiments.extras import COMMAND_EXTRAS, EXTRA_MODULES, require_extra

ROOT = Path(__file__).resolve().parent.parent


def hide(monkeypatch: pytest.MonkeyPatch, *modules: str) -> None:
    """Make ``find_spec`` find none of ``modules``, as on an install without them."""
    installed = extras.importlib.util.find_spec
    monkeypatch.setattr(extras.importlib.util, "find_spec", lambda name: None if name in modules else installed(name))


def exit_line(command: str, prog: str | None = None) -> str:
    with pytest.raises(SystemExit) as stop:
        require_extra(command, prog)
    return str(stop.value.code)


def test_a_missing_module_names_its_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    hide(monkeypatch, "matplotlib")
    assert exit_line("plot") == 'sb3-mtte plot needs matplotlib: pip install "sb3-mtte[plots]"'
    assert exit_line("plot", "python -m sb3_mtte plot").startswith("python -m sb3_mtte plot needs matplotlib: ")
    require_extra("train")  # [zoo] does not need matplotlib
    require_extra("evaluate")


def test_modules_missing_from_two_extras_name_both_in_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    hide(monkeypatch, "rl_zoo3", "yaml", "moviepy")
    line = exit_line("record_video")
    assert line == 'sb3-mtte record_video needs rl-zoo3, pyyaml, moviepy: pip install "sb3-mtte[zoo,video]"'
    assert "\n" not in line


def test_ray_is_named_once_by_its_install(monkeypatch: pytest.MonkeyPatch) -> None:
    hide(monkeypatch, "ray", "pyarrow")
    assert exit_line("sweep") == 'sb3-mtte sweep needs ray[tune]: pip install "sb3-mtte[ray]"'


def test_nothing_missing_lets_every_command_through() -> None:
    for command in COMMAND_EXTRAS:
        require_extra(command)


def test_an_unlisted_command_is_an_error() -> None:
    with pytest.raises(ValueError, match="COMMAND_EXTRAS"):
        require_extra("trian")


def test_a_module_hidden_from_python_itself_is_found_missing_without_importing_anything() -> None:
    """In a fresh interpreter, ``sys.modules[name] = None`` hides a module; the check imports none of the others."""
    code = (
        "import sys\n"
        "sys.modules['rliable'] = None\n"
        "from sb3_mtte.experiments.extras import EXTRA_MODULES, require_extra\n"
        "try:\n"
        "    require_extra('compare')\n"
        "except SystemExit as stop:\n"
        "    print(stop.code)\n"
        "print(sorted(m for extra in EXTRA_MODULES.values() for m in extra if m in sys.modules and sys.modules[m]))\n"
        "print('torch' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.splitlines() == ['sb3-mtte compare needs rliable: pip install "sb3-mtte[plots]"', "[]", "False"]


def test_every_command_of_the_dispatcher_is_in_the_table() -> None:
    assert set(COMMAND_TARGETS) == set(COMMAND_EXTRAS)


def extras_of_setup_cfg() -> dict[str, set[str]]:
    config = configparser.ConfigParser(inline_comment_prefixes=("#",))
    config.read(ROOT / "setup.cfg")
    section = config["options.extras_require"]
    return {
        extra: {canonicalize_name(Requirement(line).name) for line in section[extra].splitlines() if line.strip()}
        for extra in section
    }


def test_each_extra_of_the_table_is_declared_with_its_distributions() -> None:
    declared = extras_of_setup_cfg()
    for extra, modules in EXTRA_MODULES.items():
        names = {canonicalize_name(Requirement(dist).name) for dist in modules.values()}
        assert names <= declared[extra], f"setup.cfg's [{extra}] lacks {names - declared[extra]}"
    assert set(EXTRA_MODULES) | {"docs", "tests", "all"} == set(declared)
