"""OpenMP's spin count is set by :func:`sb3_mtte.process.tune_process`; training has nothing to warn about."""


def warn_if_spinning(n_threads: int) -> None:
    """Nothing: the spin count is the user's, or what :func:`~sb3_mtte.process.tune_process` set."""
