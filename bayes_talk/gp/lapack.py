"""In-place LAPACK on Fortran-ordered float64 arrays, lower triangle only.

The fused GP core (:mod:`bayes_talk.gp.fused`) factorises and inverts one N×N buffer in
place: ``dpotrf`` (K = L Lᵀ), ``dpotrs`` (K⁻¹B) and ``dpotri`` (K⁻¹ from L), each
touching only the lower triangle, so the strict upper triangle of the same buffer can
hold other data.

Two providers of the three routines:

* ``torch-mkl``: the MKL that torch's CPU library is linked with (x86-64 Linux wheels
  export its Fortran symbols ``dpotrf_``, ``dpotri_``, ``dpotrs_``), called through
  :mod:`ctypes`. It is the
  LAPACK torch itself uses for ``torch.linalg.cholesky``, so results are identical to
  the torch path's factor, and it follows ``torch.set_num_threads``. Measured on this
  machine at N = 2000, one thread: ``dpotri`` 0.20 s against 0.33 s for scipy's
  OpenBLAS, ``dpotrf`` 0.09 s against 0.15 s.
* ``scipy``: :mod:`scipy.linalg.lapack` (OpenBLAS), with
  ``overwrite`` flags so they work in place too; used where torch exports no LAPACK
  symbols (other platforms, other torch builds).

The default is ``torch-mkl`` when available, else ``scipy``; the switch ``lapack`` of
:mod:`bayes_talk.base.settings` (``BAYES_TALK_LAPACK=scipy``, read at each call) or
:func:`set_provider` chooses scipy.
:func:`provider` names the one in use.

Threads: MKL inside torch follows ``torch.set_num_threads``; each routine takes
``threads``, the most MKL threads for that call (set thread-locally with
``MKL_Set_Num_Threads_Local`` and restored; None: torch's count), and ``dpotri`` runs on
at most ``potri_threads`` MKL threads besides (:mod:`bayes_talk.base.settings`; default 1,
environment variable ``BAYES_TALK_POTRI_THREADS``, 0 = follow torch). The scipy provider
ignores ``threads`` (its OpenBLAS keeps its own count). Measured on this shared 2-core machine
with other processes on both cores (one thread; median of 7): MKL ``dpotrf`` + ``dpotri``
at N = 2000 took 0.14 + 0.19 s on one thread, and 0.19 + 1.65 s on two threads (at
N = 1000 0.05 s against 3.6 s): MKL's two-thread ``dpotri`` collapses when the second
core is taken, its ``dpotrf`` does not. On an idle multi-core machine raise it.
"""
from __future__ import annotations

import contextlib
import ctypes
from collections.abc import Iterator

import numpy as np
import torch
from scipy.linalg import lapack

from bayes_talk.base import settings
from bayes_talk.gp.threads import torch_cpu_library

_c_int = ctypes.c_int
_c_double = ctypes.c_double
_ptr = ctypes.c_void_p
_LEN1 = ctypes.c_size_t(1)  # hidden Fortran string-length argument
_ROUTINES = ("dpotrf_", "dpotri_", "dpotrs_")


def _torch_lapack() -> ctypes.CDLL | None:
    """torch's CPU library when it exports the Fortran LAPACK/BLAS routines used here."""
    lib = torch_cpu_library()
    if lib is not None and all(hasattr(lib, r) for r in _ROUTINES):
        return lib
    return None


_TORCH_LIB = _torch_lapack()


def _lib():
    """torch's LAPACK library, or None for scipy (the ``lapack`` switch, or none exported)."""
    return None if settings.get("lapack") == "scipy" else _TORCH_LIB


def provider() -> str:
    """The LAPACK in use: ``"torch-mkl"`` or ``"scipy"`` (see the module docstring)."""
    return "torch-mkl" if _lib() is not None else "scipy"


