"""The one result type of every synthesis path: :class:`SynthesisResult`.

The posterior methods (:func:`bayes_talk.posterior.sampling.sample_synthesis`),
deena2010's Algorithms 1 and 2 (:func:`bayes_talk.synthesis.sequential.synthesize`),
deena2009's SGPLVM (:meth:`bayes_talk.models.sgplvm.SGPLVM.synthesize`) and the baselines
that have a predictive variance all describe the visual prediction of frame t the same
way: a mixture over K = C·S components (C chains of S draws) of Gaussians,

    p(z_td) = (1/K) Σ_k N(z_td; μ_td^k, v_td^k),                                   (1)

with μ^k = μ_Z(x^k) and v^k = σ²_Z(x^k)/w² the visual GP's predictive mean and variance
at latent draw x^k (deena2010 eq. 10 at each draw; docs/uncertainty.md). A point method (MAP,
Algorithms 1–2, SGPLVM, a baseline) is the one-component case K = 1: a single Gaussian.

From (1):

* mean  E[z]   = (1/K) Σ_k μ^k;   var  Var[z] = (1/K) Σ_k v^k + Var_k(μ^k)   (law of total variance);
* cdf   F(y)   = (1/K) Σ_k Φ((y − μ^k)/√v^k);   logpdf  ln p(y) = logsumexp_k ln N(y; μ^k, v^k) − ln K;
* quantile(q)  = F⁻¹(q), solved per entry by Newton's method safeguarded by bisection inside
  the bracket [min_k, max_k] of the components' own q-quantiles (F is monotone; for K = 1
  it is the exact normal quantile μ + √v Φ⁻¹(q));
* interval(level) = (F⁻¹((1 − level)/2), F⁻¹((1 + level)/2)), the central band. These are the
  bands ``synth`` writes (``bands.npz``, ``bands.png``) and ``evaluate`` scores.

:meth:`SynthesisResult.to_inference_data` gives an ArviZ ``InferenceData`` (``posterior``:
the latent draws and μ_Z at each; ``posterior_predictive``: draws of (1); ``sample_stats``
where the sampler has them; ``observed_data`` when the truth is given), which ``synth``
saves as ``posterior.nc``.
"""
from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.special import logsumexp, ndtr, ndtri

from bayes_talk.base.errors import check_level

if TYPE_CHECKING:
    import arviz

    from bayes_talk.synthesis.joint_map import MapResult

__all__ = ["DEFAULT_LEVELS", "PREDICTIVE_DRAWS", "SynthesisResult"]

#: central band levels reported by default (coverage is scored at these)
DEFAULT_LEVELS = (0.5, 0.8, 0.9, 0.95)
#: posterior-predictive draws stored by :meth:`SynthesisResult.to_inference_data` (at least)
PREDICTIVE_DRAWS = 100
_TINY_SD = 1e-150
_Q_TOL = 1e-12


