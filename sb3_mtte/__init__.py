"""sb3-mtte: multi-task SAC with a task embedding network, and the MTSAC baselines, for Stable-Baselines3.

``import sb3_mtte`` loads neither torch nor the algorithms: each public name is imported on first use. So
:func:`~sb3_mtte.process.tune_process` can still run before torch loads, and the import changes no process state.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from sb3_mtte.process import tune_process
from sb3_mtte.version import __version__

if TYPE_CHECKING:
    from sb3_mtte.common.buffers import MultiTaskReplayBuffer
    from sb3_mtte.evaluation import MultiTaskEvalCallback, SuccessResult, evaluate_success
    from sb3_mtte.envs import OneHotTaskWrapper, get_task_names, make_mt_env
    from sb3_mtte.mtsac import MTSAC
    from sb3_mtte.mtsacte import MTSACTE

_MODULE_OF = {
    "MTSAC": "sb3_mtte.mtsac",
    "MTSACTE": "sb3_mtte.mtsacte",
    "MultiTaskEvalCallback": "sb3_mtte.evaluation",
    "MultiTaskReplayBuffer": "sb3_mtte.common.buffers",
    "OneHotTaskWrapper": "sb3_mtte.envs",
    "SuccessResult": "sb3_mtte.evaluation",
    "evaluate_success": "sb3_mtte.evaluation",
    "get_task_names": "sb3_mtte.envs",
    "make_mt_env": "sb3_mtte.envs",
}
"""Public name -> the module that defines it, imported on first use."""

__all__ = [
    "MTSAC",
    "MTSACTE",
    "MultiTaskEvalCallback",
    "MultiTaskReplayBuffer",
    "OneHotTaskWrapper",
    "SuccessResult",
    "__version__",
    "evaluate_success",
    "get_task_names",
    "make_mt_env",
    "tune_process",
]


def __getattr__(name: str) -> Any:
    """Import a public name's module on first use (PEP 562), and keep the name here."""
    if name not in _MODULE_OF:
        raise AttributeError(f"module 'sb3_mtte' has no attribute {name!r}")
    value = getattr(importlib.import_module(_MODULE_OF[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
