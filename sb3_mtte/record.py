"""``python -m sb3_mtte.record RUNS_DIR --out DIR``: one small JSON record per finished run.

The same as ``sb3-mtte record`` (:mod:`sb3_mtte.experiments.records`).
"""

from sb3_mtte.experiments import closed_pipe_exit
from sb3_mtte.experiments.records import main

__all__ = ["main"]

if __name__ == "__main__":
    closed_pipe_exit(main)
