"""Band calibration fitted on held-out training utterances: four stages per AAM parameter.

The whole-utterance posterior's bands are too narrow on new sentences (their raw coverage
is in docs/results.md): the synthesis posterior is conditional on the trained
hyperparameters and training latents, whose own uncertainty is not propagated, and the GP
noise levels are fitted to training frames. The remedy here has four stages, each per AAM
parameter d, each fitted on held-out training utterances, and applied in this order by
:meth:`BandCalibration.apply`:

0. a **mean shrinkage** a_d of the mixture's component means towards the prediction's
   mean function (0);
1. a **scale** s_d of the whole mixture about its mean (1);
2. a **monotone level map** H_d of the scaled mixture's central levels (quantile
   recalibration; :class:`~bayes_talk.calibration.recalibrated.RecalibratedResult`);
3. a **pool with a constant band** N(m_td, v_d) around the same mean, weight w_d (4)
   (:class:`~bayes_talk.calibration.pooled.PooledResult`).

Stage 1 is always there; stage 0 is off with ``shrink_mean=False``, stage 3 with
``pool=False``, and a file of an older format version may lack stages 0, 2 or 3 (then
they are skipped). A constant-band control, fitted on the same utterances, judges
whether the posterior's shape of uncertainty carries information (below).

**Stage 0, a mean shrinkage.** The posterior mean varies more than the truth does with it
(mode jumps), so each parameter's component means are first pulled towards the explicit
mean function c_td of the prediction (``SynthesisResult.mean_function``; 0 without one) by
the least-squares factor fitted on the held-out entries,

    μ'^k_td = c_td + a_d (μ^k_td − c_td),   a_d = clip(Σ (m − c)(y − c) / Σ (m − c)², 0, 1),   (0)

(sums over held-out frames; m the mixture mean, y the truth), so a part of the mean that
does not predict the truth is shrunk away and one that does is kept.

**Stage 1, a scale.** One factor s_d applied to the whole predictive mixture about its
mean m_td,

    z' = m_td + s_d (z − m_td):   μ'^k_td = m_td + s_d (μ^k_td − m_td),   v'^k_td = s_d² v^k_td,   (1)

an affine map of the mixture, so its mean is unchanged, its standard deviation and every
central band's half-widths are multiplied by s_d, and samples, quantiles, CDF and density
of the scaled result follow exactly (it is again a
:class:`~bayes_talk.synthesis.result.SynthesisResult`).

**Fitting s_d** (:meth:`BandCalibration.fit`). For each held-out entry with truth y,
mixture mean m and raw central band [l_q, u_q] at level q, the smallest scale whose band
(1) contains y is

    s*_q = (y − m)/(u_q − m)  if y > m,   (m − y)/(m − l_q)  if y < m,   0 if y = m,

so the calibrated coverage at level q is the empirical CDF of s*_q at s_d, exactly, with
no re-synthesis. s_d minimises Σ_q (cov_q(s) − q)² over q ∈ {0.5, 0.8, 0.9, 0.95} on a log
grid of s in [1/8, 8] (the middle of the minimising set when it is flat).

**Stage 2, a monotone level map** (quantile recalibration, Kuleshov et al. 2018). One
factor per parameter cannot fix a wrong *shape*: with errors heavier-tailed than the
mixture, the 50 % band wants a smaller factor than the 90 % band. So the scaled
mixture's central level of each held-out truth, c = |2F_s(y) − 1| (the smallest level
whose scaled band contains y), is collected per parameter, and H_d, its empirical
distribution function made piecewise linear through the knots (r_dj, q_j) — r_dj the
empirical q_j-quantile of c for q_j ∈ ``LEVEL_KNOTS`` = 0.05, 0.10, …, 0.95, and (0, 0),
(1, 1) — maps levels: the calibrated central q-band is the scaled mixture's central
H_d⁻¹(q)-band, so on the held-out data it covers q at every knot (up to ties). As a
distribution, F' = G_d ∘ F_s with G_d(u) = ½ + ½ sgn(u − ½) H_d(|2u − 1|):
:class:`~bayes_talk.calibration.recalibrated.RecalibratedResult` (its docstring says
which of its answers are exact and which approximated). Beyond the last knot the map is
linear to (1, 1), so the scaled mixture's own tail shape is kept there: stage 1 brings
the outer bands close first, so this last piece stays near the identity. Without a level
map (``level_raw`` None, a version-1 file) stage 2 is skipped. The in-sample coverage of
the raw predictive and after stages 0–2 is stored beside the knots.

**Where the held-out utterances come from** (:func:`fit_band_calibration`): a seeded
``holdout`` fraction (default 20 %) of the *training* utterances; a second model of the
same configuration is trained on the other 80 %, the held-out ones are synthesised by
the posterior method, and the factors are fitted to them. The factors are then applied
to the model trained on all utterances. Cost: one extra fit (on 80 % of the data) and
the synthesis of the held-out utterances; the state models' own training residuals are
in-sample (too small by construction). The full model has seen 25 % more data than the
calibration model; measured on new sentences the calibrated bands are still slightly
narrow (docs/uncertainty.md).

**Cross-fitted** (:func:`crossfit_band_calibration`, ``train --calibrated-model cv``): the
utterances are split into K = round(1/holdout) seeded folds (5 at the default 20 %); for
each fold a model of the same configuration is trained on the other folds and the fold is
synthesised by it, so every training utterance is held out once, and the factors are
fitted to all of these out-of-fold syntheses (cross-conformal calibration, Vovk 2015;
CV+, Barber, Candès, Ramdas & Tibshirani 2021, with utterances as the exchangeable unit).
K fits instead of one, and K times the held-out data for every stage.

**The constant-band control.** Whether the posterior's *shape* of
uncertainty — wider where the face is harder to predict — carries information is judged
against a control fitted on the same held-out utterances: the calibrated predictive's mean
(after stage 0) with one constant variance per parameter, v_d = mean over held-out entries
of (y − m)², and that Gaussian then calibrated by stages 1–2 exactly as above
(``control``, no mean stage). A posterior whose NLPD and CRPS do not beat this control
says no more about its uncertainty than a constant band would.
:meth:`BandCalibration.control_result` builds it for a new prediction.

**Stage 3, a pool with the constant band.** The calibrated predictive P of
stages 0–2 is pooled with the Gaussian Q_td = N(m_td, v_d) around its own mean (v_d the
control's variance above),

    p'(y) = (1 − w_d) p_P(y) + w_d N(y; m_td, v_d),                                   (4)

with w_d ∈ [0, 1] per parameter maximising the held-out log score Σ ln p'(y) — stacking
of predictive distributions (Yao et al. 2018), concave in w_d, so the best of the grid
w ∈ {0, 0.01, …, 1} is taken. The posterior keeps the weight where its frame-to-frame
shape of uncertainty predicts the truth; where it does not, the constant band takes it
over. The mean (the trajectory) is unchanged.
:class:`~bayes_talk.calibration.pooled.PooledResult` is the result type (its
docstring says how each answer is computed). The weights are fitted on the same held-out
utterances as stages 0–2 (in-sample for those stages); without ``pool_weight`` (a file of
version ≤ 4, or ``pool=False``) the calibration ends at stage 2.

Saved with the model as ``band_calibration.json`` (:meth:`BandCalibration.save`;
``bayes-talk train --calibrate-bands``), applied by ``synth`` to the posterior method it
was fitted on, and reported calibrated and raw side by side by ``evaluate``.

This module stays above ~400 lines because :class:`BandCalibration` is one object: its
four stages, the control and the validated-domain check (:meth:`BandCalibration.domain`)
are fitted from the same held-out syntheses and saved in one file; about a quarter of the
lines is the mathematics above.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from bayes_talk.base.files import write_json
from bayes_talk.calibration.pooled import PooledResult, check_pool
from bayes_talk.calibration.recalibrated import RecalibratedResult, check_level_map
from bayes_talk.posterior.diagnostics import (
    convergence_problems,
    is_sampler_warning,
    sampler_warning,
)
from bayes_talk.synthesis.result import DEFAULT_LEVELS, SynthesisResult

__all__ = ["CALIBRATED_MODELS", "CALIBRATION_FILE", "HOLDOUT_FRACTION", "LEVEL_KNOTS", "POOL_GRID", "BandCalibration", "calibrated_fit", "crossfit_band_calibration", "crossfit_folds", "fit_band_calibration", "holdout_calibrated_model",
           "mean_shrinkage", "min_scales",
           "split_for_calibration"]

log = logging.getLogger(__name__)

CALIBRATION_FILE = "band_calibration.json"
_FORMAT = "bayes_talk.band_calibration"
_VERSION = 5
_READS = (1, 2, 3, 4, 5)
#: default fraction of the training utterances held out to fit the calibration
HOLDOUT_FRACTION = 0.2
_GRID = np.exp(np.linspace(math.log(1 / 8), math.log(8), 2001))
#: calibrated central levels q_j of the level map's knots (stage 2)
LEVEL_KNOTS: tuple[float, ...] = tuple(np.round(np.arange(1, 20) * 0.05, 2))
_KNOT_EPS = 1e-9
#: the weights w of stage 3 searched (the held-out log score is concave in each w_d)
POOL_GRID = np.round(np.linspace(0.0, 1.0, 101), 2)


def min_scales(result: SynthesisResult, truth: np.ndarray, levels: Sequence[float] = DEFAULT_LEVELS
               ) -> np.ndarray:
    """s*_q (L, T, D): the smallest scale (1) whose central band at each level contains the
    truth (T, D) (inf where no scale does: a band that does not reach past the mean)."""
    y = np.asarray(truth, dtype=np.float64)
    m = result.mean
    if y.shape != m.shape:
        raise ValueError(f"truth: expected shape {m.shape} (the prediction's), found {y.shape}")
    out = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for q in levels:
            lo, hi = result.interval(q)
            up = np.where(hi > m, (y - m) / (hi - m), np.inf)
            down = np.where(lo < m, (m - y) / (m - lo), np.inf)
            out.append(np.where(y > m, up, np.where(y < m, down, 0.0)))
    return np.asarray(out)


def _mean_function(result: SynthesisResult) -> np.ndarray | float:
    """c_t of the result's explicit mean function, or 0."""
    return 0.0 if result.mean_function is None else result.mean_function


