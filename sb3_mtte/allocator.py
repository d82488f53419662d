"""Keep freed tensor memory in the process instead of handing it back to the kernel (glibc malloc).

glibc serves large blocks from fresh mappings (above its mmap threshold) and returns the top of its heap to the
kernel once that exceeds the trim threshold. A training update frees and re-allocates the same activations and
gradients every step, so the kernel maps and zero-fills the same amount of memory again at every update: thousands
of page faults per update. Raising both thresholds lets malloc reuse the freed blocks. mallopt can be called at any
time, so the order of imports does not matter here. ``SB3_MTTE_MALLOC=default`` keeps glibc's own behaviour.
"""

from __future__ import annotations

import ctypes
import os
import sys

MMAP_THRESHOLD = 32 * 1024 * 1024  # the largest glibc accepts on 64-bit: bigger blocks (replay buffers) stay mapped
TRIM_THRESHOLD = 256 * 1024 * 1024
USER_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")
OPT_OUT = "SB3_MTTE_MALLOC"  # "default": leave glibc's thresholds alone
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameter numbers of <malloc.h>


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds unless the user set a ``MALLOC_*`` tunable or opted out.

    :return: whether the thresholds were set (False off Linux/glibc or when the user chose their own).
    """
    if os.environ.get(OPT_OUT) == "default" or any(name in os.environ for name in USER_VARIABLES):
        return False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # noqa: B018  # present in glibc only; musl has a different mallopt
    except (OSError, AttributeError):
        return False
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )
