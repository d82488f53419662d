"""Every module that the algorithms and each command import comes from a declared dependency of sb3-mtte: the core
install for the algorithms and ``sb3-mtte evaluate``, the extras a command names for the others. Every module that the
device check imports comes from the GPU machine's packages or the wheels the check carries."""

from __future__ import annotations

import configparser
import os
import re
import subprocess
import sys
from importlib.metadata import PackageNotFoundError, distribution, packages_distributions
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from script_loader import load_script

from sb3_mtte.experiments.cli import COMMAND_TARGETS
from sb3_mtte.experiments.extras import COMMAND_EXTRAS

ROOT = Path(__file__).resolve().parent.parent
GPU_SCRIPTS = ROOT / "scripts" / "gpu"
package_names = load_script("scripts/gpu/device_venv.py").package_names

CORE_MODULES = ["sb3_mtte.mtsac", "sb3_mtte.mtsacte", "sb3_mtte.envs", "sb3_mtte.evaluation", "tqdm", "rich"]
"""What the algorithms import, and what ``progress_bar=True`` imports (SB3's progress bar)."""
SNIPPET = """
import sb3_mtte
from sb3_mtte import MTSACTE, evaluate_success, make_mt_env
env = make_mt_env("toy-conflict", seed=0)
model = MTSACTE("MlpPolicy", env, learning_starts=64, policy_kwargs=dict(net_arch=[16]), device="cpu", seed=0)
model.learn(160, progress_bar=True)
model.save("model.zip")
print(evaluate_success(MTSACTE.load("model.zip", device="cpu"), make_mt_env("toy-conflict", seed=1), 1))
"""
"""The README's snippet, small: training with the progress bar, save and load, the success evaluation."""
ZOO_MODULES = ["rl_zoo3.train", "rl_zoo3.enjoy", "rl_zoo3.record_video", "rl_zoo3.exp_manager"]
EXTRA_MODULES = [*ZOO_MODULES, "moviepy.video.io.ffmpeg_writer", "matplotlib.pyplot"]
EXTRA_MODULES += ["tensorboard.backend.event_processing.event_accumulator"]
"""What the commands reach in the libraries of their extras (the ``[ray]`` extra of ``sweep`` is imported only when a
sweep runs)."""


def declared_requirements(extras: frozenset[str] = frozenset()) -> list[str]:
    """``install_requires`` and the requirements of ``extras`` in this checkout's setup.cfg (the installed metadata may
    predate it)."""
    config = configparser.ConfigParser(inline_comment_prefixes=("#",))
    config.read(ROOT / "setup.cfg")
    sections = [config["options"]["install_requires"], *(config["options.extras_require"][e] for e in sorted(extras))]
    return [line.strip() for section in sections for line in section.splitlines() if line.strip()]


def requirements_of(name: str, extras: frozenset[str]) -> list[Requirement]:
    """The requirements that installing ``name[extras]`` brings (for sb3-mtte, from this tree's setup.cfg)."""
    try:
        lines = declared_requirements(extras) if name == "sb3-mtte" else distribution(name).requires or []
    except PackageNotFoundError:
        return []
    requirements = [Requirement(line) for line in lines]
    wanted = [{"extra": extra} for extra in ("", *extras)]
    return [r for r in requirements if r.marker is None or any(r.marker.evaluate(e) for e in wanted)]


def requirement_closure(name: str, extras: tuple[str, ...] = ()) -> set[str]:
    """Canonical names of ``name`` and everything it pulls in with its ``extras``, recursively (an extra naming
    another package's extras, ``ray[tune]`` or sb3-mtte's own, brings theirs)."""
    seen: set[tuple[str, frozenset[str]]] = set()
    stack = [(canonicalize_name(name), frozenset(extras))]
    while stack:
        current = stack.pop()
        if current in seen:
            continue
        seen.add(current)
        stack += [(canonicalize_name(r.name), frozenset(r.extras)) for r in requirements_of(*current)]
    return {name for name, _ in seen}


def modules_outside(allowed: set[str]) -> list[str]:
    """Top-level modules installed here only by distributions whose canonical names are not in ``allowed``."""
    return sorted(
        module
        for module, owners in packages_distributions().items()
        if module not in sys.stdlib_module_names and not {canonicalize_name(d) for d in owners} & allowed
    )


def undeclared_modules(extras: tuple[str, ...] = ()) -> list[str]:
    """Top-level modules installed here only by distributions outside what ``sb3-mtte[extras]`` pulls in."""
    return modules_outside(requirement_closure("sb3-mtte", extras))


def command_module(command: str) -> str:
    """The module that runs ``command`` (the dispatcher imports it once the command's extras are found)."""
    return COMMAND_TARGETS[command].split(":")[0]


def import_as_on_a_plain_install(
    modules: list[str], blocked: list[str], then: str = "", cwd: Path | None = None, paths: tuple[Path, ...] = ()
) -> subprocess.CompletedProcess:
    """Import ``modules`` in a fresh interpreter where the ``blocked`` top-level modules cannot be found, as after
    ``pip install -e .`` alone (optional imports guarded by try/except still pass, and a probe with
    ``importlib.util.find_spec``, as torch makes for optional modules, finds them absent), then run the code
    ``then``. ``paths`` go on the module search path after the checkout."""
    code = (
        "import importlib, importlib.util, sys\n"
        f"BLOCKED = set({blocked!r})\n"
        "class Blocker:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in BLOCKED:\n"
        "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
        "sys.meta_path.insert(0, Blocker())\n"
        "installed_spec = importlib.util.find_spec\n"
        "def find_spec(name, package=None):\n"
        "    return None if name.split('.')[0] in BLOCKED else installed_spec(name, package)\n"
        "importlib.util.find_spec = find_spec\n"
        f"for name in {modules!r}: importlib.import_module(name)\n"
        f"{then}\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(map(str, (ROOT, *paths)))}  # this checkout's package
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, cwd=cwd, env=env)