def _shrunk(result: SynthesisResult, a: np.ndarray) -> SynthesisResult:
    """Stage 0 (0): every component mean's part beyond the mean function c_t multiplied by
    a_d, μ' = c + a_d (μ − c) (c = 0 without one), variances kept."""
    c = _mean_function(result)
    return replace(result, draw_mean=c + (result.draw_mean - c) * a)


def mean_shrinkage(results: Sequence[SynthesisResult], truths: Sequence[np.ndarray]) -> np.ndarray:
    """a_d of (0) (D,) from held-out predictions and their truths (both taken relative to
    the predictions' mean function c_t, where they have one)."""
    m = np.concatenate([r.mean - _mean_function(r) for r in results])
    y = np.concatenate([np.asarray(z, dtype=np.float64) - _mean_function(r) for z, r in zip(truths, results)])
    if m.shape != y.shape:
        raise ValueError(f"truths: expected frames of shape {m.shape} (the predictions'), found {y.shape}")
    den = np.sum(m * m, axis=0)
    return np.clip(np.where(den > 0, np.sum(m * y, axis=0) / np.where(den > 0, den, 1.0), 1.0), 0.0, 1.0)


def _constant_band(result: SynthesisResult, var: np.ndarray) -> SynthesisResult:
    """N(mixture mean of ``result``, var_d) per entry: the constant-band control's predictive."""
    return SynthesisResult.gaussian(result.mean, np.broadcast_to(var, result.mean.shape).copy(),
                                    method=f"{result.method}-control", seed=result.seed)


def _coverage_at(s_star: np.ndarray, scale: np.ndarray | float) -> np.ndarray:
    """(L,) coverage at each level of bands scaled by ``scale`` (per last axis)."""
    return np.mean(s_star <= scale, axis=tuple(range(1, s_star.ndim)))


def _scaled(result: SynthesisResult, scale: np.ndarray) -> SynthesisResult:
    """The mixture scaled by (1) about its mean."""
    m = result.mean[None, None]
    return replace(result, draw_mean=m + scale * (result.draw_mean - m), draw_var=result.draw_var * scale * scale)


