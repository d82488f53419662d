"""A virtual environment that holds what the GPU machine holds and nothing else, for the device check's dry run.

The GPU machine has no package registry: the check can import its image's packages (``device_packages.txt``), the
wheels it carries (``gpu_wheels.txt``, downloaded with the package's own wheel by ``gpu_wheels.sh``) and nothing
else. This builds, from nothing, a venv of the carried wheels (without their dependencies, as the machine installs
them) and of the image's packages that they and the package require (with the CPU torch standing in for the
machine's CUDA build). It refuses to go on when a carried wheel requires a package that is neither on the machine
nor carried, and removes what the install pulled in that the machine lacks (a newer release's new requirement, say).
The package's own requirements that the machine lacks (rl-zoo3, optuna, ...) are left out: the check must not
import them, and in this venv it cannot. Prints the venv's python last.

    python scripts/gpu/device_venv.py /tmp/sb3_mtte_device_venv [--python python3.11] [--torch torch==2.13.0]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

HERE = Path(__file__).resolve().parent
TOOLS = {"pip", "setuptools", "wheel"}
"""What a new venv holds besides the packages."""


def package_names(path: Path) -> set[str]:
    """Canonical names of a package list (one requirement a line; ``#`` comments)."""
    lines = [line.strip() for line in path.read_text().splitlines()]
    return {canonicalize_name(Requirement(line).name) for line in lines if line and not line.startswith("#")}


def wheel_requirements(wheel: Path) -> tuple[str, set[str]]:
    """A wheel's canonical name and those of its requirements (without extras, markers evaluated here)."""
    with zipfile.ZipFile(wheel) as archive:
        metadata = next(name for name in archive.namelist() if name.endswith(".dist-info/METADATA"))
        lines = archive.read(metadata).decode().splitlines()
    name = canonicalize_name(next(line.split(":", 1)[1].strip() for line in lines if line.startswith("Name:")))
    requirements = [Requirement(line.split(":", 1)[1]) for line in lines if line.startswith("Requires-Dist:")]
    return name, {
        canonicalize_name(r.name) for r in requirements if r.marker is None or r.marker.evaluate({"extra": ""})
    }


def needed_from_the_image(wheels: list[Path], on_device: set[str], carried: set[str]) -> list[str]:
    """The image's packages that the carried wheels require, and pytest (the check's tests).

    :raises SystemExit: when a carried wheel (the package's own excepted) requires what the machine lacks.
    """
    needed, missing, left_out = {"pytest"}, [], set()
    for wheel in wheels:
        name, requirements = wheel_requirements(wheel)
        for requirement in sorted(requirements - carried):
            if requirement in on_device:
                needed.add(requirement)
            elif name == "sb3-mtte":
                left_out.add(requirement)
            else:
                missing.append(f"{requirement} (required by {name})")
    if missing:
        sys.exit(f"not on the GPU machine and not carried: {', '.join(missing)}; add them to gpu_wheels.txt")
    print(f"left out, as the GPU machine has none of them: {', '.join(sorted(left_out))}", file=sys.stderr)
    return sorted(needed)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("venv", type=Path, help="the venv's folder (made anew)")
    parser.add_argument("--python", default="python3.11", help="the interpreter standing in for the machine's")
    parser.add_argument("--torch", default="torch==2.13.0", help="the torch standing in for the machine's")
    args = parser.parse_args(argv)
    version = subprocess.run(
        [args.python, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"], check=True, capture_output=True,
        text=True,
    ).stdout.strip()  # fmt: skip
    wheel_dir = args.venv.with_name(args.venv.name + "-wheels")
    for folder in (args.venv, wheel_dir):
        shutil.rmtree(folder, ignore_errors=True)
    subprocess.run(["bash", str(HERE / "gpu_wheels.sh"), version, str(wheel_dir)], check=True, stdout=sys.stderr)
    on_device, carried = package_names(HERE / "device_packages.txt"), package_names(HERE / "gpu_wheels.txt")
    wheels = sorted(wheel_dir.glob("*.whl"))
    needed = needed_from_the_image(wheels, on_device, carried | {"sb3-mtte"})
    subprocess.run([args.python, "-m", "venv", str(args.venv)], check=True)
    python = str(args.venv / "bin" / "python")
    pip(python, "install", args.torch, *needed)
    pip(python, "install", "--no-deps", *map(str, wheels))  # pip's complaint of the missing requirements is expected
    listed = pip(python, "list", "--format=json")
    installed = {canonicalize_name(package["name"]) for package in json.loads(listed)}
    extra = sorted(installed - on_device - carried - {"sb3-mtte"} - TOOLS)
    if extra:
        print(f"removed, as the GPU machine lacks them: {', '.join(extra)}", file=sys.stderr)
        pip(python, "uninstall", "--yes", *extra)
    print(python)


def pip(python: str, *args: str) -> str:
    """Run pip in the venv; its output only when it fails (then exit)."""
    result = subprocess.run([python, "-m", "pip", *args, "--disable-pip-version-check"], capture_output=True, text=True)
    if result.returncode:
        sys.exit(f"pip {args[0]} failed:\n{result.stdout[-3000:]}{result.stderr[-3000:]}")
    return result.stdout


if __name__ == "__main__":
    main()
