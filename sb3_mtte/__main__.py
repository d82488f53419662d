"""``python -m sb3_mtte <command>``: the commands of ``sb3-mtte`` (:mod:`sb3_mtte.experiments.cli`)."""

from sb3_mtte.experiments.cli import console_main

if __name__ == "__main__":
    console_main()