def set_provider(name: str) -> None:
    """Use ``"torch-mkl"`` (when torch exports it) or ``"scipy"`` from now on (sets the
    ``lapack`` switch of :mod:`bayes_talk.base.settings` for the process)."""
    if name not in ("torch-mkl", "scipy"):
        raise ValueError(f"unknown LAPACK provider {name!r}: expected 'torch-mkl' or 'scipy'")
    if name == "torch-mkl" and _TORCH_LIB is None:
        raise ValueError("LAPACK provider 'torch-mkl': this torch build exports no dpotrf_/dpotri_/dpotrs_")
    settings.set_switch("lapack", name)


def _check(a: np.ndarray, what: str) -> None:
    if a.dtype != np.float64 or not a.flags.f_contiguous:
        raise TypeError(f"{what}: a Fortran-ordered float64 array is needed, got {a.dtype}, "
                        f"f_contiguous={a.flags.f_contiguous}")


def _data(a: np.ndarray):
    return a.ctypes.data_as(_ptr)


@contextlib.contextmanager
def _mkl_threads(lib, threads: int | None) -> Iterator[None]:
    """At most ``threads`` MKL threads for this thread's calls in the block (None, or no
    MKL: unchanged)."""
    set_local = getattr(lib, "MKL_Set_Num_Threads_Local", None) if lib is not None else None
    if set_local is None or threads is None:
        yield
        return
    prev = set_local(max(1, min(threads, torch.get_num_threads())))
    try:
        yield
    finally:
        set_local(prev)


def _square_in_place(a: np.ndarray, routine: str, scipy_call, threads: int | None) -> int:
    """``routine`` ('L') on the square array ``a`` in place, on at most ``threads`` MKL
    threads; LAPACK's ``info``."""
    _check(a, routine)
    lib = _lib()
    if lib is None:
        out, info = scipy_call(a)
        if out is not a and a.size:
            a[...] = out
        return int(info)
    n_, info = _c_int(a.shape[0]), _c_int(0)
    with _mkl_threads(lib, threads):
        getattr(lib, routine + "_")(b"L", ctypes.byref(n_), _data(a), ctypes.byref(n_), ctypes.byref(info), _LEN1)
    return info.value


def potrf_lower(a: np.ndarray, threads: int | None = None) -> int:
    """Overwrite the lower triangle of the N×N array ``a`` with L, K = L Lᵀ (``dpotrf``,
    'L'); the strict upper triangle is not touched. Returns LAPACK's ``info`` (0: success,
    k > 0: the leading minor of order k is not positive definite). ``threads``: the most
    MKL threads (module docstring)."""
    return _square_in_place(a, "dpotrf", lambda a: lapack.dpotrf(a, lower=1, clean=0, overwrite_a=1), threads)


def potri_lower(a: np.ndarray, threads: int | None = None) -> int:
    """Overwrite the lower triangle of ``a`` (holding L) with that of K⁻¹ (``dpotri``,
    'L'); the strict upper triangle is not touched. Returns ``info``. Runs on at most
    ``threads`` and at most ``potri_threads`` MKL threads (module docstring)."""
    cap = settings.get("potri_threads")
    if cap is not None:
        threads = cap if threads is None else min(cap, threads)
    return _square_in_place(a, "dpotri", lambda a: lapack.dpotri(a, lower=1, overwrite_c=1), threads)


def potrs_lower(L: np.ndarray, b: np.ndarray, threads: int | None = None) -> int:
    """Overwrite ``b`` (N×D, Fortran order) with K⁻¹ b, K = L Lᵀ and L in the lower
    triangle of ``L`` (``dpotrs``, 'L'). Returns ``info``. ``threads``: the most MKL
    threads (module docstring)."""
    _check(L, "potrs factor")
    _check(b, "potrs right-hand side")
    lib = _lib()
    if lib is None:
        out, info = lapack.dpotrs(L, b, lower=1, overwrite_b=1)
        if out is not b and b.size:
            b[...] = out
        return int(info)
    n_, d_, info = _c_int(L.shape[0]), _c_int(b.shape[1]), _c_int(0)
    with _mkl_threads(lib, threads):
        lib.dpotrs_(b"L", ctypes.byref(n_), ctypes.byref(d_), _data(L), ctypes.byref(n_),
                     _data(b), ctypes.byref(n_), ctypes.byref(info), _LEN1)
    return info.value
