"""MCMC diagnostics through ArviZ (DESIGN.md §6) - the only module that imports arviz.

ArviZ is pinned below 0.24 (ArviZ 1.x needs Python >= 3.12); every call to it is here.

:func:`chain_diagnostics` takes draws of shape (chains, draws, n) and returns

* ``rhat_max``: the largest rank-normalised split R-hat over the n coordinates
  (``arviz.rhat(method="rank")``, Vehtari et al. 2021); ``rhat`` per coordinate;
* ``ess_bulk_min`` / ``ess_tail_min`` (and per coordinate ``ess_bulk`` / ``ess_tail``):
  ``arviz.ess(method="bulk" | "tail")``;
* ``n_chains``, ``n_draws``.

With a single chain (Laplace draws) the chain is split in two halves before ArviZ sees it
(ArviZ returns nan R-hat for one chain); ``n_chains`` reports the chains given.
Sampler statistics (divergences, acceptance) are merged in by the caller.
"""
from __future__ import annotations

import warnings

import numpy as np

with warnings.catch_warnings():
    warnings.simplefilter("ignore", FutureWarning)  # arviz 0.2x announces its 1.0 refactor
    import arviz as az

DIAGNOSTIC_KEYS = ("rhat_max", "ess_bulk_min", "ess_tail_min", "n_chains", "n_draws", "rhat", "ess_bulk",
                   "ess_tail")


def chain_diagnostics(samples: np.ndarray) -> dict:
    """Split R-hat and bulk/tail ESS of (chains, draws, n) samples via ArviZ."""
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 3:
        raise ValueError(f"samples: expected (chains, draws, n), got shape {s.shape}")
    C, S, n = s.shape
    if S < 4:
        raise ValueError(f"need at least 4 draws per chain for split R-hat, got {S}")
    if C == 1:  # ArviZ gives nan R-hat for one chain: split it explicitly (what split R-hat does)
        h = S // 2
        s = np.stack([s[0, :h], s[0, h:2 * h]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "more chains than draws": emcee walkers
        idata = az.from_dict(posterior={"x": s})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rhat = np.asarray(az.rhat(idata, var_names=["x"], method="rank")["x"].values, dtype=float).reshape(n)
        bulk = np.asarray(az.ess(idata, var_names=["x"], method="bulk")["x"].values, dtype=float).reshape(n)
        tail = np.asarray(az.ess(idata, var_names=["x"], method="tail")["x"].values, dtype=float).reshape(n)
    return {
        "rhat_max": float(np.nanmax(rhat)),
        "ess_bulk_min": float(np.nanmin(bulk)),
        "ess_tail_min": float(np.nanmin(tail)),
        "n_chains": int(C),
        "n_draws": int(S),
        "rhat": rhat,
        "ess_bulk": bulk,
        "ess_tail": tail,
    }


#: thresholds of :func:`convergence_problems` (Vehtari et al. 2021): rank R-hat at most
#: this, bulk and tail ESS at least ESS_MIN, no divergent transition
RHAT_MAX = 1.01
ESS_MIN = 400.0


def convergence_problems(diag: dict) -> list[str]:
    """The failed checks of a sampler run's diagnostics, in words: R-hat above
    :data:`RHAT_MAX`, bulk or tail ESS below :data:`ESS_MIN`, any divergent transition.
    Only the keys present are checked ([] for a run without chains, e.g. Laplace)."""
    out = []
    r = diag.get("rhat_max")
    if r is not None and (not np.isfinite(r) or r > RHAT_MAX):
        out.append(f"R-hat {r:.3g} > {RHAT_MAX}")
    for key, what in (("ess_bulk_min", "bulk"), ("ess_tail_min", "tail")):
        e = diag.get(key)
        if e is not None and (not np.isfinite(e) or e < ESS_MIN):
            out.append(f"{what} ESS {e:.3g} < {ESS_MIN:g}")
    dv = diag.get("divergences")
    if dv:
        out.append(f"{int(dv)} divergent transitions")
    return out


__all__ = ["DIAGNOSTIC_KEYS", "chain_diagnostics", "convergence_problems"]
