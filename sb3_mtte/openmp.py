"""How long PyTorch's OpenMP threads spin before they sleep: set before the runtime loads.

PyTorch's CPU wheels use GNU OpenMP (libgomp). Between parallel regions its idle threads busy-wait for
``GOMP_SPINCOUNT`` iterations (300,000 by default) before sleeping. A training step runs thousands of short
regions, so two training processes on the same cores spend most of their time spinning against each other. A
shorter spin keeps a lone process as fast while processes that share cores keep their share. libgomp reads the
variable once, when it loads (at ``import torch``), so the package sets it on import, before importing torch.
"""

from __future__ import annotations

import os
import sys
import warnings

SPIN_COUNT = "5000"
USER_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
_state = {"applied": False, "torch_loaded_first": False}


def set_spin_default() -> bool:
    """Set ``GOMP_SPINCOUNT`` unless the user chose a wait policy or PyTorch is already loaded.

    :return: whether the default was applied to this process.
    """
    if any(name in os.environ for name in USER_VARIABLES):
        return False
    if "torch" in sys.modules:
        _state["torch_loaded_first"] = True
        return False
    os.environ["GOMP_SPINCOUNT"] = SPIN_COUNT
    _state["applied"] = True
    return True


def warn_if_spinning(n_threads: int) -> None:
    """Warn (once) when PyTorch was loaded before the package with the default spin-wait and several threads."""
    if _state["torch_loaded_first"] and n_threads > 1:
        _state["torch_loaded_first"] = False
        warnings.warn(
            "torch was imported before sb3_mtte, so its OpenMP threads busy-wait for libgomp's default "
            "300,000 spins: training processes that share CPU cores then slow each other down several-fold. "
            f"Import sb3_mtte before torch, or set GOMP_SPINCOUNT={SPIN_COUNT} (or OMP_WAIT_POLICY=PASSIVE) in "
            "the environment, or use torch.set_num_threads(1) per process.",
            stacklevel=3,
        )
