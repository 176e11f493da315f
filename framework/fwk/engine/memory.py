"""Keep freed memory for the next training step instead of handing it back to the kernel.

torch allocates CPU tensors with the C library's allocator. glibc serves a block above its mmap
threshold (128 KB at first, raised up to 32 MB as such blocks are freed) with a fresh ``mmap``
and unmaps it on ``free``; a step that makes a 45 MB intermediate (the thesis-width vcconv VAE
makes several) therefore faults every one of its pages in again at every step, and the kernel
zeroes each page first. On this project's 2-core machine, pages fault in at 1-3 GB/s, so a
45 MB tensor costs 15-30 ms before any arithmetic, and a step of the thesis-width VAE faulted
about 50,000 pages (200 MB). This is what the PyTorch CPU performance guides answer with
jemalloc or tcmalloc preloaded; fwk does it in-process with glibc's own ``mallopt``:

* ``M_MMAP_THRESHOLD`` 1 GiB: blocks below it come from the heap, whose freed blocks the next
  step reuses (a larger block is still mapped, and unmapped when freed);
* ``M_TRIM_THRESHOLD`` 2 GiB - 1: free memory at the top of the heap is kept up to that amount;
* ``M_TOP_PAD`` 64 MiB: the heap grows in steps of at least that much.

The resident memory of a training then stays near its peak between steps (it would reach that
peak in every step anyway). Applied by ``fwk.engine.trainer.fit`` once per process; nothing is
done where the C library is not glibc, where ``FWK_KEEP_FREED_MEMORY=0``, or where the user set
glibc's own ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` / ``MALLOC_TOP_PAD_`` /
``MALLOC_MMAP_MAX_`` (theirs win). Measured in ``benchmarks/training.py`` (``--default-malloc``
times glibc's defaults instead).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform

M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
SETTINGS = {M_MMAP_THRESHOLD: 1 << 30, M_TRIM_THRESHOLD: (1 << 31) - 1, M_TOP_PAD: 64 << 20}
USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")

_applied: str | None = None


def retain_freed_memory(env=None) -> str:
    """Sets glibc's thresholds (module docstring) once per process; returns what was done, in words."""
    global _applied
    if _applied is not None:
        return _applied
    env = os.environ if env is None else env
    if env.get("FWK_KEEP_FREED_MEMORY", "1") == "0":
        _applied = "not applied: FWK_KEEP_FREED_MEMORY=0"
    elif any(k in env for k in USER_SETTINGS):
        _applied = "not applied: glibc's MALLOC_* settings in the environment are used"
    elif platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        _applied = "not applied: the C library is not glibc"
    else:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            ok = all(libc.mallopt(ctypes.c_int(k), ctypes.c_int(v)) == 1 for k, v in SETTINGS.items())
            _applied = "applied" if ok else "not applied: mallopt refused a setting"
        except (OSError, AttributeError) as e:
            _applied = f"not applied: {e}"
    return _applied
