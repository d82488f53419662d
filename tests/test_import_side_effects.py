"""Importing the package changes no process state: os.environ stays as it was and glibc's malloc keeps its thresholds.

Each probe is a fresh interpreter that imports the package and every public name (so torch and the algorithms load
too). It then asks glibc's malloc for a 30 MiB block: under glibc's own thresholds that block gets a mapping of its
own (``mallinfo2().hblkhd`` grows by it); under the package's raised mmap threshold (32 MiB) it comes from the heap.
The same probe with :func:`sb3_mtte.tune_process` called shows both changes, so the probe can see them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from sb3_mtte import process

PROBE = """
import ctypes, json, os, sys
environ_before = dict(os.environ)
import sb3_mtte
torch_loaded_by_import = "torch" in sys.modules
if sys.argv[1] == "tune":
    sb3_mtte.tune_process()
for name in sb3_mtte.__all__:
    getattr(sb3_mtte, name)
assert "torch" in sys.modules

class MallInfo2(ctypes.Structure):
    _fields_ = [(field, ctypes.c_size_t) for field in
                "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]

libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
size = 30 << 20
mapped_before = libc.mallinfo2().hblkhd
block = libc.malloc(size)
mapped = libc.mallinfo2().hblkhd - mapped_before >= size
libc.free(block)
changed = sorted(k for k in {*environ_before, *os.environ} if environ_before.get(k) != os.environ.get(k))
print(json.dumps({"changed": changed, "mapped": mapped, "torch_loaded_by_import": torch_loaded_by_import,
                  "applied": sb3_mtte.process.applied_settings()._asdict()}))
"""


def probe(mode: str) -> dict:
    """Run the probe in a fresh interpreter whose environment holds no OpenMP or malloc setting of a user's."""
    user_settings = (*process.SPIN_VARIABLES, *process.MALLOC_VARIABLES, process.MALLOC_OPT_OUT)
    env = {k: v for k, v in os.environ.items() if k not in user_settings}
    out = subprocess.run([sys.executable, "-c", PROBE, mode], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallinfo2")
def test_import_changes_no_environment_variable_and_no_malloc_threshold() -> None:
    imported = probe("import")
    assert imported["changed"] == []
    assert imported["mapped"], "a 30 MiB block came from the heap: the mmap threshold was raised"
    assert imported["applied"] == {"spin_count": False, "malloc_thresholds": False}
    assert not imported["torch_loaded_by_import"], "import sb3_mtte loaded torch: tune_process() would come too late"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallinfo2")
def test_the_probe_sees_what_tune_process_changes() -> None:
    tuned = probe("tune")
    assert tuned["changed"] == ["GOMP_SPINCOUNT"]
    assert not tuned["mapped"]
    assert tuned["applied"] == {"spin_count": True, "malloc_thresholds": True}
