"""Rank tests with power for simulation-based calibration, and thinning to the ESS.

SBC (Talts et al. 2018, Theorem 1): the rank r ∈ {0..L} of the truth among L posterior draws
is uniform for every coordinate when the sampler is exact. The per-coordinate χ² test with
Holm's correction (:func:`bayes_talk.evaluation.sbc.uniformity_test`) is a test against every
departure in every coordinate separately; against the departure that matters most — a
posterior uniformly too narrow or too wide — it has little power (measured on a conjugate
Gaussian, 24 coordinates, L = 19, 200 simulations, 40 repeats: a sampler with 0.85× the true
spread is rejected by it in 80 % of the repeats, by the dispersion test below in all of them;
``benchmarks/sbc_power.py``). Two directed tests
pool the coordinates of each simulation, so they use the whole rank matrix, and stay valid
whatever the dependence between a simulation's coordinates (the simulations are independent):

* :func:`dispersion_test` - with u = (r + ½)/(L + 1), the per-simulation statistic
  D_n = (1/K) Σ_k |2u_{nk} − 1| has, under uniform ranks, the exact mean
  m_L = (1/(L + 1)) Σ_{r=0}^{L} |2(r + ½)/(L + 1) − 1|, which is ½ for L + 1 even and
  ½ (1 − 1/(L + 1)²) for L + 1 odd. A too-narrow posterior puts the truth at the extremes (D_n > m_L on average), a
  too-wide one in the middle; one-sample Student t-test of D_1..D_N against m_L, two-sided.
* :func:`bias_test` - B_n = (1/K) Σ_k (2u_{nk} − 1), mean 0 under uniform ranks; t-test.
* :func:`combined_verdict` - calibration passes when none of the three tests (χ² Holm, the
  dispersion and the bias test) rejects at level α/3 (Bonferroni over the three: family-wise
  level ≤ α).

MCMC draws are autocorrelated; ranks among consecutive draws are not uniform even for an
exact sampler (Talts et al. §4.1: ∪-shaped). :func:`thin_to_ess` keeps L evenly spaced draws
of the pooled chains and reports the smallest bulk ESS (ArviZ, rank-normalised; Vehtari et
al. 2021), so that "ranked draws ≤ ESS" can be checked per simulation; the spacing is then at
least the integrated autocorrelation time.
"""
from __future__ import annotations

import numpy as np
import scipy.stats

from bayes_talk.base import arviz_compat as azc

#: family-wise level shared by the three tests of :func:`combined_verdict`
ALPHA = 0.05


def _u(ranks: np.ndarray, n_draws: int) -> np.ndarray:
    r = np.asarray(ranks)
    if r.ndim != 2:
        raise ValueError(f"ranks: expected (simulations, coordinates), got shape {r.shape}")
    if r.shape[0] < 10:
        raise ValueError(f"ranks: at least 10 simulations needed for a t-test, got {r.shape[0]}")
    if np.any(r < 0) or np.any(r > n_draws):
        raise ValueError(f"ranks must lie in 0..{n_draws} (n_draws), found {r.min()}..{r.max()}")
    return (r + 0.5) / (n_draws + 1)


def null_dispersion(n_draws: int) -> float:
    """m_L: E|2u − 1| for a rank uniform on {0..L}, u = (r + ½)/(L + 1)."""
    r = np.arange(n_draws + 1)
    return float(np.mean(np.abs(2 * (r + 0.5) / (n_draws + 1) - 1)))


def _ttest(v: np.ndarray, mean0: float) -> tuple[float, float]:
    if np.all(v == v[0]):
        return (0.0, 1.0) if v[0] == mean0 else (float(np.sign(v[0] - mean0) * np.inf), 0.0)
    res = scipy.stats.ttest_1samp(v, mean0)
    return float(res.statistic), float(res.pvalue)


def dispersion_test(ranks: np.ndarray, n_draws: int) -> tuple[float, float]:
    """(t, p): two-sided t-test of the per-simulation dispersion D_n against m_L (module
    docstring). t > 0: the truth falls at the extremes (posterior too narrow); t < 0: too wide."""
    u = _u(ranks, n_draws)
    return _ttest(np.abs(2 * u - 1).mean(1), null_dispersion(n_draws))


def bias_test(ranks: np.ndarray, n_draws: int) -> tuple[float, float]:
    """(t, p): two-sided t-test of the per-simulation mean of 2u − 1 against 0. t > 0: the
    truth lies above the posterior draws too often (the posterior sits too low)."""
    u = _u(ranks, n_draws)
    return _ttest((2 * u - 1).mean(1), 0.0)


def combined_verdict(ranks: np.ndarray, n_draws: int, chi2_p_adjusted: np.ndarray, alpha: float = ALPHA) -> dict:
    """The three tests of the module docstring at level α/3 each: ``passed`` and each test's
    statistic, p-value and rejection. ``chi2_p_adjusted``: the Holm-adjusted per-coordinate
    p-values of the χ² uniformity test (:func:`bayes_talk.evaluation.sbc.uniformity_test`)."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    a = alpha / 3
    t_d, p_d = dispersion_test(ranks, n_draws)
    t_b, p_b = bias_test(ranks, n_draws)
    p_chi = float(np.min(chi2_p_adjusted))
    rej = {"chi2_holm": p_chi < a, "dispersion": p_d < a, "bias": p_b < a}
    return {"passed": not any(rej.values()), "alpha": alpha, "level_each": a, "rejected": rej,
            "chi2_min_p_adjusted": p_chi, "dispersion_t": t_d, "dispersion_p": p_d,
            "dispersion_mean": float(np.abs(2 * _u(ranks, n_draws) - 1).mean()),
            "dispersion_null": null_dispersion(n_draws), "bias_t": t_b, "bias_p": p_b}


def thin_to_ess(samples: np.ndarray, n_draws: int) -> tuple[np.ndarray, float]:
    """``n_draws`` (L) evenly spaced draws (L, K) of the pooled chains ``samples`` (chains, M, K)
    and the smallest bulk ESS over the K coordinates: "ranked draws ≤ ESS" holds when
    L ≤ that ESS."""
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 3:
        raise ValueError(f"samples: expected (chains, draws, coordinates), got shape {s.shape}")
    flat = s.reshape(-1, s.shape[2])
    if len(flat) < n_draws:
        raise ValueError(f"need at least n_draws = {n_draws} pooled draws to thin, got {len(flat)}")
    if s.shape[0] == 1:   # one chain: split in halves, as split R-hat / ESS do
        h = s.shape[1] // 2
        s = np.stack([s[0, :h], s[0, h:2 * h]])
    ess = float(np.nanmin(azc.ess(s, "bulk")))
    return flat[np.linspace(0, len(flat) - 1, n_draws).round().astype(int)], ess


__all__ = ["ALPHA", "bias_test", "combined_verdict", "dispersion_test", "null_dispersion", "thin_to_ess"]
