"""rl-baselines3-zoo launcher of the multi-task algorithms: ``python -m sb3_mtte.zoo <command>``, the commands of
``sb3-mtte`` (train, enjoy, record_video, evaluate, record, plot, sweep; :mod:`sb3_mtte.experiments.cli`).
"""

from sb3_mtte.experiments.cli import zoo_main as main

__all__ = ["main"]

if __name__ == "__main__":
    main()
