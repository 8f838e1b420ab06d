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

The default is ``torch-mkl`` when available, else ``scipy``; the environment variable
``BAYES_TALK_LAPACK=scipy`` (read at import) or :func:`set_provider` chooses scipy.
:func:`provider` names the one in use.

Threads: MKL inside torch follows ``torch.set_num_threads``; on this shared 2-core
machine under load (other processes on both cores) MKL's two-thread ``dpotri`` was
measured 4x slower than on one thread, while OpenBLAS degraded less; the per-state
models run on one thread (:mod:`bayes_talk.gp.threads`), where MKL is the faster.
"""
from __future__ import annotations

import ctypes
import os
from pathlib import Path

import numpy as np
import torch
from scipy.linalg import lapack

_c_int = ctypes.c_int
_c_double = ctypes.c_double
_ptr = ctypes.c_void_p
_LEN1 = ctypes.c_size_t(1)  # hidden Fortran string-length argument
_ROUTINES = ("dpotrf_", "dpotri_", "dpotrs_")


def _torch_lapack() -> ctypes.CDLL | None:
    """torch's CPU library when it exports the Fortran LAPACK/BLAS routines used here."""
    lib_dir = Path(torch.__file__).resolve().parent / "lib"
    for name in ("libtorch_cpu.so", "libtorch_cpu.dylib"):
        path = lib_dir / name
        if not path.exists():
            continue
        try:
            lib = ctypes.CDLL(str(path))
        except OSError:
            return None
        if all(hasattr(lib, r) for r in _ROUTINES):
            return lib
    return None


_TORCH_LIB = _torch_lapack()
_LIB = None if os.environ.get("BAYES_TALK_LAPACK", "") == "scipy" else _TORCH_LIB


def provider() -> str:
    """The LAPACK in use: ``"torch-mkl"`` or ``"scipy"`` (see the module docstring)."""
    return "torch-mkl" if _LIB is not None else "scipy"


def set_provider(name: str) -> None:
    """Use ``"torch-mkl"`` (when torch exports it) or ``"scipy"`` from now on."""
    global _LIB
    if name == "scipy":
        _LIB = None
    elif name == "torch-mkl":
        if _TORCH_LIB is None:
            raise ValueError("LAPACK provider 'torch-mkl': this torch build exports no dpotrf_/dpotri_/dpotrs_")
        _LIB = _TORCH_LIB
    else:
        raise ValueError(f"unknown LAPACK provider {name!r}: expected 'torch-mkl' or 'scipy'")


def _check(a: np.ndarray, what: str) -> None:
    if a.dtype != np.float64 or not a.flags.f_contiguous:
        raise TypeError(f"{what}: a Fortran-ordered float64 array is needed, got {a.dtype}, "
                        f"f_contiguous={a.flags.f_contiguous}")


def _data(a: np.ndarray):
    return a.ctypes.data_as(_ptr)


def potrf_lower(a: np.ndarray) -> int:
    """Overwrite the lower triangle of the N×N array ``a`` with L, K = L Lᵀ (``dpotrf``,
    'L'); the strict upper triangle is not touched. Returns LAPACK's ``info`` (0: success,
    k > 0: the leading minor of order k is not positive definite)."""
    _check(a, "potrf")
    n = a.shape[0]
    if _LIB is None:
        out, info = lapack.dpotrf(a, lower=1, clean=0, overwrite_a=1)
        if out is not a and n:
            a[...] = out
        return int(info)
    n_, info = _c_int(n), _c_int(0)
    _LIB.dpotrf_(b"L", ctypes.byref(n_), _data(a), ctypes.byref(n_), ctypes.byref(info), _LEN1)
    return info.value


def potri_lower(a: np.ndarray) -> int:
    """Overwrite the lower triangle of ``a`` (holding L) with that of K⁻¹ (``dpotri``,
    'L'); the strict upper triangle is not touched. Returns ``info``."""
    _check(a, "potri")
    n = a.shape[0]
    if _LIB is None:
        out, info = lapack.dpotri(a, lower=1, overwrite_c=1)
        if out is not a and n:
            a[...] = out
        return int(info)
    n_, info = _c_int(n), _c_int(0)
    _LIB.dpotri_(b"L", ctypes.byref(n_), _data(a), ctypes.byref(n_), ctypes.byref(info), _LEN1)
    return info.value


def potrs_lower(L: np.ndarray, b: np.ndarray) -> int:
    """Overwrite ``b`` (N×D, Fortran order) with K⁻¹ b, K = L Lᵀ and L in the lower
    triangle of ``L`` (``dpotrs``, 'L'). Returns ``info``."""
    _check(L, "potrs factor")
    _check(b, "potrs right-hand side")
    if _LIB is None:
        out, info = lapack.dpotrs(L, b, lower=1, overwrite_b=1)
        if out is not b and b.size:
            b[...] = out
        return int(info)
    n_, d_, info = _c_int(L.shape[0]), _c_int(b.shape[1]), _c_int(0)
    _LIB.dpotrs_(b"L", ctypes.byref(n_), ctypes.byref(d_), _data(L), ctypes.byref(n_),
                 _data(b), ctypes.byref(n_), ctypes.byref(info), _LEN1)
    return info.value
