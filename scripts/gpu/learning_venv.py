"""Add to the device check's venv (``device_venv.py``) what the learning runs import: the wheels they carry
(``learning_wheels.txt``) without their dependencies, as the GPU machine installs them, and the image's packages
that those wheels and the package's ``zoo`` and ``plots`` extras require. What the install pulls in that the machine
lacks is removed again, so that an import the machine cannot satisfy fails in this venv too.

    python scripts/gpu/learning_venv.py VENV WHEEL_DIR   # WHEEL_DIR: the carried wheels, the package's own among them
"""

from __future__ import annotations

import argparse
import json
import sys
import zipfile
from pathlib import Path

from device_venv import TOOLS, package_names, pip, wheel_requirements
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

HERE = Path(__file__).resolve().parent
EXTRAS = ("zoo", "plots")
"""The package's extras that ``train`` and ``record`` need."""
SEEN_ON_DEVICE = {"huggingface-hub": "huggingface-hub==1.33.0"}
"""Versions read on the GPU machine (``pip list`` there) where the newest release here differs in what it imports:
huggingface_hub 2 imports httpcore2, which the machine lacks."""


def extra_requirements(wheel: Path, extras: tuple[str, ...] = EXTRAS) -> set[str]:
    """Canonical names of what a wheel requires for ``extras`` alone (markers evaluated here)."""
    with zipfile.ZipFile(wheel) as archive:
        metadata = next(name for name in archive.namelist() if name.endswith(".dist-info/METADATA"))
        lines = archive.read(metadata).decode().splitlines()
    requirements = [Requirement(line.split(":", 1)[1]) for line in lines if line.startswith("Requires-Dist:")]
    return {
        canonicalize_name(r.name)
        for r in requirements
        if r.marker is not None and any(r.marker.evaluate({"extra": extra}) for extra in extras)
    }


def needed(wheels: list[Path], on_device: set[str], carried: set[str]) -> tuple[list[str], list[str]]:
    """The image's packages to install (the carried wheels' requirements and the extras', on the machine), and the
    requirements that are neither on the machine nor carried (left out: an import of one fails)."""
    wanted: set[str] = set()
    for wheel in wheels:
        name, requirements = wheel_requirements(wheel)
        wanted |= requirements | (extra_requirements(wheel) if name == "sb3-mtte" else set())
    wanted -= carried
    return sorted(wanted & on_device), sorted(wanted - on_device)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("venv", type=Path, help="the venv that device_venv.py made")
    parser.add_argument("wheel_dir", type=Path, help="the carried wheels (gpu_wheels.txt's, the package's, ours)")
    args = parser.parse_args(argv)
    python = str(args.venv / "bin" / "python")
    on_device = package_names(HERE / "device_packages.txt")
    ours = package_names(HERE / "learning_wheels.txt")
    carried = package_names(HERE / "gpu_wheels.txt") | ours | {"sb3-mtte"}
    wheels = sorted(args.wheel_dir.glob("*.whl"))
    found = {wheel_requirements(wheel)[0] for wheel in wheels}
    if ours - found:
        sys.exit(f"{args.wheel_dir} lacks the wheels of {', '.join(sorted(ours - found))}: run learning_runs.sh wheels")
    install, left_out = needed(wheels, on_device, carried)
    print(f"left out, as the GPU machine has none of them: {', '.join(left_out)}", file=sys.stderr)
    pip(python, "install", *(SEEN_ON_DEVICE.get(name, name) for name in install))
    pip(python, "install", "--no-deps", *(str(w) for w in wheels if wheel_requirements(w)[0] in ours))
    listed = json.loads(pip(python, "list", "--format=json"))
    extra = sorted({canonicalize_name(p["name"]) for p in listed} - on_device - carried - TOOLS)
    if extra:
        print(f"removed, as the GPU machine lacks them: {', '.join(extra)}", file=sys.stderr)
        pip(python, "uninstall", "--yes", *extra)
    print(python)


if __name__ == "__main__":
    main()
