"""Every module that the README's commands import comes from a declared runtime dependency of sb3-mtte, and every module
that the device check imports from the GPU machine's packages or the wheels the check carries."""

from __future__ import annotations

import configparser
import os
import re
import subprocess
import sys
from importlib.metadata import PackageNotFoundError, distribution, packages_distributions
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from device_venv import package_names  # noqa: E402

# What `python -m sb3_mtte.zoo train|enjoy|record_video`, `sb3_mtte.evaluate`, `sb3_mtte.record`, `sb3_mtte.plot`
# and the `sb3-mtte` command import when they run (the `[ray]` extra of `sweep` is imported only when a sweep runs).
COMMAND_MODULES = [
    "sb3_mtte",
    "sb3_mtte.zoo",
    "sb3_mtte.evaluate",
    "sb3_mtte.record",
    "sb3_mtte.plot",
    "sb3_mtte.experiments.cli",
    "rl_zoo3.train",
    "rl_zoo3.enjoy",
    "rl_zoo3.record_video",
    "rl_zoo3.exp_manager",
    "moviepy.video.io.ffmpeg_writer",
    "tqdm",
    "matplotlib.pyplot",
    "tensorboard.backend.event_processing.event_accumulator",
]


def declared_requirements() -> list[str]:
    """``install_requires`` of this checkout's setup.cfg (the installed metadata may predate it)."""
    config = configparser.ConfigParser(inline_comment_prefixes=("#",))
    config.read(ROOT / "setup.cfg")
    return [line.strip() for line in config["options"]["install_requires"].splitlines() if line.strip()]


def requirement_closure(name: str) -> set[str]:
    """Canonical names of ``name`` and everything its base (no-extra) requirements pull in, recursively (for
    sb3-mtte, from this tree's setup.cfg)."""
    seen: set[str] = set()
    stack = [name]
    while stack:
        current = canonicalize_name(stack.pop())
        if current in seen:
            continue
        seen.add(current)
        try:
            requirements = declared_requirements() if current == "sb3-mtte" else distribution(current).requires or []
        except PackageNotFoundError:
            continue
        for line in requirements:
            requirement = Requirement(line)
            if requirement.marker is None or requirement.marker.evaluate({"extra": ""}):
                stack.append(requirement.name)
    return seen


def modules_outside(allowed: set[str]) -> list[str]:
    """Top-level modules installed here only by distributions whose canonical names are not in ``allowed``."""
    return sorted(
        module
        for module, owners in packages_distributions().items()
        if module not in sys.stdlib_module_names and not {canonicalize_name(d) for d in owners} & allowed
    )


def undeclared_modules() -> list[str]:
    """Top-level modules installed here only by distributions outside sb3-mtte's requirement closure."""
    return modules_outside(requirement_closure("sb3-mtte"))


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


def test_command_imports_need_only_declared_dependencies():
    result = import_as_on_a_plain_install(COMMAND_MODULES, undeclared_modules())
    assert result.returncode == 0, f"a command needs an undeclared dependency:\n{result.stderr[-2000:]}"


def test_optuna_search_needs_only_declared_dependencies(tmp_path):
    """``-optimize`` (rl-zoo's optuna search, whose report is a pandas table) runs on a plain install."""
    argv = ["train", "--algo", "mtsac_mt", "--env", "toy-conflict", "-f", "logs", "-optimize", "--n-trials", "1"]
    argv += ["-n", "200", "--n-evaluations", "1", "--eval-episodes", "1", "--no-optim-plots", "--verbose", "0"]
    argv += ["--sampler", "random", "--pruner", "none", "--no-progress", "--seed", "3"]
    run = f"from sb3_mtte.experiments.cli import main\nmain({argv!r})"
    result = import_as_on_a_plain_install(["sb3_mtte"], undeclared_modules(), then=run, cwd=tmp_path)
    assert result.returncode == 0, f"-optimize needs an undeclared dependency:\n{result.stderr[-2000:]}"
    assert list((tmp_path / "logs" / "mtsac_mt").glob("report_*.csv"))


def test_a_missing_dependency_is_caught():
    """The check can fail: with stable-baselines3 treated as undeclared, importing the package breaks."""
    result = import_as_on_a_plain_install(["sb3_mtte"], ["stable_baselines3"])
    assert result.returncode != 0 and "stable_baselines3" in result.stderr
    assert "pytest" not in requirement_closure("sb3-mtte")


# ------------------------------------------------------------------------------------------------ the device check
def device_check_modules() -> list[str]:
    """What ``benchmarks/gpu_check.sh`` imports: ``bench_gpu`` and ``profile_gpu`` (run from benchmarks/), and
    conftest and the test modules it names."""
    script = (ROOT / "benchmarks" / "gpu_check.sh").read_text()
    tests = sorted(set(re.findall(r"tests/(test_\w+)\.py", script)))
    assert tests, "gpu_check.sh names no test file"
    return ["bench_gpu", "profile_gpu", "conftest", *tests]


def test_the_device_check_imports_only_what_the_gpu_machine_has():
    """``bench_gpu.py``, ``profile_gpu.py`` and the tests of the device check import nothing beyond the GPU machine's
    packages (``benchmarks/device_packages.txt``), the wheels the check carries (``benchmarks/gpu_wheels.txt``) and the
    package: rl-zoo3, sb3-contrib, huggingface_sb3, optuna, ray, rliable are not there."""
    allowed = package_names(ROOT / "benchmarks" / "device_packages.txt") | {"sb3-mtte"}
    blocked = modules_outside(allowed | package_names(ROOT / "benchmarks" / "gpu_wheels.txt"))
    assert {"rl_zoo3", "sb3_contrib", "huggingface_sb3", "optuna", "rliable"} <= set(blocked)
    paths = (ROOT / "benchmarks", ROOT / "tests")
    result = import_as_on_a_plain_install(device_check_modules(), blocked, paths=paths)
    assert result.returncode == 0, f"the device check needs a package the GPU machine lacks:\n{result.stderr[-2000:]}"