def test_the_algorithms_need_only_the_core_install(tmp_path):
    """The snippet trains with a progress bar, saves, loads and evaluates with the core install alone."""
    result = import_as_on_a_plain_install(CORE_MODULES, undeclared_modules(), then=SNIPPET, cwd=tmp_path)
    assert result.returncode == 0, f"the algorithms need more than the core install:\n{result.stderr[-2000:]}"
    assert "SuccessResult" in result.stdout


@pytest.mark.parametrize("extras", sorted(set(COMMAND_EXTRAS.values())), ids=lambda e: ",".join(e) or "core")
def test_each_command_needs_only_the_core_and_the_extras_it_names(extras):
    commands = [command for command, needed in COMMAND_EXTRAS.items() if needed == extras]
    result = import_as_on_a_plain_install([command_module(c) for c in commands], undeclared_modules(extras))
    assert result.returncode == 0, f"{commands} need more than the extras {extras}:\n{result.stderr[-2000:]}"


def test_command_imports_need_only_declared_dependencies():
    result = import_as_on_a_plain_install(EXTRA_MODULES, undeclared_modules(("zoo", "plots", "video")))
    assert result.returncode == 0, f"a command needs an undeclared dependency:\n{result.stderr[-2000:]}"


def test_optuna_search_needs_only_declared_dependencies(tmp_path):
    """``-optimize`` (rl-zoo's optuna search, whose report is a pandas table) runs with the ``[zoo]`` extra."""
    argv = ["train", "--algo", "mtsac_mt", "--env", "toy-conflict", "-f", "logs", "-optimize", "--n-trials", "1"]
    argv += ["-n", "200", "--n-evaluations", "1", "--eval-episodes", "1", "--no-optim-plots", "--verbose", "0"]
    argv += ["--sampler", "random", "--pruner", "none", "--no-progress", "--seed", "3"]
    run = f"from sb3_mtte.experiments.cli import main\nmain({argv!r})"
    result = import_as_on_a_plain_install(["sb3_mtte"], undeclared_modules(("zoo",)), then=run, cwd=tmp_path)
    assert result.returncode == 0, f"-optimize needs an undeclared dependency:\n{result.stderr[-2000:]}"
    assert list((tmp_path / "logs" / "mtsac_mt").glob("report_*.csv"))


def test_a_missing_dependency_is_caught():
    """The check can fail: with stable-baselines3 treated as undeclared, importing the algorithms breaks; with the
    core install alone, ``train`` breaks on rl-zoo3."""
    result = import_as_on_a_plain_install(["sb3_mtte.mtsac"], ["stable_baselines3"])
    assert result.returncode != 0 and "stable_baselines3" in result.stderr
    result = import_as_on_a_plain_install([command_module("train")], undeclared_modules())
    assert result.returncode != 0 and "rl_zoo3" in result.stderr
    core = requirement_closure("sb3-mtte")
    assert {"pytest", "rl-zoo3", "optuna", "moviepy", "rliable", "matplotlib", "ray"}.isdisjoint(core)
    assert {"rl-zoo3", "rliable", "moviepy", "ray", "pyarrow"} <= requirement_closure("sb3-mtte", ("all",))


# ------------------------------------------------------------------------------------------------ the device check
def device_check_modules() -> list[str]:
    """What ``scripts/gpu/gpu_check.sh`` imports: ``bench_gpu`` and ``profile_gpu`` (run from benchmarks/), and
    conftest and the test modules it names."""
    script = (GPU_SCRIPTS / "gpu_check.sh").read_text()
    tests = sorted(set(re.findall(r"tests/(test_\w+)\.py", script)))
    assert tests, "gpu_check.sh names no test file"
    return ["bench_gpu", "profile_gpu", "conftest", *tests]


def test_the_device_check_imports_only_what_the_gpu_machine_has():
    """``bench_gpu.py``, ``profile_gpu.py`` and the tests of the device check import nothing beyond the GPU machine's
    packages (``scripts/gpu/device_packages.txt``), the wheels the check carries (``scripts/gpu/gpu_wheels.txt``) and
    the package: rl-zoo3, sb3-contrib, huggingface_sb3, optuna, ray, rliable are not there."""
    allowed = package_names(GPU_SCRIPTS / "device_packages.txt") | {"sb3-mtte"}
    blocked = modules_outside(allowed | package_names(GPU_SCRIPTS / "gpu_wheels.txt"))
    assert {"rl_zoo3", "sb3_contrib", "huggingface_sb3", "optuna", "rliable"} <= set(blocked)
    paths = (ROOT / "benchmarks", ROOT / "tests")
    result = import_as_on_a_plain_install(device_check_modules(), blocked, paths=paths)
    assert result.returncode == 0, f"the device check needs a package the GPU machine lacks:\n{result.stderr[-2000:]}"