@dataclass
class BandCalibration:
    """The stages (module docstring) of one synthesis method's band calibration.

    scale: (D,) factors s_d (stage 1); mean_scale: (D,) factors a_d (stage 0; None: none,
    e.g. a file of version ≤ 2); level_raw: (D, J) raw central levels r_dj of the
    level map's knots (stage 2; None: stage 1 alone) and level_cal: (J,) their calibrated
    levels q_j; method: the synthesis method they were fitted on ("laplace", ...);
    levels: the levels reported; n_utterances / n_frames: the held-out data;
    coverage_raw / coverage_calibrated: {level: pooled coverage} on that data before and
    after stages 0–2 (in-sample); pool_weight: (D,) weights w_d of stage 3 (None: no pool);
    control_var / control: the constant-band control; held_out: the held-out utterance names; info: how it was made
    (hold-out fraction, seed, draws).
    """

    scale: np.ndarray
    method: str
    levels: tuple[float, ...] = tuple(DEFAULT_LEVELS)
    level_raw: np.ndarray | None = None
    level_cal: tuple[float, ...] = LEVEL_KNOTS
    n_utterances: int = 0
    n_frames: int = 0
    coverage_raw: dict[str, float] = field(default_factory=dict)
    coverage_calibrated: dict[str, float] = field(default_factory=dict)
    held_out: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    mean_scale: np.ndarray | None = None
    control_var: np.ndarray | None = None
    control: BandCalibration | None = None
    pool_weight: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.scale = np.asarray(self.scale, dtype=np.float64)
        if self.mean_scale is not None:
            self.mean_scale = np.asarray(self.mean_scale, dtype=np.float64)
            if self.mean_scale.shape != self.scale.shape or not np.all(
                    np.isfinite(self.mean_scale) & (self.mean_scale >= 0) & (self.mean_scale <= 1)):
                raise ValueError(f"mean_scale: expected {self.scale.size} factors in [0, 1], found "
                                 f"{self.mean_scale.tolist() if self.mean_scale.size < 8 else self.mean_scale.shape}")
        if self.scale.ndim != 1 or self.scale.size == 0:
            raise ValueError(f"scale: expected a non-empty 1-D array (one factor per AAM parameter), "
                             f"found shape {self.scale.shape}")
        if not np.all(np.isfinite(self.scale) & (self.scale > 0)):
            raise ValueError("scale: expected finite factors > 0")
        if self.control_var is not None:
            self.control_var = np.asarray(self.control_var, dtype=np.float64)
            if self.control_var.shape != self.scale.shape or not np.all(
                    np.isfinite(self.control_var) & (self.control_var > 0)):
                raise ValueError(f"control_var: expected {self.scale.size} finite variances > 0")
        if self.pool_weight is not None:
            if self.control_var is None:
                raise ValueError("pool_weight: the pool (stage 3) needs control_var, the Gaussian's variances")
            self.pool_weight, _ = check_pool(self.pool_weight, self.control_var, self.scale.size, "band calibration")
        self.levels = tuple(float(q) for q in self.levels)
        if self.level_raw is not None:
            raw, cal = check_level_map(self.level_raw, self.level_cal, self.scale.size, "band calibration")
            self.level_raw, self.level_cal = raw, tuple(float(q) for q in cal)

    # ------------------------------------------------------------------ fit / apply
    @classmethod
    def fit(cls, results: Sequence[SynthesisResult], truths: Sequence[np.ndarray], method: str | None = None,
            levels: Sequence[float] = DEFAULT_LEVELS, per_parameter: bool = True,
            names: Sequence[str] = (), shrink_mean: bool = True, with_control: bool = True,
            pool: bool = True) -> BandCalibration:
        """Fit a_d (``shrink_mean``), s_d and the level map on held-out predictions
        ``results`` and their truths (each (T_i, D)). per_parameter=False fits one factor and
        one map for all parameters (pooled). ``with_control``: also fit the constant-band
        control; ``pool`` (needs ``with_control``): also the weights of stage 3 (module
        docstring)."""
        if not results or len(results) != len(truths):
            raise ValueError(f"fit: need one truth per result and at least one, got {len(results)} results "
                             f"and {len(truths)} truths")
        levels = tuple(float(q) for q in levels)
        raw = _coverage_at(np.concatenate([min_scales(r, z, levels) for r, z in zip(results, truths)], axis=1), 1.0)
        a = mean_shrinkage(results, truths) if shrink_mean else None
        if a is not None:
            results = [_shrunk(r, a) for r in results]
        s_star = np.concatenate([min_scales(r, z, levels) for r, z in zip(results, truths)], axis=1)  # (L, N, D)
        L, N, D = s_star.shape
        target = np.asarray(levels)[:, None]
        cols = [s_star.reshape(L, -1)] if not per_parameter else [s_star[:, :, d] for d in range(D)]
        scale = []
        for col in cols:
            srt = np.sort(col, axis=1)
            cov = np.stack([np.searchsorted(srt[j], _GRID, side="right") for j in range(L)]) / srt.shape[1]
            loss = np.sum((cov - target) ** 2, axis=0)
            best = np.flatnonzero(loss <= loss.min() + 1e-12)
            scale.append(float(_GRID[best[len(best) // 2]]))
        scale = np.full(D, scale[0]) if not per_parameter else np.asarray(scale)
        # stage 2: central levels c = |2 F_s(y) - 1| of the truths under the scaled mixtures
        c = np.concatenate([np.abs(2.0 * _scaled(r, scale).cdf(z) - 1.0) for r, z in zip(results, truths)])
        knots = np.asarray(LEVEL_KNOTS)
        J = knots.size
        pooled = c.reshape(-1, 1) if not per_parameter else c
        r_dj = np.quantile(pooled, knots, axis=0).T                      # (D or 1, J)
        r_dj = np.clip(r_dj, _KNOT_EPS, 1.0 - (J + 1) * _KNOT_EPS)
        r_dj = np.maximum.accumulate(r_dj + _KNOT_EPS * np.arange(J), axis=1)   # strictly increasing
        r_dj = np.broadcast_to(r_dj, (D, J)).copy()
        cal = [np.mean(c <= np.array([np.interp(q, np.r_[0, knots, 1], np.r_[0, r_dj[d], 1]) for d in range(D)]))
               for q in levels]
        meth = method if method is not None else results[0].method
        control_var = control = None
        if with_control:
            resid = np.concatenate([np.asarray(z, np.float64) - r.mean for r, z in zip(results, truths)])
            control_var = np.maximum(np.mean(resid ** 2, axis=0), 1e-12)
            control = cls.fit([_constant_band(r, control_var) for r in results], truths, method=f"{meth}-control",
                              levels=levels, per_parameter=per_parameter, shrink_mean=False, with_control=False)
        out = cls(scale, meth, levels, r_dj, LEVEL_KNOTS, len(results), int(N),
                  {f"{q:g}": float(v) for q, v in zip(levels, raw)},
                  {f"{q:g}": float(v) for q, v in zip(levels, cal)}, list(names),
                  {"per_parameter": bool(per_parameter),
                   "coverage_scaled": {f"{q:g}": float(v) for q, v in zip(levels, _coverage_at(s_star, scale))}},
                  a, control_var, control)
        if pool and with_control:
            # results are already shrunk (stage 0): apply stages 1-2 only, then score (4) per w
            out.pool_weight, out.info["pool_log_score"] = _fit_pool(
                [replace(out, mean_scale=None).apply(r) for r in results], truths, control_var)
        return out

    def control_result(self, result: SynthesisResult) -> SynthesisResult:
        """The constant-band control for the raw prediction ``result``: the calibrated mean
        (stage 0 applied) with the constant variances ``control_var``, calibrated by
        ``control`` (module docstring). ValueError when this calibration has no control."""
        if self.control is None or self.control_var is None:
            raise ValueError("this band calibration has no constant-band control (fitted with "
                             "with_control=False, or saved by a version before 4)")
        if result.n_dims != self.scale.size:
            raise ValueError(f"band calibration has {self.scale.size} factors but the prediction has "
                             f"{result.n_dims} AAM parameters: it belongs to another model")
        if self.mean_scale is not None:
            result = _shrunk(result, self.mean_scale)
        return self.control.apply(_constant_band(result, self.control_var))

    @property
    def calibration_khat_max(self) -> float | None:
        """The largest PSIS k̂ among the held-out syntheses the calibration was fitted on
        (``info["held_out_diagnostics"]``), or None when none was recorded. Reported beside
        a new utterance's k̂; not a gate (:meth:`domain`)."""
        return held_out_khat_max(self.info)

    def domain(self, result: SynthesisResult) -> dict[str, Any]:
        """Whether the calibrated predictive of ``result`` can be trusted — the criterion of
        its convergence warning (docs/uncertainty.md "When synth warns").

        A calibrated band's coverage rests on the held-out utterances it was fitted on, not
        on the approximation being exact: the Laplace (or VI) k̂ of the whole-utterance
        posterior is above 0.7 on every utterance (0.9–3.5 measured; the posterior is
        multimodal), and the calibration was fitted on exactly such posteriors. Measured on
        held-out sentences (``benchmarks/khat_coverage.py``; docs/uncertainty.md), the k̂
        does not predict where the
        calibrated bands fail: Spearman ρ −0.05 between k̂ and |coverage₉₀ − 0.9| over 24
        utterances; the 5 whose k̂ exceeded every held-out training k̂ covered 0.891 at 90 %,
        the other 19 0.894; with white noise at 0 dB SNR k̂ rose to 2.7–3.5 and coverage
        stayed 0.85–0.92. So the k̂ is recorded (with :attr:`calibration_khat_max` beside
        it) but gates the calibrated result only when it is not finite (a numerical
        breakdown); every other check of
        :func:`~bayes_talk.posterior.diagnostics.convergence_problems` (MAP convergence,
        R-hat, ESS, divergences, E-BFMI of the samplers) stands. The raw result
        (``calibrated=False``) keeps the k̂ ≤ 0.7 check. Returns the k̂, the calibration's
        largest k̂, whether the result is trusted, and the warning ([] when it is)."""
        return held_out_domain(result, self.info)

    def audio_fit(self, result: SynthesisResult) -> dict[str, Any]:
        """How well the model explains this utterance against the held-out utterances the
        calibration was fitted on — recorded, not gated (docs/uncertainty.md "When synth
        warns": to be validated before it gates).

        ``map_log_density_per_frame`` ℓ = ln p(X̂, audio) / T at the MAP, and the conformal
        p-value p = (1 + #{i : ℓ_i ≤ ℓ}) / (n + 1) of ℓ among the n held-out ℓ_i
        (``info["held_out_diagnostics"]["map_log_density_per_frame"]``; calibrations saved
        without it give None): small when the utterance is explained worse than (nearly) every
        utterance whose coverage the calibration measured; under exchangeable utterances
        P(p ≤ α) ≤ α. None where either is missing."""
        return held_out_audio_fit(result, self.info)

    def apply(self, result: SynthesisResult) -> SynthesisResult:
        """The calibrated result: (0) and (1) applied to every component, then the level map (a
        :class:`~bayes_talk.calibration.recalibrated.RecalibratedResult`; without one,
        the scaled mixture itself), then the pool (4) (a
        :class:`~bayes_talk.calibration.pooled.PooledResult`; without weights, stage 2's
        result). The factors are recorded in its diagnostics under
        ``band_calibration``, with the raw level of its 90 % band (median over parameters)
        and the :meth:`domain` check, whose warning replaces the raw result's sampler warning."""
        if result.n_dims != self.scale.size:
            raise ValueError(f"band calibration has {self.scale.size} factors but the prediction has "
                             f"{result.n_dims} AAM parameters: it belongs to another model")
        s = self.scale
        diag = dict(result.diagnostics)
        diag["band_calibration"] = {"method": self.method, "scale_min": float(s.min()),
                                    "scale_median": float(np.median(s)), "scale_max": float(s.max()),
                                    "level_map": self.level_raw is not None,
                                    "mean_scale_min": None if self.mean_scale is None else float(self.mean_scale.min())}
        diag["band_calibration"]["domain"] = dom = self.domain(result)
        warn = [w for w in result.warnings if not is_sampler_warning(result.method, w)] + dom["warning"]
        if self.mean_scale is not None:
            result = _shrunk(result, self.mean_scale)
        scaled = replace(_scaled(result, s), diagnostics=diag, warnings=warn)
        if self.level_raw is not None:
            knots = np.r_[0.0, self.level_cal, 1.0]
            diag["band_calibration"]["raw_level_of_90_median"] = float(np.median(
                [np.interp(0.9, knots, np.r_[0.0, r, 1.0]) for r in self.level_raw]))
            scaled = RecalibratedResult(**{f.name: getattr(scaled, f.name) for f in fields(SynthesisResult)},
                                        level_raw=self.level_raw, level_cal=np.asarray(self.level_cal))
        if self.pool_weight is None:
            return scaled
        diag["band_calibration"]["pool_weight_median"] = float(np.median(self.pool_weight))
        return PooledResult.pool(scaled, self.pool_weight, self.control_var)

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (format, version, method, levels, factors, fit information)."""
        return {"format": _FORMAT, "version": _VERSION, "method": self.method, "levels": list(self.levels),
                "scale": self.scale.tolist(), "level_cal": list(self.level_cal),
                "level_raw": None if self.level_raw is None else self.level_raw.tolist(), "n_utterances": self.n_utterances, "n_frames": self.n_frames,
                "coverage_raw": self.coverage_raw, "coverage_calibrated": self.coverage_calibrated,
                "held_out": list(self.held_out), "info": self.info,
                "mean_scale": None if self.mean_scale is None else self.mean_scale.tolist(),
                "control_var": None if self.control_var is None else self.control_var.tolist(),
                "control": None if self.control is None else self.control.to_dict(),
                "pool_weight": None if self.pool_weight is None else self.pool_weight.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "band calibration") -> BandCalibration:
        """The calibration saved by :meth:`to_dict` (ValueError naming ``where`` if malformed)."""
        if not isinstance(d, dict) or d.get("format") != _FORMAT:
            raise ValueError(f"{where}: expected format {_FORMAT!r}, found "
                             f"{d.get('format') if isinstance(d, dict) else type(d).__name__!r}")
        if d.get("version") not in _READS:
            raise ValueError(f"{where}: format version {d.get('version')!r}; this bayes_talk reads "
                             f"{', '.join(map(str, _READS))}")
        try:
            raw = d.get("level_raw") if d["version"] >= 2 else None
            return cls(np.asarray(d["scale"], dtype=np.float64), str(d["method"]), tuple(d["levels"]),
                       None if raw is None else np.asarray(raw, dtype=np.float64),
                       tuple(d["level_cal"]) if raw is not None else LEVEL_KNOTS, int(d["n_utterances"]), int(d["n_frames"]), dict(d["coverage_raw"]),
                       dict(d["coverage_calibrated"]), list(d["held_out"]), dict(d.get("info", {})),
                       None if d.get("mean_scale") is None else np.asarray(d["mean_scale"], dtype=np.float64),
                       None if d.get("control_var") is None else np.asarray(d["control_var"], dtype=np.float64),
                       None if d.get("control") is None else cls.from_dict(d["control"], where=f"{where}, control"),
                       None if d.get("pool_weight") is None else np.asarray(d["pool_weight"], dtype=np.float64))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: incomplete or invalid band calibration ({exc})") from None

    def save(self, directory: str | Path) -> Path:
        """Write ``band_calibration.json`` into ``directory`` (atomically)."""
        return write_json(Path(directory) / CALIBRATION_FILE, self.to_dict())

    @classmethod
    def load(cls, directory: str | Path) -> BandCalibration | None:
        """The calibration saved in ``directory``, or None when there is none."""
        import json

        p = Path(directory) / CALIBRATION_FILE
        if not p.is_file():
            return None
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{p}: unreadable band calibration ({exc})") from None
        return cls.from_dict(d, where=str(p))


def held_out_khat_max(info: dict[str, Any]) -> float | None:
    """The largest PSIS k̂ among the held-out syntheses a calibration (or the face's
    observation term) was fitted on (``info["held_out_diagnostics"]["khat"]``), or None."""
    ks = [k for k in info.get("held_out_diagnostics", {}).get("khat", []) if k is not None]
    return max(ks) if ks else None


def held_out_audio_fit(result: SynthesisResult, info: dict[str, Any]) -> dict[str, Any]:
    """The MAP log density per frame of ``result`` and its conformal p-value among the
    held-out syntheses recorded in ``info`` (:meth:`BandCalibration.audio_fit`)."""
    lp = result.diagnostics.get("map_log_density")
    ell = float(lp) / result.n_frames if isinstance(lp, (int, float)) and math.isfinite(lp) else None
    ref = [v for v in info.get("held_out_diagnostics", {}).get("map_log_density_per_frame", []) if v is not None]
    p = None if ell is None or not ref else (1 + sum(v <= ell for v in ref)) / (len(ref) + 1)
    return {"map_log_density_per_frame": ell, "audio_fit_p": p}


def held_out_domain(result: SynthesisResult, info: dict[str, Any]) -> dict[str, Any]:
    """Whether a predictive whose width was fitted on held-out syntheses (``info``: the band
    calibration's or the observation term's) can be trusted: the criterion of
    :meth:`BandCalibration.domain` — the k̂ is recorded, not gated (the held-out syntheses had
    such k̂ too), unless it is not finite; every other convergence check stands."""
    d = dict(result.diagnostics)
    k = d.pop("khat", None)
    fails = convergence_problems(d)
    if k is not None and not np.isfinite(k):
        fails.append(f"PSIS k̂ {k} is not finite (the importance weights broke down numerically)")
    return {"khat": k, "khat_calibration_max": held_out_khat_max(info), **held_out_audio_fit(result, info),
            "inside": not fails, "warning": sampler_warning(result.method, fails)}


def _fit_pool(calibrated: Sequence[SynthesisResult], truths: Sequence[np.ndarray], var: np.ndarray
              ) -> tuple[np.ndarray, list[float]]:
    """Stage 3: per parameter, the w of :data:`POOL_GRID` with the best held-out log score of
    (4) between the calibrated predictives and N(their mean, var_d); returns (w (D,), the
    mean log score per parameter at w)."""
    lp = np.concatenate([r.logpdf(z) for r, z in zip(calibrated, truths)])            # (N, D)
    y = np.concatenate([np.asarray(z, np.float64) for z in truths])
    m = np.concatenate([r.mean for r in calibrated])
    lq = -0.5 * (y - m) ** 2 / var - 0.5 * np.log(2 * np.pi * var)
    w = POOL_GRID[:, None, None]
    with np.errstate(divide="ignore"):
        score = np.mean(np.logaddexp(np.log1p(-w) + lp[None], np.log(w) + lq[None]), axis=1)   # (G, D)
    best = np.argmax(score, axis=0)
    return POOL_GRID[best].astype(np.float64), [float(score[b, d]) for d, b in enumerate(best)]


def _synthesis_record(results: Sequence[SynthesisResult]) -> dict[str, Any]:
    """What the held-out syntheses said about themselves (their warnings are not logged while
    the calibration is fitted, so they are kept here): per utterance the MAP's convergence,
    the PSIS k̂ (Laplace) or the largest R-hat (samplers) where reported, the MAP's log
    density per frame (how well the model explains the utterance: a reference for a domain
    check, docs/uncertainty.md "When synth warns"), and the number of results that carried a
    convergence warning."""
    def num(d: dict, key: str) -> float | None:
        v = d.get(key)
        return float(v) if isinstance(v, (int, float)) and math.isfinite(float(v)) else None

    diags = [r.diagnostics for r in results]
    return {"map_converged": [bool(d["map_converged"]) if "map_converged" in d else None for d in diags],
            "khat": [num(d, "khat") for d in diags], "rhat_max": [num(d, "rhat_max") for d in diags],
            "map_log_density_per_frame": [None if num(d, "map_log_density") is None
                                          else num(d, "map_log_density") / r.n_frames
                                          for d, r in zip(diags, results)],
            "n_with_warnings": int(sum(bool(r.warnings) for r in results)), "n": len(results)}


def split_for_calibration(n: int, holdout: float = HOLDOUT_FRACTION, seed: int = 0) -> tuple[list[int], list[int]]:
    """(fit indices, held-out indices) of ``n`` utterances: a seeded ``holdout`` fraction
    (at least one) is held out, at least two are left to fit on."""
    if not 0.0 < holdout < 1.0:
        raise ValueError(f"holdout: expected a fraction in (0, 1), found {holdout!r}")
    n_hold = max(1, round(holdout * n))
    if n - n_hold < 2:
        raise ValueError(f"band calibration needs at least 3 training utterances (2 to fit, 1 held out); "
                         f"found {n}")
    held = sorted(int(i) for i in np.random.default_rng([seed, 2**17]).choice(n, n_hold, replace=False))
    hs = set(held)
    return [i for i in range(n) if i not in hs], held


#: held-out syntheses per worker process when the calibration's syntheses run in parallel
#: (chunks balanced by frame count: more chunks balance the load, each costs one copy of the model)
SYNTHESIS_CHUNKS_PER_WORKER = 3


def balanced_chunks(sizes: Sequence[int], n_chunks: int) -> list[list[int]]:
    """Indices 0..len(sizes)−1 in ``n_chunks`` non-empty chunks of about equal total size:
    longest-processing-time-first (Graham 1969), each item, largest first (ties by index),
    to the chunk with the least total so far (the lowest-numbered among equals). The chunks
    come largest total first (a pool that hands tasks to idle workers then ends them
    together) and each lists its indices in increasing order. Deterministic: the same sizes
    give the same chunks."""
    n = len(sizes)
    if n_chunks < 1 or n_chunks > n:
        raise ValueError(f"balanced_chunks: n_chunks must be in 1..{n} (one item each at least); found {n_chunks}")
    order = sorted(range(n), key=lambda i: (-int(sizes[i]), i))
    loads, chunks = [0] * n_chunks, [[] for _ in range(n_chunks)]
    for i in order:
        k = min(range(n_chunks), key=lambda c: (loads[c], c))
        chunks[k].append(i)
        loads[k] += int(sizes[i])
    by_load = sorted(range(n_chunks), key=lambda c: (-loads[c], c))
    return [sorted(chunks[c]) for c in by_load]


def _synthesise_chunk(job: tuple) -> list[SynthesisResult]:
    """The posterior syntheses of one chunk of held-out utterances (a module-level function,
    so that process pools can pickle it)."""
    from bayes_talk.posterior.sampling import sample_synthesis

    model, utterances, method, n_draws, seed = job
    return [sample_synthesis(model, mfcc, labels, method=method, n_draws=n_draws, seed=seed, log_warnings=False)
            for mfcc, labels in utterances]


def fit_band_calibration(model, train: Sequence, method: str = "laplace", holdout: float = HOLDOUT_FRACTION,
                         n_draws: int = 64, seed: int = 0, executor=None,
                         progress: Callable[[str], None] | None = None,
                         fit: Callable | None = None) -> BandCalibration:
    """Fit the calibration of a switching model's ``method`` posterior on held-out
    training utterances (module docstring): a model of ``model``'s configuration is
    trained on the other utterances of ``train`` (through ``executor`` as
    ``SwitchingSGPDM.fit``), the held-out ones are synthesised with ``n_draws`` draws
    (seed ``seed``) and the factors fitted to their AAM parameters. ``fit(model, utterances)``
    replaces the training call (e.g. the CLI's, with its progress bar and process pool).

    The calibration is then applied to ``model`` (trained on all of ``train``: the
    ``"refit"`` scheme of :data:`CALIBRATED_MODELS`); :func:`holdout_calibrated_model` returns
    the model it was fitted for instead.

    When ``executor`` runs tasks in other processes (its ``parallel`` is true) the held-out
    syntheses go through it too, in chunks balanced by frame count (the model is sent once per chunk);
    each synthesis is seeded and single-threaded either way, so the calibration does not
    depend on the executor."""
    return holdout_calibrated_model(model, train, method, holdout, n_draws, seed, executor, progress, fit)[1]


#: which model a band calibration is shipped with (``train --calibrated-model``):
#: "holdout" -- the model trained on the other utterances, the one the calibration was
#: fitted for (split-conformal: its held-out coverage is the shipped model's, and there is
#: one fit in all); "refit" -- a second model trained on all the utterances, the factors
#: carried over to it (a model that has seen 1/(1 − holdout) times the data, but whose
#: calibration was fitted on another model's errors; two fits); "cv" -- the model trained on
#: all the utterances, the calibration fitted on out-of-fold syntheses of every one of them
#: (cross-fitted, K = round(1/holdout) folds: K + 1 fits)
CALIBRATED_MODELS = ("holdout", "refit", "cv")
#: what is fitted on the held-out training utterances (``train --calibration``): "noise", the
#: face's observation term inside the model (bayes_talk.synthesis.face_noise, fitted by
#: bayes_talk.calibration.noise_fit; the default); "bands", this module's post-hoc four-stage
#: band calibration, wrapped around the model (bayes_talk.estimators.calibrated.BandCalibrated)
CALIBRATIONS = ("noise", "bands")


def calibrated_fit(model, train: Sequence, calibrated_model: str, method: str = "laplace",
                   holdout: float = HOLDOUT_FRACTION, n_draws: int = 64, seed: int = 0, executor=None,
                   progress: Callable[[str], None] | None = None,
                   fit: Callable | None = None, fitter: Callable | None = None) -> tuple[Any, Any]:
    """(the model to ship, its calibration) by the scheme ``calibrated_model`` of
    :data:`CALIBRATED_MODELS`: "holdout", :func:`holdout_calibrated_model` (one fit); "refit",
    ``model`` fitted on all of ``train`` and :func:`fit_band_calibration` for it (two fits);
    "cv", the same model and :func:`crossfit_band_calibration` (K + 1 fits).
    The other arguments as :func:`fit_band_calibration`'s. ``train`` and ``demo`` call this.
    With "refit" and no ``fit``, the two fits and the syntheses share the executor's queue
    (:func:`refit_beside_calibration`; without workers they run one after another in this
    process, with the same results). ``fitter(results, held)``: what is fitted on the held-out
    syntheses ``results`` of the utterances ``held`` (default: :meth:`BandCalibration.fit`;
    the face's observation term: :func:`bayes_talk.calibration.noise_fit.held_out_fitter`)."""
    if calibrated_model not in CALIBRATED_MODELS:
        raise ValueError(f"calibrated_model: expected one of {', '.join(CALIBRATED_MODELS)}, found {calibrated_model!r}")
    if calibrated_model == "refit" and fit is None:
        return refit_beside_calibration(model, train, method, holdout, n_draws, seed, executor, progress, fitter)
    if fit is None:   # through the executor, with a progress bar of the states
        def fit(m, utterances):
            from bayes_talk.base.progress import ProgressMapper
            return m.fit(utterances, executor=ProgressMapper(executor, "training states", "state"))
    kw = {"method": method, "holdout": holdout, "n_draws": n_draws, "seed": seed, "executor": executor,
          "progress": progress, "fit": fit, "fitter": fitter}
    if calibrated_model == "holdout":
        return holdout_calibrated_model(model, train, **kw)
    fitted = fit(model, list(train))
    if calibrated_model == "cv":
        return fitted, crossfit_band_calibration(fitted, train, **kw)
    return fitted, holdout_calibrated_model(fitted, train, **kw)[1]


def holdout_calibrated_model(model, train: Sequence, method: str = "laplace", holdout: float = HOLDOUT_FRACTION,
                             n_draws: int = 64, seed: int = 0, executor=None,
                             progress: Callable[[str], None] | None = None,
                             fit: Callable | None = None, fitter: Callable | None = None) -> tuple[Any, Any]:
    """(the fitted model, its calibration): ``model``'s configuration trained on the
    utterances of ``train`` outside the seeded ``holdout`` fraction, and the calibration of
    its ``method`` posterior fitted on the held-out ones (see :func:`fit_band_calibration`
    for the arguments). ``model`` itself is only read for its configuration."""
    seqs, fit_idx, held_idx, sub, say = _calibration_split(model, train, holdout, seed, progress)
    rest = [seqs[i] for i in fit_idx]
    sub = fit(sub, rest) if fit is not None else sub.fit(rest, executor=executor)
    results = _held_out_syntheses(sub, [seqs[i] for i in held_idx], method, n_draws, seed, executor, say)
    return sub, _holdout_calibration(results, [seqs[i] for i in held_idx], method, holdout, n_draws, seed,
                                     len(fit_idx), say, fitter)


def _calibration_split(model, train: Sequence, holdout: float, seed: int, progress: Callable[[str], None] | None,
                       also: str = "") -> tuple[list, list[int], list[int], Any, Callable[[str], None]]:
    """(the utterances, fit indices, held-out indices, an unfitted model of ``model``'s
    configuration, the progress function) of a held-out calibration, the split announced."""
    from bayes_talk.models.switching import SwitchingModel

    if not isinstance(model, SwitchingModel):
        raise TypeError(f"band calibration needs a switching SGPDM, found {type(model).__name__}")
    seqs = list(train)
    fit_idx, held_idx = split_for_calibration(len(seqs), holdout, seed)
    say = progress or (lambda msg: log.info("%s", msg))
    say(f"band calibration: training a {model.name} model on {len(fit_idx)} utterances, "
        f"holding out {len(held_idx)}{also}")
    return seqs, fit_idx, held_idx, type(model)(**asdict(model.config)), say


def _holdout_calibration(results: Sequence[SynthesisResult], held: Sequence, method: str, holdout: float,
                         n_draws: int, seed: int, n_fit: int, say: Callable[[str], None],
                         fitter: Callable | None = None) -> Any:
    """The calibration (``fitter``'s; default :meth:`BandCalibration.fit`) fitted on the
    syntheses ``results`` of the held-out utterances ``held``, with what it was fitted on
    recorded in its ``info``."""
    if fitter is None:
        cal = BandCalibration.fit(results, [s.aam for s in held], method=method, names=[s.name for s in held])
    else:
        cal = fitter(results, held)
    cal.info.update(holdout=float(holdout), seed=int(seed), n_draws=int(n_draws), n_fit=n_fit, method=method,
                    held_out_diagnostics=_synthesis_record(results))
    _say_fitted(cal, say)
    return cal


def refit_beside_calibration(model, train: Sequence, method: str = "laplace", holdout: float = HOLDOUT_FRACTION,
                             n_draws: int = 64, seed: int = 0, executor=None,
                             progress: Callable[[str], None] | None = None,
                             fitter: Callable | None = None) -> tuple[Any, Any]:
    """The "refit" scheme of :func:`calibrated_fit` (``model`` fitted on all of ``train``, and
    :func:`fit_band_calibration` for it) with the executor's workers kept busy.

    Done one after the other, the two fits and the syntheses each end with a worker idle
    while the last task of the phase runs, and each fit's serial part (views, state model,
    :meth:`~bayes_talk.models.switching.SwitchingModel.plan_fit`) with both idle. Here they
    form one queue: the calibration model's state fits go to the workers first; this process
    plans the shipped model meanwhile and queues its state fits behind them; when the
    calibration model's states are back its held-out syntheses are queued behind the shipped
    model's states. Every task is the one the sequential scheme runs (the same seeds, one
    thread each), so the model and the calibration are the sequential scheme's. Without an
    executor (None) or on one without workers the tasks run in this process, each when its
    result is first asked for (:meth:`bayes_talk.base.executor.Executor.submit`)."""
    from bayes_talk.base.executor import LocalExecutor
    from bayes_talk.base.progress import bar
    from bayes_talk.models.switching import fit_state

    executor = executor if executor is not None else LocalExecutor()

    seqs, fit_idx, held_idx, sub, say = _calibration_split(model, train, holdout, seed, progress,
                                                           f"; the model on all {len(train)} beside it")
    sub_plan = sub.plan_fit([seqs[i] for i in fit_idx])
    sub_states = [executor.submit(fit_state, job) for job in sub_plan.jobs]
    plan = model.plan_fit(seqs)
    states = [executor.submit(fit_state, job) for job in plan.jobs]
    sub.finish_fit(sub_plan, [p.result() for p in bar(sub_states, len(sub_states),
                                                      "training states (calibration model)", "state")])
    held = [seqs[i] for i in held_idx]
    syntheses = _start_held_out_syntheses(sub, held, method, n_draws, seed, executor, say)
    model.finish_fit(plan, [p.result() for p in bar(states, len(states), "training states", "state")])
    return model, _holdout_calibration(syntheses(), held, method, holdout, n_draws, seed, len(fit_idx), say, fitter)


def _say_fitted(cal: Any, say: Callable[[str], None]) -> None:
    if not isinstance(cal, BandCalibration):
        say(f"{cal.describe()}")
        return
    say("band calibration: 90 % coverage on the held-out utterances {:.3f} raw -> {:.3f} calibrated; "
        "factors {:.2f}-{:.2f} (median {:.2f})".format(cal.coverage_raw.get("0.9", float("nan")),
                                                      cal.coverage_calibrated.get("0.9", float("nan")),
                                                      cal.scale.min(), cal.scale.max(), np.median(cal.scale)))


def crossfit_folds(n: int, holdout: float = HOLDOUT_FRACTION, seed: int = 0) -> list[list[int]]:
    """The K = round(1/``holdout``) seeded folds (sorted index lists, sizes differing by at
    most one) of ``n`` utterances that :func:`crossfit_band_calibration` holds out in turn."""
    if not 0.0 < holdout < 1.0:
        raise ValueError(f"holdout: expected a fraction in (0, 1), found {holdout!r}")
    k = max(2, round(1.0 / holdout))
    if n < k + 1:
        raise ValueError(f"cross-fitted band calibration with {k} folds needs at least {k + 1} training "
                         f"utterances; found {n}")
    perm = np.random.default_rng([seed, 2**17]).permutation(n)
    return [sorted(int(i) for i in f) for f in np.array_split(perm, k)]


def crossfit_band_calibration(model, train: Sequence, method: str = "laplace", holdout: float = HOLDOUT_FRACTION,
                              n_draws: int = 64, seed: int = 0, executor=None,
                              progress: Callable[[str], None] | None = None,
                              fit: Callable | None = None, fitter: Callable | None = None) -> Any:
    """The calibration of ``method`` posteriors fitted on out-of-fold syntheses of every
    training utterance (module docstring, "Cross-fitted"): for each fold of
    :func:`crossfit_folds`, a model of ``model``'s configuration trained on the other folds
    synthesises the fold. Arguments as :func:`fit_band_calibration`; ``model`` is only read
    for its configuration (the shipped model is fitted on all of ``train`` by the caller)."""
    from bayes_talk.models.switching import SwitchingModel

    if not isinstance(model, SwitchingModel):
        raise TypeError(f"band calibration needs a switching SGPDM, found {type(model).__name__}")
    seqs = list(train)
    folds = crossfit_folds(len(seqs), holdout, seed)
    say = progress or (lambda msg: log.info("%s", msg))
    results, order = [], []
    for k, held in enumerate(folds):
        held_set = set(held)
        rest = [s for i, s in enumerate(seqs) if i not in held_set]
        say(f"band calibration: fold {k + 1}/{len(folds)}: training a {model.name} model on {len(rest)} "
            f"utterances, holding out {len(held)}")
        sub = type(model)(**asdict(model.config))
        sub = fit(sub, rest) if fit is not None else sub.fit(rest, executor=executor)
        results += _held_out_syntheses(sub, [seqs[i] for i in held], method, n_draws, seed, executor, say)
        order += held
    held_all = [seqs[i] for i in order]
    cal = (BandCalibration.fit(results, [s.aam for s in held_all], method=method, names=[s.name for s in held_all])
           if fitter is None else fitter(results, held_all))
    cal.info.update(holdout=float(holdout), folds=len(folds), seed=int(seed), n_draws=int(n_draws),
                    n_fit=[len(seqs) - len(f) for f in folds], held_out_diagnostics=_synthesis_record(results))
    _say_fitted(cal, say)
    return cal


def _held_out_syntheses(sub, held: Sequence, method: str, n_draws: int, seed: int, executor,
                        say: Callable[[str], None]) -> list[SynthesisResult]:
    """The ``method`` posteriors of the held-out utterances ``held`` under the model ``sub``
    (seeded, warnings recorded and not logged), through ``executor`` when it runs tasks in
    other processes, in chunks of about equal frame count (:func:`balanced_chunks`; a
    synthesis's cost grows with its frames), the results in the order of ``held``."""
    return _start_held_out_syntheses(sub, held, method, n_draws, seed, executor, say)()


def _start_held_out_syntheses(sub, held: Sequence, method: str, n_draws: int, seed: int, executor,
                              say: Callable[[str], None]) -> Callable[[], list[SynthesisResult]]:
    """:func:`_held_out_syntheses` in two steps: on an executor with workers the chunks are
    queued now and the returned function waits for them; otherwise the returned function
    computes them here, one after another."""
    from bayes_talk.posterior.sampling import sample_synthesis

    if getattr(executor, "parallel", False) and len(held) > 1:
        n_chunks = min(len(held), SYNTHESIS_CHUNKS_PER_WORKER * max(1, int(getattr(executor, "n_workers", 2))))
        chunks = balanced_chunks([len(s.mfcc) for s in held], n_chunks)
        jobs = [(sub, [(held[i].mfcc, held[i].labels) for i in c], method, n_draws, seed) for c in chunks]
        say(f"band calibration: synthesising {len(held)} held-out utterances in {len(jobs)} tasks")
        pending = [executor.submit(_synthesise_chunk, job) for job in jobs]

        def collect() -> list[SynthesisResult]:
            by_index = {i: r for c, p in zip(chunks, pending) for i, r in zip(c, p.result())}
            return [by_index[i] for i in range(len(held))]
        return collect

    def serial() -> list[SynthesisResult]:
        results = []
        for j, s in enumerate(held):
            results.append(sample_synthesis(sub, s.mfcc, s.labels, method=method, n_draws=n_draws, seed=seed,
                                            log_warnings=False))
            if (j + 1) % 10 == 0 or j + 1 == len(held):
                say(f"band calibration: synthesised {j + 1}/{len(held)} held-out utterances")
        return results
    return serial
