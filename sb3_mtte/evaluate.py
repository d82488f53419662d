"""``python -m sb3_mtte.evaluate MODEL.zip [options]``: per-task success with Meta-World's protocol.

The same as ``sb3-mtte evaluate`` (:mod:`sb3_mtte.experiments.evaluate`).
"""

from sb3_mtte.experiments import closed_pipe_exit
from sb3_mtte.experiments.evaluate import main

__all__ = ["main"]

if __name__ == "__main__":
    closed_pipe_exit(main)
