"""Thread control for many small GP problems.

Switching-state models are small (a few hundred points): at that size torch's (and
OpenBLAS's) threads cost more in synchronisation than they gain, and when other processes
share the cores they oversubscribe them (measured: synthesis 14x slower with 2 threads
than with 1 under a load of 6 on 2 cores). Work on small matrices therefore runs inside
:func:`torch_threads` (1 thread), and parallelism comes from processes instead.

Results must not depend on the machine's load. MKL (torch's BLAS/LAPACK on x86-64) is
"dynamic" by default: it may run a call on fewer threads than asked when the cores are
busy, which changes the order of floating-point reductions, so the same computation gives
results that differ in the last bits from one run to the next — enough to send a chaotic
search (MAP restarts, L-BFGS on a multimodal density) to another mode. Importing this module
switches that off (``mkl_set_dynamic(0)``, :func:`fix_mkl_thread_count`): MKL then runs on
exactly the thread count torch was given, and a run with a given count is repeatable
whatever the load. Code whose results must be bit-stable runs inside :func:`torch_threads`.

The factors of a fitted GP (its Cholesky factor L and K⁻¹Y, :class:`~bayes_talk.gp.predictive.GPPredictor`)
are computed inside :func:`one_thread`, whatever the caller's count: MKL's factorisation on
two threads and on one differ in the last bits, and those bits are enough to move a
synthesis's MAP to another mode (measured: a model loaded with two torch threads and the
same model loaded with one synthesised an utterance 0.2 AAM units apart). A model then
gives the same synthesis whether it was loaded in a fresh process, in a process whose
thread count was lowered (an evaluation, a worker), or just trained.
"""
from __future__ import annotations

import contextlib
import ctypes
import logging
from collections.abc import Iterator
from pathlib import Path

import torch

log = logging.getLogger(__name__)


def torch_cpu_library() -> ctypes.CDLL | None:
    """torch's CPU library (``libtorch_cpu``), loaded with :mod:`ctypes`, or None where it
    cannot be found or loaded: the MKL (and LAPACK) that torch is linked with lives there."""
    lib_dir = Path(torch.__file__).resolve().parent / "lib"
    for name in ("libtorch_cpu.so", "libtorch_cpu.dylib"):
        path = lib_dir / name
        if not path.exists():
            continue
        try:
            return ctypes.CDLL(str(path))
        except OSError:
            return None
    return None


def fix_mkl_thread_count() -> bool:
    """Stop MKL from lowering its thread count under load (``mkl_set_dynamic(0)`` in the MKL
    that torch's CPU library is linked with). Returns whether the call was made (False where
    this torch build has no MKL, e.g. on ARM or macOS, where nothing adapts to load)."""
    lib = torch_cpu_library()
    set_dynamic = getattr(lib, "MKL_Set_Dynamic", None) if lib is not None else None
    if set_dynamic is None:
        return False
    set_dynamic(0)
    log.debug("MKL dynamic threading switched off")
    return True


MKL_THREADS_FIXED = fix_mkl_thread_count()


#: a GP problem of fewer points runs on one thread (:func:`problem_threads`; the terms of
#: :mod:`bayes_talk.gp.fused` also follow it). Measured (docs/scaling.md): on a
#: quiet 2-core machine two threads gain nothing on one observation term below about 800
#: points (1.47× slower at 200, 0.97-1.12 at 300-600, 0.90 at 800, 0.83 at 1,000), and with
#: the other core busy every parallel region of a small problem waits milliseconds for its
#: second thread.
THREADED_MIN_N = 800


@contextlib.contextmanager
def problem_threads(n_points: int) -> Iterator[None]:
    """The block (a GP objective on ``n_points`` points) on one torch and MKL thread when
    ``n_points`` < :data:`THREADED_MIN_N`, else on torch's thread count. Only the calling
    thread's count is set (``torch.set_num_threads``: OpenMP's and MKL's thread-local
    counts), and restored; no BLAS other than torch's MKL is touched (unlike
    :func:`torch_threads`, so it costs microseconds and fits inside an objective)."""
    if n_points >= THREADED_MIN_N:
        yield
        return
    with one_thread():
        yield


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """The block on one torch (and MKL) thread, whatever the caller's count; the count is
    restored after it. Only the calling thread's count is set (as :func:`problem_threads`;
    microseconds), for arithmetic whose bits must not depend on the caller's thread count
    (a fitted GP's factors)."""
    prev = torch.get_num_threads()
    if prev == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(prev)


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
