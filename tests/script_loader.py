"""The repository's scripts (``benchmarks/``, ``scripts/``), loaded by file path for their tests.

The scripts are not part of the package, and the tests leave the module search path as it is: each script is loaded
from its file, under the name Python gives it when it runs the script.
"""

from __future__ import annotations

import ast
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load_script(path: str) -> ModuleType:
    """The script at ``path`` (from the repository root), loaded once as the module its file name says.

    A script imports the scripts beside it by their names, as Python finds them when it runs the script. Those are
    loaded first, the same way.

    :raises ImportError: when another module of that name is loaded already.
    """
    file = (ROOT / path).resolve()
    name = file.stem
    loaded = sys.modules.get(name)
    if loaded is not None:
        if Path(getattr(loaded, "__file__", None) or "").resolve() != file:
            raise ImportError(f"cannot load {path} as {name!r}: {loaded!r} holds that name; rename the script")
        return loaded
    for sibling in sibling_scripts(file):
        load_script(str(sibling.relative_to(ROOT)))
    spec = importlib.util.spec_from_file_location(name, file)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


def sibling_scripts(file: Path) -> list[Path]:
    """The scripts in ``file``'s folder that it imports, at its top or inside a function."""
    names = set()
    for node in ast.walk(ast.parse(file.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name.partition(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.partition(".")[0])
    return sorted(file.with_name(f"{name}.py") for name in names if file.with_name(f"{name}.py").is_file())
