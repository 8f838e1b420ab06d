"""The one place that calls ArviZ: the same NumPy-level API on ArviZ 0.2x
(Python 3.11) and ArviZ 1.x (``arviz-base`` / ``arviz-stats``, Python >= 3.12).

* :func:`rhat` - rank-normalised split R-hat (Vehtari et al. 2021) of draws
  (chains, draws, n), per coordinate.
* :func:`ess` - bulk (rank-normalised) or tail (the smaller of the ESS of the 5 % and 95 %
  quantile indicators) effective sample size (Vehtari et al. 2021).
* :func:`mcse` - Monte-Carlo standard error of the mean or of the standard deviation.
* :func:`bfmi` - energy Bayesian fraction of missing information per chain (Betancourt
  2016): Σ(E_n − E_{n−1})² / Σ(E_n − Ē)².
* :func:`psislw` - Pareto-smoothed importance log weights and the Pareto shape k̂
  (Vehtari et al. 2024).
* :func:`from_dict` / :func:`from_netcdf` - the InferenceData of 0.2x, an
  ``xarray.DataTree`` on 1.x: both give ``.posterior``, ``.attrs``, ``.to_netcdf``.

Both versions give the same numbers on the same draws (R-hat, bulk and tail ESS, MCSE,
BFMI to the last digit; checked on 2 × 100 × 3 standard-normal draws). Two 1.x calls need
their arguments spelled out for that: the tail ESS quantiles (1.x otherwise takes them
from its credible-interval setting, 0.89/0.94) and the sign of ``psislw``'s input
(arviz-stats negates it, taking log-likelihood values as in PSIS-LOO). ArviZ 0.23's numba path of ``mcse(method="sd")`` fails on NumPy >= 2.3, so numba is
switched off around that call (0.2x only).
"""
from __future__ import annotations

import warnings
from contextlib import contextmanager
from typing import Any

import numpy as np
from scipy.special import logsumexp

with warnings.catch_warnings():
    warnings.simplefilter("ignore", FutureWarning)  # arviz 0.2x announces its 1.0 refactor
    import arviz as az

__all__ = ["ARVIZ_1", "ARVIZ_VERSION", "bfmi", "ess", "from_dict", "from_netcdf", "mcse", "psislw", "rhat"]

#: the installed ArviZ version string
ARVIZ_VERSION: str = str(az.__version__)
#: True for ArviZ >= 1.0 (arviz-base / arviz-stats)
ARVIZ_1: bool = int(ARVIZ_VERSION.split(".")[0]) >= 1

if ARVIZ_1:
    from arviz_stats.base import array_stats as _array_stats

#: the quantiles of the tail ESS (Vehtari et al. 2021)
_TAIL_PROBS = (0.05, 0.95)


def _draws(samples: np.ndarray) -> np.ndarray:
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 3:
        raise ValueError(f"samples: expected (chains, draws, n), got shape {s.shape}")
    return s


@contextmanager
def _numba_off():
    was = bool(az.Numba.numba_flag)
    if was:
        az.Numba.disable_numba()
    try:
        yield
    finally:
        if was:
            az.Numba.enable_numba()


def _per_coord_0x(fn, s: np.ndarray, **kw) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "more chains than draws": emcee walkers
        idata = az.from_dict(posterior={"x": s})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.asarray(fn(idata, var_names=["x"], **kw)["x"].values, dtype=float).reshape(s.shape[2])


def _per_coord_1x(name: str, s: np.ndarray, **kw) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out = getattr(_array_stats, name)(s, chain_axis=0, draw_axis=1, **kw)
    return np.asarray(out, dtype=float).reshape(s.shape[2])


def rhat(samples: np.ndarray) -> np.ndarray:
    """Rank-normalised split R-hat (n,) of draws (chains, draws, n)."""
    s = _draws(samples)
    return _per_coord_1x("rhat", s, method="rank") if ARVIZ_1 else _per_coord_0x(az.rhat, s, method="rank")


