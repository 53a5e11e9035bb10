"""The C allocator's handling of large freed blocks during training (``trainer.keep_freed_memory``).

A training step allocates and frees the same large tensors again and again (at 96x320, batch 4: the 22 MB stack of
SSIM's moments for the 12 reprojected views, the networks' activations and their gradients). By default glibc's
``malloc`` serves blocks over its (adaptive) mmap threshold with fresh ``mmap`` calls and gives freed memory at the
top of the heap back to the system, so each such tensor is page-faulted in again at every step: a million minor
page faults per ten ``depth_stage2`` steps on one thread, a fresh 22 MB tensor costing ~9 ms against ~1 ms when its
memory is reused. :func:`keep_freed_memory` sets glibc's mmap threshold to its maximum (32 MiB on 64-bit) and its trim
threshold to 1 GiB (``mallopt``), so freed blocks stay in the process for the next step: ~4x fewer page faults and
~x1.1 steps an hour for ``depth_stage2`` (docs/training.md). The process keeps up to that much freed memory resident
(a training run's peak is already held). Elsewhere than glibc (macOS, musl) nothing changes and the log says so.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "keep_freed_memory"]

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
MMAP_THRESHOLD = 32 << 20  # bytes: glibc's largest accepted mmap threshold on 64-bit (HEAP_MAX_SIZE / 2)
TRIM_THRESHOLD = 1 << 30  # bytes of free memory at the heap's top kept before any is returned


def keep_freed_memory() -> tuple[bool, str]:
    """Make glibc keep large freed blocks for reuse (module docstring); process-wide, for the rest of the process.

    Returns:
        (applied, reason): whether both ``mallopt`` calls succeeded, and a line for the log.
    """
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False, (f"trainer.keep_freed_memory: not glibc ({platform.system()} {platform.libc_ver()[0] or '?'}): "
                       "the allocator is left as it is")
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        ok = libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1 and libc.mallopt(M_TRIM_THRESHOLD,
                                                                                   TRIM_THRESHOLD) == 1
    except (OSError, AttributeError) as err:
        return False, f"trainer.keep_freed_memory: glibc's mallopt unavailable ({err}): the allocator is left as it is"
    if not ok:
        return False, "trainer.keep_freed_memory: glibc refused mallopt: the allocator is left as it is"
    return True, (f"trainer.keep_freed_memory: glibc keeps freed blocks up to {MMAP_THRESHOLD >> 20} MiB in the heap "
                  f"and up to {TRIM_THRESHOLD >> 30} GiB of free memory (mallopt): fewer page faults per step")
