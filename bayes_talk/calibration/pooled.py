"""A linear pool of a synthesis predictive and a constant-variance Gaussian.

Stage 3, the last of the four of :mod:`bayes_talk.calibration.bands`. Per entry (frame t, AAM
parameter d), with P the calibrated posterior predictive (stages 0–2; CDF F_P, density
p_P, mean m_td) and Q_td = N(m_td, v_d) the Gaussian around the same mean with one
variance per parameter (the constant-band control's v_d), the pooled predictive is

    p(y) = (1 − w_d) p_P(y) + w_d N(y; m_td, v_d),      F(y) = (1 − w_d) F_P(y) + w_d Φ((y − m_td)/√v_d),   (4)

a linear opinion pool (Stone 1961) whose weights w_d ∈ [0, 1] are chosen by log score on
held-out data — stacking of predictive distributions (Yao, Vehtari, Simpson & Gelman 2018,
"Using stacking to average Bayesian predictive distributions", eq. 4): the posterior
contributes where its frame-to-frame shape of uncertainty predicts the truth, the constant
band where it does not. What this class answers, and how:

* ``mean``      m_td, exactly (both parts have mean m; the trajectory is unchanged);
* ``var``       (1 − w_d) E_P[(y − m)²] + w_d v_d — exact given P's ``var``;
* ``cdf`` / ``logpdf``   (4), exact given P's;
* ``quantile``  F⁻¹(q) per entry by bisection on (4) between the two parts' own
  q-quantiles (the pooled CDF lies between the two CDFs there), to 1e-10 of the bracket;
  ``interval`` / ``quantiles`` use it;
* ``sample`` / ``predictive_draws`` — each draw takes, per parameter d, its whole
  trajectory from Q with probability w_d and from P otherwise (so a draw from P keeps P's
  frame-to-frame correlation); the marginals are exactly (4);
* ``draw_mean`` / ``draw_var`` and ``to_inference_data``'s posterior group are P's
  components; its posterior-predictive draws are of (4);
* ``shift`` moves P and the Gaussian together.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from scipy.special import ndtr, ndtri

from bayes_talk.base.errors import check_level
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["PooledResult", "check_pool"]

_BISECT_STEPS = 60


def check_pool(weight: np.ndarray, var: np.ndarray, n_dims: int, what: str = "pool") -> tuple[np.ndarray, np.ndarray]:
    """Validated (w (D,), v (D,)): weights in [0, 1] and finite variances > 0 (ValueError
    naming ``what`` otherwise)."""
    w = np.asarray(weight, dtype=np.float64)
    v = np.asarray(var, dtype=np.float64)
    for name, a in (("weight", w), ("var", v)):
        if a.shape != (n_dims,):
            raise ValueError(f"{what}: {name} must have one value per AAM parameter ({n_dims},), found {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what}: {name} contains NaN or inf")
    if not np.all((w >= 0) & (w <= 1)):
        raise ValueError(f"{what}: weights must lie in [0, 1], found values in [{w.min():.6g}, {w.max():.6g}]")
    if not np.all(v > 0):
        raise ValueError(f"{what}: variances must be > 0, found a minimum of {v.min():.6g}")
    return w, v


@dataclass
class PooledResult(SynthesisResult):
    """The pool (4) of ``base`` (P) and N(P's mean, ``pool_var``) with weights ``pool_weight``.

    ``draw_mean``/``draw_var`` are P's components (for the posterior group of
    :meth:`to_inference_data`); the distribution answers are those of (4) (module docstring).
    """

    base: SynthesisResult | None = None
    pool_weight: np.ndarray | None = None
    pool_var: np.ndarray | None = None

    @classmethod
    def pool(cls, base: SynthesisResult, weight: np.ndarray, var: np.ndarray) -> PooledResult:
        """(4) of ``base`` with weights ``weight`` (D,) and Gaussian variances ``var`` (D,)."""
        return cls(**{f.name: getattr(base, f.name) for f in fields(SynthesisResult)},
                   base=base, pool_weight=weight, pool_var=var)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.base is None:
            raise ValueError("PooledResult needs its base predictive (use PooledResult.pool)")
        self.pool_weight, self.pool_var = check_pool(self.pool_weight, self.pool_var, self.n_dims)

    # ------------------------------------------------------------------ the two parts
    @property
    def is_gaussian(self) -> bool:
        """Never a single Gaussian (a pool is a mixture, even with every weight 0 or 1)."""
        return False

    @property
    def mean(self) -> np.ndarray:
        """m_td (T, D), the mean of both parts."""
        return self.base.mean

    @property
    def var(self) -> np.ndarray:
        """(1 − w_d) E_P[(y − m)²] + w_d v_d (T, D)."""
        w = self.pool_weight
        return (1.0 - w) * self.base.var + w * self.pool_var

    def _z(self, y: np.ndarray) -> np.ndarray:
        return (self._check_y(y) - self.base.mean) / np.sqrt(self.pool_var)

    def cdf(self, y: np.ndarray) -> np.ndarray:
        """F(y) of (4) (T, D)."""
        w = self.pool_weight
        return (1.0 - w) * self.base.cdf(y) + w * ndtr(self._z(y))

    def logpdf(self, y: np.ndarray) -> np.ndarray:
        """ln p(y) of (4) (T, D)."""
        w = self.pool_weight
        z = self._z(y)
        lq = -0.5 * z * z - 0.5 * np.log(2 * np.pi * self.pool_var)
        with np.errstate(divide="ignore"):
            return np.logaddexp(np.log1p(-w) + self.base.logpdf(y), np.log(w) + lq)

    def quantile(self, q: float) -> np.ndarray:
        """F⁻¹(q) (T, D) of (4): bisection between the parts' own q-quantiles."""
        q = check_level(q, "q")
        a = self.base.quantile(q)
        b = self.base.mean + np.sqrt(self.pool_var) * float(ndtri(q))
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        for _ in range(_BISECT_STEPS):
            mid = 0.5 * (lo + hi)
            below = self.cdf(mid) < q
            lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
            if np.all(hi - lo <= 1e-10 * (1.0 + np.abs(mid))):
                break
        return 0.5 * (lo + hi)

    def sample(self, n: int = 2000, seed: int | None = None) -> np.ndarray:
        """n draws (n, T, D) of (4): per draw and parameter, the trajectory of Q with
        probability w_d, else that of P (seeded by ``seed``, default ``self.seed + 1``)."""
        if int(n) < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        rng = np.random.default_rng(self.seed + 1 if seed is None else seed)
        n = int(n)
        y = self.base.sample(n, seed=int(rng.integers(2**31)))
        from_q = rng.random((n, 1, self.n_dims)) < self.pool_weight
        g = self.base.mean + np.sqrt(self.pool_var) * rng.standard_normal(y.shape)
        return np.where(from_q, g, y)

    def predictive_draws(self, per_component: int = 1, seed: int | None = None) -> np.ndarray:
        """C·S·per_component independent draws of (4), shaped (C, S·per_component, T, D)."""
        return self.independent_draws(per_component, seed)

    def shift(self, delta: np.ndarray) -> PooledResult:
        """P and the Gaussian moved together by delta (T, D); weights and variances kept."""
        return PooledResult.pool(self.base.shift(delta), self.pool_weight, self.pool_var)
