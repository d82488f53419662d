"""``python -m sb3_mtte.plot RUNS_DIR [options]``: figures and Table 1 of the paper from a folder of runs.

The same as ``sb3-mtte plot`` (:mod:`sb3_mtte.experiments.plot`).
"""

from sb3_mtte.experiments import closed_pipe_exit
from sb3_mtte.experiments.plot import main

__all__ = ["main"]

if __name__ == "__main__":
    closed_pipe_exit(main)
