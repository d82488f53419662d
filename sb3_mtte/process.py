"""Process settings for training speed: OpenMP's spin-wait and glibc's malloc thresholds.

Importing the package changes neither. The ``sb3-mtte`` commands apply both, first thing, before torch loads. A
script applies them with one call, before anything imports torch::

    import sb3_mtte

    sb3_mtte.tune_process()  # before torch loads: import sb3_mtte alone does not load it

    from sb3_mtte import MTSACTE

=================  =============================================  ===================================================
setting            what it changes                                after torch has loaded
=================  =============================================  ===================================================
spin count         ``GOMP_SPINCOUNT``: how long idle OpenMP       nothing in this process, since libgomp reads the
                   threads busy-wait between parallel regions     variable once, as torch loads; the call warns and
                                                                  skips it
malloc thresholds  glibc's mmap and trim thresholds               applied at once, to this process only
                   (``mallopt``): freed memory kept for reuse
=================  =============================================  ===================================================

PyTorch's CPU wheels use GNU OpenMP (libgomp). Its idle threads spin 300,000 times before they sleep. A training
step runs thousands of short parallel regions, so two training processes on the same cores spin against each other.
A shorter spin lets processes that share cores keep their share.

glibc serves large blocks from fresh mappings and hands the top of its heap back to the kernel. A training update
frees and allocates the same activations and gradients at every step. The kernel then maps and zero-fills that
memory again at every update. Raised thresholds let malloc reuse the freed blocks.

A setting of your own always wins. With ``GOMP_SPINCOUNT`` or ``OMP_WAIT_POLICY`` set, the spin count stays yours.
With any ``MALLOC_*`` tunable or ``SB3_MTTE_MALLOC=default`` set, glibc keeps its thresholds. Processes started
later inherit ``GOMP_SPINCOUNT`` from the environment, but not the malloc thresholds. Nothing computed changes either
way.
"""

from __future__ import annotations

import ctypes
import os
import sys
import warnings
from typing import NamedTuple

SPIN_COUNT = 5000
"""The spin count :func:`tune_process` sets (libgomp's own default: 300,000)."""
SPIN_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
"""A user's choice of OpenMP wait policy: either one keeps the spin count as it is."""

MMAP_THRESHOLD = 32 * 1024 * 1024  # the largest glibc accepts on 64-bit: bigger blocks (replay buffers) stay mapped
TRIM_THRESHOLD = 256 * 1024 * 1024
MALLOC_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")
"""glibc's own malloc tunables: any one of them keeps glibc's thresholds as they are."""
MALLOC_OPT_OUT = "SB3_MTTE_MALLOC"
"""``SB3_MTTE_MALLOC=default`` keeps glibc's thresholds."""
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameter numbers of <malloc.h>

_applied = {"spin_count": False, "malloc_thresholds": False}
"""What this process has had applied by :func:`tune_process` (nothing until it is called)."""


class ProcessTuning(NamedTuple):
    """What one call of :func:`tune_process` applied."""

    spin_count: bool
    """``GOMP_SPINCOUNT`` was set, before torch loaded."""
    malloc_thresholds: bool
    """glibc's mmap and trim thresholds were raised."""


def tune_process(spin_count: bool = True, malloc_thresholds: bool = True) -> ProcessTuning:
    """Apply the package's speed settings to this process, leaving every setting of the user's own alone.

    Call it before torch is imported. ``import sb3_mtte`` does not import torch, but ``from sb3_mtte import MTSAC``
    and any ``sb3_mtte`` submodule may. Called after torch has loaded, the spin count cannot change for this process:
    the call then warns and skips it. The malloc thresholds apply at any time. Calling it again changes nothing.

    :param spin_count: set ``GOMP_SPINCOUNT`` to :data:`SPIN_COUNT`.
    :param malloc_thresholds: raise glibc's mmap and trim thresholds (Linux with glibc only).
    :return: what this call applied.
    """
    return ProcessTuning(
        spin_count=spin_count and set_spin_count(),
        malloc_thresholds=malloc_thresholds and keep_freed_memory(),
    )


def set_spin_count() -> bool:
    """Set ``GOMP_SPINCOUNT`` unless the user chose a wait policy; warn and skip when torch is already loaded.

    The variable stays in ``os.environ``, so processes started from this one get it too.

    :return: whether the variable was set by this call.
    """
    if any(name in os.environ for name in SPIN_VARIABLES):
        return False
    if "torch" in sys.modules:
        warnings.warn(
            "torch was imported before sb3_mtte.tune_process(), so its OpenMP threads keep libgomp's default spin "
            f"count. Call tune_process() before importing torch, or set GOMP_SPINCOUNT={SPIN_COUNT} in the "
            "environment.",
            stacklevel=3,
        )
        return False
    os.environ["GOMP_SPINCOUNT"] = str(SPIN_COUNT)
    _applied["spin_count"] = True
    return True


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds unless the user set a ``MALLOC_*`` tunable or opted out.

    :return: whether the thresholds were set (False off Linux with glibc, or when the user chose their own).
    """
    if os.environ.get(MALLOC_OPT_OUT) == "default" or any(name in os.environ for name in MALLOC_VARIABLES):
        return False
    libc = glibc()
    if libc is None:
        return False
    applied = bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )
    _applied["malloc_thresholds"] = _applied["malloc_thresholds"] or applied
    return applied


def glibc() -> ctypes.CDLL | None:
    """The C library of this process when it is glibc (musl and other platforms have no such mallopt), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # noqa: B018  # present in glibc only
    except (OSError, AttributeError):
        return None
    return libc


def applied_settings() -> ProcessTuning:
    """What :func:`tune_process` has applied to this process so far (both False until it is called)."""
    return ProcessTuning(**_applied)
