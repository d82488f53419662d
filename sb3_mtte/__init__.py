"""sb3-mtte: multi-task SAC with a task embedding network, and the MTSAC baselines, for Stable-Baselines3."""

from sb3_mtte.allocator import keep_freed_memory
from sb3_mtte.openmp import set_spin_default

set_spin_default()  # before torch loads its OpenMP runtime
keep_freed_memory()


from sb3_mtte.common.buffers import MultiTaskReplayBuffer
from sb3_mtte.common.evaluation import MultiTaskEvalCallback, SuccessResult, evaluate_success
from sb3_mtte.envs import OneHotTaskWrapper, get_task_names, make_mt_env
from sb3_mtte.mtsac import MTSAC
from sb3_mtte.mtsacte import MTSACTE
from sb3_mtte.version import __version__

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
]