@dataclass
class SynthesisResult:
    """The synthesis of one utterance: the mixture (1) of the module docstring.

    method: how it was made ("map", "laplace", "nuts", "emcee", "optimise" / "predict"
        (deena2010 Algorithms 1 / 2), "sgplvm", or a baseline's name).
    latent_draws: (C, S, T, d) latent draws (C chains of S draws; C = S = 1 for a point
        method), or None when the method has no latent space (the baselines).
    draw_mean, draw_var: (C, S, T, D) the Gaussian components μ^k and v^k of (1).
    map: the joint MAP of the whole-utterance posterior (posterior methods), or None.
    segments / model_states: the segmentation and the state model that synthesised each.
    diagnostics: optimiser and sampler diagnostics (R-hat, ESS, divergences, ...).
    seed: the seed of the run (also seeds :meth:`sample` and the predictive draws).
    seconds: wall time of the synthesis.
    warnings: the failed convergence checks, in words.
    sample_stats: per-draw sampler statistics, each (C, S) (ArviZ names: ``diverging``,
        ``tree_depth``, ``step_size``, ``energy``, ``acceptance_rate``, ``lp``), or
        (C, S, T) per draw and frame (the particle Gibbs sweeps' ``pg_frame_moved``), or empty.
    mean_function: (T, D) the explicit mean function c_t already included in every μ^k
        (``SwitchingConfig.context_mean``: μ^k = c_t + μ_Z(x^k)), or None (zero). The band
        calibration's mean stage shrinks μ^k − c_t, not μ^k.
    """

    method: str
    latent_draws: np.ndarray | None
    draw_mean: np.ndarray
    draw_var: np.ndarray
    map: MapResult | None = None
    segments: list = field(default_factory=list)
    model_states: list = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    seed: int = 0
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)
    sample_stats: dict[str, np.ndarray] = field(default_factory=dict)
    mean_function: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.draw_mean = np.asarray(self.draw_mean, dtype=np.float64)
        self.draw_var = np.asarray(self.draw_var, dtype=np.float64)
        if self.draw_mean.ndim != 4:
            raise ValueError(f"draw_mean: expected shape (chains, draws, T, D), found {self.draw_mean.shape}")
        if self.draw_var.shape != self.draw_mean.shape:
            raise ValueError(f"draw_var: expected shape {self.draw_mean.shape} (that of draw_mean), "
                             f"found {self.draw_var.shape}")
        if not np.all(np.isfinite(self.draw_mean)):
            raise ValueError("draw_mean: expected finite values, found NaN or inf")
        if not np.all(self.draw_var >= 0):  # also rejects NaN
            raise ValueError("draw_var: expected variances >= 0, found a negative or NaN value")
        C, S, T, _ = self.draw_mean.shape
        if self.latent_draws is not None:
            self.latent_draws = np.asarray(self.latent_draws, dtype=np.float64)
            if self.latent_draws.ndim != 4 or self.latent_draws.shape[:3] != (C, S, T):
                raise ValueError(f"latent_draws: expected shape ({C}, {S}, {T}, d), found "
                                 f"{self.latent_draws.shape}")
        if self.mean_function is not None:
            self.mean_function = np.asarray(self.mean_function, dtype=np.float64)
            if self.mean_function.shape != self.draw_mean.shape[2:]:
                raise ValueError(f"mean_function: expected shape {self.draw_mean.shape[2:]}, found "
                                 f"{self.mean_function.shape}")
        for k, v in self.sample_stats.items():
            if np.shape(v) not in ((C, S), (C, S, T)):
                raise ValueError(f"sample_stats[{k!r}]: expected shape ({C}, {S}) or ({C}, {S}, {T}), found "
                                 f"{np.shape(v)}")

    # ------------------------------------------------------------------ constructors
    @classmethod
    def gaussian(cls, mean: np.ndarray, var: np.ndarray, latents: np.ndarray | None = None, *,
                 method: str, segments: list | None = None, model_states: list | None = None,
                 diagnostics: dict | None = None, seed: int = 0, seconds: float = 0.0,
                 mean_function: np.ndarray | None = None) -> SynthesisResult:
        """A point method's result: one Gaussian N(mean, var) per entry (K = 1 in (1)).

        mean, var: (T, D); latents: (T, d) the latent path, or None; mean_function: the
        class docstring's."""
        mean, var = np.asarray(mean, dtype=np.float64), np.asarray(var, dtype=np.float64)
        if mean.ndim != 2:
            raise ValueError(f"mean: expected shape (T, D), found {mean.shape}")
        lat = None
        if latents is not None:
            lat = np.asarray(latents, dtype=np.float64)
            if lat.ndim != 2 or lat.shape[0] != mean.shape[0]:
                raise ValueError(f"latents: expected shape ({mean.shape[0]}, d), found {lat.shape}")
            lat = lat[None, None]
        return cls(method, lat, mean[None, None], np.broadcast_to(var, mean.shape)[None, None], None,
                   list(segments or []), list(model_states or []), dict(diagnostics or {}), int(seed),
                   float(seconds), mean_function=mean_function)

    # ------------------------------------------------------------------ shapes
    @property
    def n_chains(self) -> int:
        return int(self.draw_mean.shape[0])

    @property
    def n_draws(self) -> int:
        """Components K = chains × draws per chain (1 for a point method)."""
        return int(self.draw_mean.shape[0] * self.draw_mean.shape[1])

    @property
    def n_frames(self) -> int:
        return int(self.draw_mean.shape[2])

    @property
    def n_dims(self) -> int:
        """D, the visual (AAM) parameters per frame."""
        return int(self.draw_mean.shape[3])

    @property
    def is_gaussian(self) -> bool:
        """True for a single-Gaussian (point method) result."""
        return self.n_draws == 1

    def _flat(self, a: np.ndarray) -> np.ndarray:
        return a.reshape((-1,) + a.shape[2:])

    # ------------------------------------------------------------------ moments
    @property
    def mean(self) -> np.ndarray:
        """Mixture mean (T, D)."""
        return self._flat(self.draw_mean).mean(0)

    @property
    def var(self) -> np.ndarray:
        """Mixture variance (T, D) = mean of the component variances + variance of their means."""
        return self._flat(self.draw_var).mean(0) + self._flat(self.draw_mean).var(0)

    @property
    def gp_var(self) -> np.ndarray:
        """Average component variance (T, D) (the mixture variance without the spread of the means)."""
        return self._flat(self.draw_var).mean(0)

    @property
    def latents(self) -> np.ndarray | None:
        """The point latent path (T, d): the path of a point method, the joint MAP of a
        posterior method (the draws are in :attr:`latent_draws`); None without latents."""
        if self.map is not None:
            return self.map.latents
        if self.latent_draws is None:
            return None
        return self._flat(self.latent_draws).mean(0)

    @property
    def map_latents(self) -> np.ndarray | None:
        """The joint MAP path (T, d) of a posterior method (None otherwise)."""
        return None if self.map is None else self.map.latents

    @property
    def summary(self) -> dict:
        return self.diagnostics

    # ------------------------------------------------------------------ the mixture
    def _components(self) -> tuple[np.ndarray, np.ndarray]:
        """(K, T, D) component means and standard deviations (floored at a tiny value)."""
        return self._flat(self.draw_mean), np.maximum(np.sqrt(self._flat(self.draw_var)), _TINY_SD)

    def _check_y(self, y: np.ndarray) -> np.ndarray:
        y = np.asarray(y, dtype=np.float64)
        if y.shape != (self.n_frames, self.n_dims):
            raise ValueError(f"expected values of shape ({self.n_frames}, {self.n_dims}), found {y.shape}")
        return y

    def cdf(self, y: np.ndarray) -> np.ndarray:
        """F(y) (T, D): the mixture CDF of each entry at y (T, D) (the PIT values of the truth)."""
        m, s = self._components()
        return ndtr((self._check_y(y)[None] - m) / s).mean(0)

    def logpdf(self, y: np.ndarray) -> np.ndarray:
        """ln p(y) (T, D): the mixture log density of each entry at y (T, D)."""
        m, s = self._components()
        r = (self._check_y(y)[None] - m) / s
        return logsumexp(-0.5 * r * r - np.log(s), axis=0) - 0.5 * math.log(2 * math.pi) - math.log(len(m))

    def quantile(self, q: float) -> np.ndarray:
        """F⁻¹(q) (T, D): the exact mixture quantile of every entry (see the module docstring)."""
        q = check_level(q, "q")
        m, s = self._components()
        z = float(ndtri(q))
        if len(m) == 1:
            return m[0] + s[0] * z
        K = len(m)
        m, s = m.reshape(K, -1), s.reshape(K, -1)
        own = m + s * z                       # each component's own q-quantile
        lo, hi = own.min(0), own.max(0)
        y = np.clip(self.mean.reshape(-1) + np.sqrt(self.var.reshape(-1)) * z, lo, hi)
        act = np.arange(y.size)               # entries not yet converged
        c = 1.0 / math.sqrt(2 * math.pi)
        for _ in range(200):
            ma, sa, ya = m[:, act], s[:, act], y[act]
            r = (ya[None] - ma) / sa
            F = ndtr(r).mean(0)
            f = (np.exp(-0.5 * r * r) / sa).mean(0) * c
            below = F < q
            la, ha = np.where(below, ya, lo[act]), np.where(below, hi[act], ya)
            lo[act], hi[act] = la, ha
            done = (np.abs(F - q) <= _Q_TOL) | (ha - la <= 1e-13 * (1.0 + np.abs(ya)))
            with np.errstate(divide="ignore", invalid="ignore"):
                newton = ya - (F - q) / f
            ok = np.isfinite(newton) & (newton > la) & (newton < ha)
            y[act] = np.where(done, ya, np.where(ok, newton, 0.5 * (la + ha)))
            act = act[~done]
            if act.size == 0:
                break
        return y.reshape(self.n_frames, self.n_dims)

    def interval(self, level: float) -> tuple[np.ndarray, np.ndarray]:
        """The central ``level`` band (lower, upper), each (T, D): F⁻¹((1 ∓ level)/2)."""
        level = check_level(level)
        return self.quantile(0.5 - level / 2), self.quantile(0.5 + level / 2)

    def quantiles(self, levels=DEFAULT_LEVELS, n_samples: int | None = None,
                  seed: int | None = None) -> dict[float, tuple[np.ndarray, np.ndarray]]:
        """Central bands {level: (lower, upper)} (:meth:`interval` at each level; nested).

        ``n_samples`` and ``seed`` are ignored: the bands are exact mixture quantiles, no
        longer estimated from samples (kept so that older calls still run)."""
        if n_samples is not None or seed is not None:
            warnings.warn("SynthesisResult.quantiles: n_samples and seed are ignored (exact mixture "
                          "quantiles)", DeprecationWarning, stacklevel=2)
        levels = [check_level(q) for q in levels]
        return {q: self.interval(q) for q in levels}

    def sample(self, n: int = 2000, seed: int | None = None) -> np.ndarray:
        """n samples (n, T, D) of the mixture (1): component k mod K of a random
        permutation, then its Gaussian. Seeded by ``seed`` (default ``self.seed + 1``)."""
        if int(n) < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        rng = np.random.default_rng(self.seed + 1 if seed is None else seed)
        dm, dv = self._flat(self.draw_mean), self._flat(self.draw_var)
        comp = np.resize(rng.permutation(dm.shape[0]), int(n))
        return dm[comp] + np.sqrt(dv[comp]) * rng.standard_normal((int(n),) + dm.shape[1:])

    def predictive_draws(self, per_component: int = 1, seed: int | None = None) -> np.ndarray:
        """Posterior-predictive draws (C, S·per_component, T, D): ``per_component`` draws of
        each component's Gaussian, kept in its chain (so chain diagnostics still apply)."""
        if int(per_component) < 1:
            raise ValueError(f"per_component must be >= 1, got {per_component}")
        rng = np.random.default_rng(self.seed + 2 if seed is None else seed)
        k = int(per_component)
        m, v = np.repeat(self.draw_mean, k, axis=1), np.repeat(self.draw_var, k, axis=1)
        return m + np.sqrt(v) * rng.standard_normal(m.shape)

    def independent_draws(self, per_component: int = 1, seed: int | None = None) -> np.ndarray:
        """C·S·per_component independent draws of :meth:`sample`'s distribution, shaped like
        :meth:`predictive_draws`' (C, S·per_component, T, D) — for results whose
        distribution is no longer the components' mixture (recalibrated, pooled)."""
        if int(per_component) < 1:
            raise ValueError(f"per_component must be >= 1, got {per_component}")
        C, S = self.draw_mean.shape[:2]
        k = int(per_component)
        y = self.sample(C * S * k, seed=self.seed + 2 if seed is None else seed)
        return y.reshape(C, S * k, self.n_frames, self.n_dims)

    @property
    def draws(self) -> np.ndarray:
        """One posterior-predictive draw per component, (C, S, T, D) (:meth:`predictive_draws`)."""
        return self.predictive_draws(1)

    def shift(self, delta: np.ndarray) -> SynthesisResult:
        """The same result with every component mean moved by delta (T, D), e.g. a post-filter
        of the mean (``lowpass(mean) − mean``): the bands move with it, their widths stay."""
        delta = self._check_y(delta)
        return replace(self, draw_mean=self.draw_mean + delta[None, None], draw_var=self.draw_var.copy())

    # ------------------------------------------------------------------ ArviZ
    def to_inference_data(self, truth: np.ndarray | None = None,
                          n_predictive: int = PREDICTIVE_DRAWS) -> arviz.InferenceData:
        """An ArviZ InferenceData of this result.

        Groups: ``posterior`` — ``latents`` (chain, draw, frame, latent_dim) when the method
        has latents, and ``aam_mean`` / ``aam_gp_var`` (chain, draw, frame, aam_param), the
        components μ^k and v^k of (1) (deterministic functions of the latent draw);
        ``posterior_predictive`` — ``aam``: draws of (1), ⌈n_predictive / K⌉ per component;
        ``sample_stats`` — :attr:`sample_stats` when a sampler recorded them (chain, draw),
        those per frame (chain, draw, frame);
        ``observed_data`` — ``aam``, the truth (T, D), when given. The method, seed,
        diagnostics, warnings and segmentation are attributes of the posterior group
        (JSON strings where not scalars), so they survive ``to_netcdf``.
        """
        from bayes_talk.base.arviz_compat import from_dict

        T, D = self.n_frames, self.n_dims
        coords: dict[str, Any] = {"frame": np.arange(T), "aam_param": np.arange(D)}
        dims = {"aam_mean": ["frame", "aam_param"], "aam_gp_var": ["frame", "aam_param"],
                "aam": ["frame", "aam_param"]}
        posterior = {"aam_mean": self.draw_mean, "aam_gp_var": self.draw_var}
        if self.latent_draws is not None:
            posterior["latents"] = self.latent_draws
            coords["latent_dim"] = np.arange(self.latent_draws.shape[3])
            dims["latents"] = ["frame", "latent_dim"]
        kw: dict[str, Any] = {}
        if truth is not None:
            kw["observed_data"] = {"aam": self._check_y(truth)}
        if self.sample_stats:
            kw["sample_stats"] = {k: np.asarray(v) for k, v in self.sample_stats.items()}
            dims.update({k: ["frame"] for k, v in kw["sample_stats"].items() if v.ndim == 3})
        per = max(1, -(-int(n_predictive) // self.n_draws))
        # (a point method has one draw: the adapter silences ArviZ's "More chains" warning only)
        idata = from_dict(posterior, posterior_predictive={"aam": self.predictive_draws(per)},
                          coords=coords, dims=dims, **kw)
        idata.posterior.attrs.update(self._attrs())
        return idata

    def _attrs(self) -> dict[str, Any]:
        def js(obj: Any) -> str:
            return json.dumps(obj, default=_json_default)

        return {"bayes_talk_method": self.method, "bayes_talk_seed": int(self.seed),
                "bayes_talk_seconds": float(self.seconds), "bayes_talk_n_components": self.n_draws,
                "bayes_talk_diagnostics": js(self.diagnostics), "bayes_talk_warnings": js(list(self.warnings)),
                "bayes_talk_segments": js([{"state": list(s.state), "start": int(s.start), "stop": int(s.stop)}
                                           for s in self.segments]),
                "bayes_talk_model_states": js([list(k) for k in self.model_states])}


def _json_default(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, (np.ndarray, tuple)):
        return np.asarray(o).tolist()
    if isinstance(o, np.bool_):
        return bool(o)
    return str(o)
