"""Thread control for many small GP problems.

Switching-state models are small (a few hundred points): at that size torch's (and
OpenBLAS's) threads cost more in synchronisation than they gain, and when other processes
share the cores they oversubscribe them (measured: synthesis 14x slower with 2 threads
than with 1 under a load of 6 on 2 cores). Work on small matrices therefore runs inside
:func:`torch_threads` (1 thread), and parallelism comes from processes instead.
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def torch_threads(n: int = 1) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads and ``n`` BLAS threads (numpy/scipy,
    through threadpoolctl), restoring the previous numbers."""
    from threadpoolctl import threadpool_limits

    prev = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        with threadpool_limits(limits=n):
            yield
    finally:
        torch.set_num_threads(prev)
