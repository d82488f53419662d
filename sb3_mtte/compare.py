"""``python -m sb3_mtte.compare SOURCE --benchmark B``: two algorithms compared as fixed before the runs.

The same as ``sb3-mtte compare`` (:mod:`sb3_mtte.experiments.compare`).
"""

from sb3_mtte.experiments.compare import main

__all__ = ["main"]

if __name__ == "__main__":
    main()
