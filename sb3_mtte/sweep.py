"""``python -m sb3_mtte.sweep --algos ... --envs ... [options]``: a grid of training runs on Ray Tune.

The same as ``sb3-mtte sweep`` (:mod:`sb3_mtte.experiments.sweep`).
"""

from sb3_mtte.experiments import closed_pipe_exit
from sb3_mtte.experiments.sweep import main

__all__ = ["main"]

if __name__ == "__main__":
    closed_pipe_exit(main)
