"""Keep freed N×N arrays from inflating a process's memory.

GP training and synthesis allocate and free many large float64 matrices: kernel
matrices, their Cholesky factors and the buffers of the fused GP core
(:mod:`bayes_talk.gp.fused`), 18 MB each at N = 1,500. glibc's ``malloc`` serves a
request of at least ``M_MMAP_THRESHOLD`` bytes (128 KiB at start-up) with its own
``mmap``, returned to the system by ``free``; but the threshold is *dynamic*: each
time such a block is freed, the threshold rises to its size (up to 32 MiB). From then
on every N×N matrix is carved out of the heap, and the heap is only given back from its
top end, so freed matrices below a live one stay resident. On one deena2009 split this
alone kept ~170 MB more resident than the live arrays needed (the SGPLVM fit peaked at
897 MB with the dynamic threshold, 725 MB with a fixed one; docs/scaling.md).

:func:`release_large_blocks` fixes the threshold (which turns the dynamic adjustment
off) so every large block keeps its own mapping and goes back to the system as soon as
it is freed. Nothing numerical changes: only where the bytes live. It is called where
the library's heavy work starts (the CLI, every executor task, :func:`run_protocol
<bayes_talk.evaluation.harness.run_protocol>`); it is a no-op off glibc, and when the
user has set ``MALLOC_MMAP_THRESHOLD_`` (glibc's own environment variable, which then
wins) or ``BAYES_TALK_MALLOC=0``.
"""
from __future__ import annotations

import ctypes
import os

from bayes_talk.base import settings

__all__ = ["MMAP_THRESHOLD", "release_large_blocks"]

#: requests of at least this many bytes get their own mapping (1 MiB: an N×N float64
#: matrix from N = 363; smaller arrays stay in the heap, where reuse is cheap)
MMAP_THRESHOLD = 1 << 20
_M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter number (malloc.h)
_done: bool | None = None


def release_large_blocks() -> bool:
    """Fix glibc's mmap threshold at :data:`MMAP_THRESHOLD` in this process (once).

    Returns True when the setting is in force (set now or by an earlier call), False
    when it was skipped: not glibc, ``MALLOC_MMAP_THRESHOLD_`` set by the user, or
    ``BAYES_TALK_MALLOC=0``."""
    global _done
    if _done is not None:
        return _done
    _done = False
    if not settings.get("malloc") or "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return False
    try:
        libc = ctypes.CDLL(None)  # the symbols already loaded (find_library would run ldconfig)
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 - glibc only (musl has no dynamic threshold)
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _done = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
    return _done
