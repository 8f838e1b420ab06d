"""A synthesis result whose bands were recalibrated by a monotone level map.

Stage 2 of the four of :mod:`bayes_talk.calibration.bands`. Start from the mixture
(1) of :mod:`bayes_talk.synthesis.result` (already mean-shrunk and scaled per parameter by
stages 0 and 1),
with CDF F and density p per entry (frame t, AAM parameter d). The central level of a
value y is the smallest level whose central band contains it,

    c(y) = |2F(y) − 1|                                                             (2)

(y lies in the central r-band [F⁻¹((1−r)/2), F⁻¹((1+r)/2)] iff c(y) ≤ r). For a calibrated
predictive c(truth) is uniform on [0, 1]. Quantile recalibration (Kuleshov, Fenner &
Ermon 2018, "Accurate uncertainties for deep learning using calibrated regression",
§3), here symmetric about the median and per AAM parameter: H_d is the distribution
function of c(truth) on held-out data, made continuous and strictly increasing by linear
interpolation through knots (r_dj, q_j), j = 1..J, with (0, 0) and (1, 1) added (r_dj: the
empirical q_j-quantile of c(truth) for parameter d). The recalibrated predictive is

    F'(y) = G_d(F(y)),   G_d(u) = ½ + ½ sgn(u − ½) H_d(|2u − 1|),                   (3)

a distribution whose central q-band is the mixture's central H_d⁻¹(q)-band. What this
class answers, and how:

* ``cdf``      F'(y) = G_d(F(y)) — exact;
* ``logpdf``   ln p'(y) = ln p(y) + ln H_d'(c(y)) — exact (H_d' is piecewise constant:
  the slope of the knot interval holding c(y); d/dy of (3) is ½ H_d'(c)·2p(y));
* ``quantile`` F'⁻¹(τ) = F⁻¹(G_d⁻¹(τ)) — exact (the mixture quantile at the per-parameter
  level G_d⁻¹(τ), solved column by column), and so are ``interval`` / ``quantiles``;
* ``mean``     the mixture mean m (the point prediction, unchanged by the calibration).
  (3) keeps the median of every entry; the mean too when the entry's mixture is
  symmetric about m (a Gaussian, or a mixture of components placed symmetrically) —
  otherwise the recalibrated mean ∫ y dF' differs from m, and ``mean`` is then m, not it;
* ``var``      E'[(y − m)²] = ∫ (F⁻¹(Φ(z)) − m)² H_d'(c) φ(z) dz (u = Φ(z), c = |2u − 1|),
  the second moment of (3) about m (its variance when its mean is m) — approximated: the
  trapezoid rule on z ∈ [−8, 8] step 0.05, with F⁻¹(Φ(z)) interpolated linearly in z
  between exact mixture quantiles at z = −6, −5.75, …, 6 (extrapolated linearly beyond;
  a Gaussian's quantile is exactly linear in z);
* ``sample`` / ``predictive_draws`` / ``draws`` — inverse-transform draws y = F'⁻¹(U),
  U uniform, with F⁻¹ interpolated in z as for ``var`` (approximate only through that
  interpolation). The draws are independent draws of (3); the chain dimension of
  ``predictive_draws`` no longer follows the sampler's chains;
* ``draw_mean`` / ``draw_var`` and ``to_inference_data``'s posterior group are the
  mixture's components (after stages 0 and 1); its posterior-predictive draws are of (3).

``shift`` (a post-filter of the mean) moves F and F' together, the map staying.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri

from bayes_talk.base.errors import check_level
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["RecalibratedResult", "check_level_map"]

#: normal scores z of the exact mixture quantiles F⁻¹(Φ(z)) that ``var`` and ``sample`` interpolate
_Z_GRID = np.linspace(-6.0, 6.0, 49)
#: trapezoid nodes of ``var``
_Z_QUAD = np.linspace(-8.0, 8.0, 321)
_SAMPLE_BLOCK = 256


def check_level_map(level_raw: np.ndarray, level_cal: np.ndarray, n_dims: int | None = None,
                    what: str = "level map") -> tuple[np.ndarray, np.ndarray]:
    """Validated knots: ``level_cal`` (J,) calibrated central levels and ``level_raw`` (D, J)
    the raw central levels of each parameter, each finite, strictly increasing, in (0, 1)
    (ValueError naming ``what`` and the problem otherwise)."""
    q = np.asarray(level_cal, dtype=np.float64)
    r = np.asarray(level_raw, dtype=np.float64)
    if q.ndim != 1 or q.size == 0:
        raise ValueError(f"{what}: level_cal must be a non-empty 1-D list of levels, found shape {q.shape}")
    if r.ndim != 2 or r.shape[1] != q.size or (n_dims is not None and r.shape[0] != n_dims):
        want = f"({n_dims if n_dims is not None else 'D'}, {q.size})"
        raise ValueError(f"{what}: level_raw must have shape {want} (parameters × knots), found {r.shape}")
    for name, a in (("level_cal", q), ("level_raw", r)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what}: {name} contains NaN or inf")
        if not np.all((a > 0) & (a < 1)):
            raise ValueError(f"{what}: {name} must lie in (0, 1), found values in "
                             f"[{a.min():.6g}, {a.max():.6g}]")
        if not np.all(np.diff(a, axis=-1) > 0):
            raise ValueError(f"{what}: {name} must be strictly increasing along the knots")
    return r, q


@dataclass
class RecalibratedResult(SynthesisResult):
    """A :class:`SynthesisResult` recalibrated by the level map (3) (module docstring).

    ``draw_mean``/``draw_var``: the mixture (1) the map acts on; ``level_raw`` (D, J) and
    ``level_cal`` (J,): the knots (r_dj, q_j) of H_d.
    """

    level_raw: np.ndarray | None = None
    level_cal: np.ndarray | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.level_raw is None or self.level_cal is None:
            raise ValueError("RecalibratedResult needs level_raw and level_cal (the level map's knots)")
        self.level_raw, self.level_cal = check_level_map(self.level_raw, self.level_cal, self.n_dims)
        D = self.n_dims
        self._xs = np.hstack([np.zeros((D, 1)), self.level_raw, np.ones((D, 1))])   # (D, J + 2)
        self._ys = np.concatenate([[0.0], self.level_cal, [1.0]])                  # (J + 2,)
        self._slope = np.diff(self._ys)[None] / np.diff(self._xs, axis=1)           # (D, J + 1)
        self._mix: SynthesisResult | None = None
        self._cols: list[SynthesisResult] | None = None
        self._grid: np.ndarray | None = None

    # ------------------------------------------------------------------ the map
    @property
    def mixture(self) -> SynthesisResult:
        """The mixture (1) before the level map (a plain :class:`SynthesisResult`)."""
        if self._mix is None:
            self._mix = SynthesisResult(self.method, None, self.draw_mean, self.draw_var, seed=self.seed)
        return self._mix

    def _per_dim(self, fn, a: np.ndarray) -> np.ndarray:
        out = np.empty_like(a)
        for d in range(self.n_dims):
            out[..., d] = fn(d, a[..., d])
        return out

    def _G(self, u: np.ndarray, inverse: bool = False) -> np.ndarray:
        """G_d(u) of (3) (or G_d⁻¹) per last axis."""
        c = np.abs(2.0 * u - 1.0)
        if inverse:
            h = self._per_dim(lambda d, x: np.interp(x, self._ys, self._xs[d]), c)
        else:
            h = self._per_dim(lambda d, x: np.interp(x, self._xs[d], self._ys), c)
        return 0.5 + 0.5 * np.sign(u - 0.5) * h

    def _log_slope(self, u: np.ndarray) -> np.ndarray:
        """ln H_d'(|2u − 1|) per last axis."""
        c = np.abs(2.0 * u - 1.0)
        J1 = self._slope.shape[1]

        def one(d, x):
            k = np.clip(np.searchsorted(self._xs[d], x, side="right") - 1, 0, J1 - 1)
            return np.log(self._slope[d, k])
        return self._per_dim(one, c)

    # ------------------------------------------------------------------ exact parts
    @property
    def is_gaussian(self) -> bool:
        """Never a single Gaussian (the map changes the shape)."""
        return False

    def cdf(self, y: np.ndarray) -> np.ndarray:
        """F'(y) = G_d(F(y)) (T, D)."""
        return self._G(self.mixture.cdf(y))

    def logpdf(self, y: np.ndarray) -> np.ndarray:
        """ln p'(y) = ln p(y) + ln H_d'(c(y)) (T, D)."""
        return self.mixture.logpdf(y) + self._log_slope(self.mixture.cdf(y))

    def quantile(self, q: float) -> np.ndarray:
        """F'⁻¹(q) = F⁻¹(G_d⁻¹(q)) (T, D), the mixture quantile at each parameter's level."""
        q = check_level(q, "q")
        levels = self._G(np.full(self.n_dims, q), inverse=True)
        if self._cols is None:
            self._cols = [SynthesisResult(self.method, None, np.ascontiguousarray(self.draw_mean[..., d:d + 1]),
                                          np.ascontiguousarray(self.draw_var[..., d:d + 1]))
                          for d in range(self.n_dims)]
        return np.hstack([col.quantile(float(np.clip(v, 1e-300, 1 - 1e-16)))
                          for col, v in zip(self._cols, levels)])

    # ------------------------------------------------------------------ interpolated parts
    def _quantile_at_scores(self, z: np.ndarray) -> np.ndarray:
        """F⁻¹(Φ(z)) for normal scores z (..., T, D), interpolated linearly in z between the
        exact mixture quantiles at ``_Z_GRID`` (extrapolated linearly beyond)."""
        if self._grid is None:
            self._grid = np.stack([self.mixture.quantile(float(ndtr(g))) for g in _Z_GRID])   # (G, T, D)
        G = _Z_GRID.size
        k = np.clip(np.searchsorted(_Z_GRID, z, side="right") - 1, 0, G - 2)
        w = (z - _Z_GRID[k]) / (_Z_GRID[k + 1] - _Z_GRID[k])
        t = np.arange(self.n_frames)[:, None]
        d = np.arange(self.n_dims)[None, :]
        lo, hi = self._grid[k, t, d], self._grid[k + 1, t, d]
        return lo + w * (hi - lo)

    @property
    def var(self) -> np.ndarray:
        """E'[(y − m)²] (T, D) about the mixture mean m (module docstring: trapezoid rule)."""
        z = _Z_QUAD[:, None, None] * np.ones((1, self.n_frames, self.n_dims))
        u = ndtr(z)
        f = (self._quantile_at_scores(z) - self.mean[None]) ** 2 * np.exp(self._log_slope(u))
        f *= np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)
        return np.trapezoid(f, _Z_QUAD, axis=0)

    def sample(self, n: int = 2000, seed: int | None = None) -> np.ndarray:
        """n draws (n, T, D) of (3): y = F⁻¹(G_d⁻¹(U)), U uniform (seeded by ``seed``,
        default ``self.seed + 1``)."""
        if int(n) < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        rng = np.random.default_rng(self.seed + 1 if seed is None else seed)
        out = np.empty((int(n), self.n_frames, self.n_dims))
        for i in range(0, int(n), _SAMPLE_BLOCK):
            u = self._G(rng.random((min(_SAMPLE_BLOCK, int(n) - i), self.n_frames, self.n_dims)), inverse=True)
            out[i:i + len(u)] = self._quantile_at_scores(ndtri(np.clip(u, 1e-300, 1 - 1e-16)))
        return out

    def predictive_draws(self, per_component: int = 1, seed: int | None = None) -> np.ndarray:
        """C·S·per_component independent draws of (3), shaped (C, S·per_component, T, D)."""
        return self.independent_draws(per_component, seed)