def ess(samples: np.ndarray, method: str = "bulk") -> np.ndarray:
    """Effective sample size (n,) of draws (chains, draws, n); ``method`` "bulk" or "tail"."""
    if method not in ("bulk", "tail"):
        raise ValueError(f"ess method: expected 'bulk' or 'tail', found {method!r}")
    s = _draws(samples)
    if not ARVIZ_1:
        return _per_coord_0x(az.ess, s, method=method)
    # 1.x's own default tail quantiles follow its credible-interval setting (0.89 / 0.94):
    # ask for Vehtari et al.'s 5 % and 95 % (the 0.2x default)
    return _per_coord_1x("ess", s, method=method, **({"prob": _TAIL_PROBS} if method == "tail" else {}))


def mcse(samples: np.ndarray, method: str = "mean") -> np.ndarray:
    """Monte-Carlo standard error (n,) of the mean or the sd of draws (chains, draws, n)."""
    if method not in ("mean", "sd"):
        raise ValueError(f"mcse method: expected 'mean' or 'sd', found {method!r}")
    s = _draws(samples)
    if ARVIZ_1:
        return _per_coord_1x("mcse", s, method=method)
    with _numba_off():
        return _per_coord_0x(az.mcse, s, method=method)


def bfmi(energy: np.ndarray) -> np.ndarray:
    """E-BFMI (chains,) of the Hamiltonian energy (chains, draws) of NUTS iterations."""
    e = np.asarray(energy, dtype=np.float64)
    if e.ndim != 2 or e.shape[1] < 2:
        raise ValueError(f"energy: expected (chains, draws >= 2), got shape {e.shape}")
    out = _array_stats.bfmi(e, chain_axis=0, draw_axis=1) if ARVIZ_1 else az.bfmi(e)
    return np.asarray(out, dtype=float).reshape(e.shape[0])


def psislw(log_weights: np.ndarray) -> tuple[np.ndarray, float]:
    """(smoothed log weights (S,), normalised, Pareto k̂) of importance log weights (S,)
    (PSIS, r_eff 1). ArviZ's warning for k̂ > 0.7 is silenced: the caller reports k̂. A
    constant tail (e.g. q = p) gives k̂ = inf on both versions (0.2x's answer; 1.x raises)."""
    lw = np.asarray(log_weights, dtype=np.float64).reshape(-1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if not ARVIZ_1:
            lw_s, k = az.psislw(lw)
        else:
            try:  # arviz-stats' psislw takes log-likelihood values (PSIS-LOO's ratios are 1/p): negate
                lw_s, k = _array_stats.psislw(-lw)
            except ValueError as exc:
                if "tail values are the same" not in str(exc):
                    raise
                # a constant tail: 0.2x returns the normalised weights and k̂ = inf; so do we
                lw_s, k = lw - logsumexp(lw), np.inf
    return np.asarray(lw_s, dtype=np.float64).reshape(-1), float(np.asarray(k).reshape(()))


def from_dict(posterior: dict, *, posterior_predictive: dict | None = None, sample_stats: dict | None = None,
              observed_data: dict | None = None, coords: dict | None = None, dims: dict | None = None) -> Any:
    """ArviZ data of arrays (chain, draw, ...) per group (``observed_data`` without chain and
    draw): an ``InferenceData`` (0.2x) or ``xarray.DataTree`` (1.x). Either has the groups
    as attributes (``idata.posterior["x"]``), per-group ``.attrs`` and ``.to_netcdf``."""
    groups = {"posterior": posterior, "posterior_predictive": posterior_predictive,
              "sample_stats": sample_stats, "observed_data": observed_data}
    groups = {k: v for k, v in groups.items() if v is not None}
    with warnings.catch_warnings():
        # one draw (a point method), or emcee's walkers: "More chains than draws" is expected
        warnings.filterwarnings("ignore", message="More chains", category=UserWarning)
        if ARVIZ_1:
            return az.from_dict(groups, coords=coords, dims=dims)
        return az.from_dict(**groups, coords=coords, dims=dims)


def from_netcdf(path) -> Any:
    """Read what :func:`from_dict`'s ``.to_netcdf`` wrote."""
    return az.from_netcdf(str(path))
