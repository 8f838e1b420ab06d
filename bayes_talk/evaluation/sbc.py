"""Simulation-based calibration (Talts, Betancourt, Simpson, Vehtari & Gelman 2018) of the
synthesis posterior (docs/uncertainty.md).

If θ̃ ~ p(θ), ỹ ~ p(y | θ̃) and θ_1..θ_L are draws of the posterior p(θ | ỹ), then the rank
of θ̃ among the θ_l, r = #{l : θ_l < θ̃} ∈ {0, …, L}, is uniform on {0, …, L} for every
scalar function of θ — whatever the prior and the data — exactly when the sampler draws
from the true posterior (Talts et al. 2018, Theorem 1). A sampler whose posterior is too
narrow puts the truth at the extremes too often (a ∪-shaped rank histogram), too wide in
the middle (∩), biased on one side.

* :func:`ranks` - the rank statistic of each coordinate.
* :func:`uniformity_test` - per coordinate, Pearson's χ² test of the rank histogram
  (B bins, B dividing L + 1 so that each bin has equal probability) against uniform,
  p-values Holm-corrected (Holm 1979) for the K coordinates (``SBCResult.passed``: no
  corrected p-value below ``alpha``). This test alone is weak against a posterior uniformly
  too narrow; the calibration's verdict is ``SBCResult.verdict`` (also in ``to_dict()``):
  χ²-Holm, the pooled dispersion test and the bias test of
  :mod:`bayes_talk.evaluation.sbc_power` at ``alpha``/3 each.
* :func:`run_sbc` - the loop: simulate, sample, rank, for any simulator and posterior.
* :func:`synthesis_sbc` - SBC of the whole-utterance synthesis model of a trained
  switching SGPDM (:mod:`bayes_talk.synthesis.joint`) on a given frame-label sequence:
  latent trajectories and audio simulated with ``pyro.infer.Predictive`` on
  ``synthesis_model`` (:func:`~bayes_talk.posterior.predictive_checks.prior_predictive`),
  each simulated audio given to :func:`~bayes_talk.posterior.sampling.sample_synthesis`
  (any method), ranks over the T·d latent coordinates. With smoothness on (the default,
  as in synthesis) each smoothness factor is the density at u = 0 of a pseudo-observation
  u | X (:mod:`bayes_talk.synthesis.joint`, (S)); the simulation draws (X, audio, u) from
  that joint, and the sampler targets p(X | audio, u) (``sample_synthesis(...,
  smooth_shift=u)``), the synthesis density with the simulated u in place of 0.
* :func:`scaled_laplace` - a deliberately wrong posterior: Laplace draws shrunk towards the
  MAP so that the variance is ``scale`` times Laplace's (0.5 in the tests) - the control
  that SBC must reject.

Draws from MCMC are thinned to L evenly spaced draws of the pooled chains (Talts et al.
§4.1: autocorrelated draws give ∪-shaped histograms even for a correct sampler); the
smallest bulk ESS of each run is recorded so that L ≤ ESS can be checked.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import pairwise
from typing import TYPE_CHECKING

import numpy as np
import scipy.stats

from bayes_talk.evaluation.sbc_power import combined_verdict

if TYPE_CHECKING:
    from bayes_talk.models.switching import SwitchingModel as SwitchingSGPDM

#: family-wise level of the uniformity test
ALPHA = 0.05


def ranks(truth: np.ndarray, draws: np.ndarray) -> np.ndarray:
    """Rank statistics (N, K): #{l : draws[n, l, k] < truth[n, k]} for truth (N, K), draws (N, L, K)."""
    t = np.asarray(truth, dtype=np.float64)
    d = np.asarray(draws, dtype=np.float64)
    if d.ndim != 3 or t.shape != (d.shape[0], d.shape[2]):
        raise ValueError(f"truth (N, K) and draws (N, L, K) expected, got {t.shape} and {d.shape}")
    return np.sum(d < t[:, None, :], axis=1)


def holm(p: np.ndarray) -> np.ndarray:
    """Holm's step-down adjusted p-values: p̃_(i) = max_{j ≤ i} min(1, (K − j + 1) p_(j))."""
    p = np.asarray(p, dtype=np.float64)
    order = np.argsort(p)
    K = p.size
    adj = np.minimum(1.0, np.maximum.accumulate((K - np.arange(K)) * p[order]))
    out = np.empty_like(adj)
    out[order] = adj
    return out


def default_bins(n_draws: int, n_sims: int) -> int:
    """The largest B dividing L + 1 with at least 5 expected ranks per bin (N / B ≥ 5), ≥ 3
    (two bins, lower and upper half, cannot see a ∪- or ∩-shaped histogram)."""
    L1 = n_draws + 1
    ok = [b for b in range(3, L1 + 1) if L1 % b == 0 and n_sims / b >= 5]
    if not ok:
        raise ValueError(f"{n_sims} simulations cannot fill 3 or more equal-probability bins of {L1} ranks "
                         "with 5 each; use more simulations, or draws with n_draws + 1 divisible by 3, 4 or 5")
    return max(ok)


def check_bins(n_draws: int, n_sims: int, bins: int | None = None) -> int:
    """The number of equal-probability rank bins an SBC of ``n_sims`` simulations and
    ``n_draws`` ranked draws uses (``bins``, else :func:`default_bins`); a ValueError naming
    the problem when there is none or there are fewer than 10 simulations (so a run can be
    refused before it simulates)."""
    if n_sims < 10:
        raise ValueError(f"n_sims must be >= 10, got {n_sims}")
    B = default_bins(n_draws, n_sims) if bins is None else int(bins)
    if B < 1 or (n_draws + 1) % B:
        raise ValueError(f"bins ({B}) must divide n_draws + 1 ({n_draws + 1}) for equal-probability bins")
    return B


def uniformity_test(r: np.ndarray, n_draws: int, bins: int | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """χ² p-values (K,) of the rank histograms r (N, K) in ``bins`` equal-probability bins of
    {0..L}, their Holm adjustment (K,), and the number of bins."""
    r = np.asarray(r)
    B = check_bins(n_draws, r.shape[0], bins)
    if np.any(r < 0) or np.any(r > n_draws):
        raise ValueError(f"ranks must lie in 0..{n_draws}")
    b = (r * B) // (n_draws + 1)
    counts = np.stack([np.sum(b == j, axis=0) for j in range(B)])   # (B, K)
    p = scipy.stats.chisquare(counts, axis=0).pvalue
    return np.asarray(p, dtype=float), holm(p), B


@dataclass
class SBCResult:
    """ranks (N, K) of the truth among n_draws posterior draws for N simulations and K
    coordinates; p_values / p_adjusted (K,) the χ² uniformity test before / after Holm."""

    ranks: np.ndarray
    n_draws: int
    p_values: np.ndarray
    p_adjusted: np.ndarray
    bins: int
    alpha: float = ALPHA
    info: dict = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        """The χ²-Holm test alone: no coordinate rejects uniformity at family-wise level
        ``alpha``. Weak against a uniformly too narrow posterior; :attr:`verdict` is the
        combined test."""
        return bool(np.all(self.p_adjusted >= self.alpha))

    @property
    def verdict(self) -> dict:
        """The combined verdict (:func:`bayes_talk.evaluation.sbc_power.combined_verdict`):
        χ²-Holm, the pooled dispersion test and the bias test at ``alpha``/3 each;
        ``verdict["passed"]`` is the calibration's pass/fail."""
        return combined_verdict(self.ranks, self.n_draws, self.p_adjusted, self.alpha)

    @property
    def n_rejected(self) -> int:
        """Coordinates whose uniformity test rejects at the family-wise level (Holm-adjusted p < alpha)."""
        return int(np.sum(self.p_adjusted < self.alpha))

    @property
    def extreme_fraction(self) -> float:
        """Fraction of ranks in the outer 2 / (L + 1)·⌈(L + 1)/40⌉ of {0..L} (lowest or highest
        ⌈(L + 1)/40⌉ values); expected: 2⌈(L + 1)/40⌉ / (L + 1)."""
        m = self.extreme_width
        return float(np.mean((self.ranks < m) | (self.ranks > self.n_draws - m)))

    @property
    def extreme_width(self) -> int:
        """Ranks counted as extreme at each end (about 2.5 % of the L + 1 possible ranks, at least 1)."""
        return max(1, -(-(self.n_draws + 1) // 40))

    @property
    def extreme_expected(self) -> float:
        """Fraction of ranks expected in the extremes under uniformity."""
        return 2 * self.extreme_width / (self.n_draws + 1)

    def histogram(self) -> np.ndarray:
        """Rank counts (bins,) pooled over coordinates."""
        b = (self.ranks * self.bins) // (self.n_draws + 1)
        return np.bincount(b.ravel(), minlength=self.bins)

    def to_dict(self) -> dict:
        """JSON-ready summary (the per-coordinate p-values included, not the ranks): ``passed``
        is the χ²-Holm test alone, ``verdict`` the combined verdict (read ``verdict["passed"]``)."""
        return {"verdict": self.verdict, "passed": self.passed, "alpha": self.alpha, "n_sims": int(self.ranks.shape[0]),
                "n_coordinates": int(self.ranks.shape[1]), "n_draws": self.n_draws, "bins": self.bins,
                "n_rejected": self.n_rejected, "min_p_adjusted": float(np.min(self.p_adjusted)),
                "min_p": float(np.min(self.p_values)), "extreme_fraction": self.extreme_fraction,
                "extreme_expected": self.extreme_expected, "histogram_pooled": self.histogram().tolist(),
                "p_values": self.p_values.tolist(), **self.info}


def thin(draws: np.ndarray, n: int) -> np.ndarray:
    """n evenly spaced rows of draws (M, K) (M ≥ n)."""
    d = np.asarray(draws)
    if d.shape[0] < n:
        raise ValueError(f"need at least {n} posterior draws to thin, got {d.shape[0]}")
    return d[np.linspace(0, d.shape[0] - 1, n).round().astype(int)]


def run_sbc(simulate: Callable[[np.random.Generator], tuple[np.ndarray, object]],
            posterior: Callable[[object, int], np.ndarray], n_sims: int, n_draws: int, seed: int = 0,
            bins: int | None = None, alpha: float = ALPHA) -> SBCResult:
    """SBC with ``simulate(rng) -> (θ̃ (K,), ỹ)`` and ``posterior(ỹ, seed) -> draws (M, K)``
    (M ≥ n_draws; thinned to ``n_draws`` evenly spaced draws)."""
    check_bins(n_draws, n_sims, bins)   # before the sampler runs n_sims times, not after
    rng = np.random.default_rng(seed)
    truth, draws = [], []
    for i in range(n_sims):
        theta, y = simulate(rng)
        truth.append(np.asarray(theta, dtype=np.float64).reshape(-1))
        draws.append(thin(np.asarray(posterior(y, seed + 1 + i)).reshape(-1, truth[-1].size), n_draws))
    r = ranks(np.stack(truth), np.stack(draws))
    p, padj, B = uniformity_test(r, n_draws, bins)
    return SBCResult(r, n_draws, p, padj, B, alpha)


SynthesisPosterior = Callable[..., tuple[np.ndarray, dict]]


def _smooth_kw(smooth_shift: np.ndarray | None) -> dict:
    """sample_synthesis keywords: smoothness off (None), or on with the pseudo-observations u."""
    return {"smoothness": "off"} if smooth_shift is None else {"smoothness": "frame", "smooth_shift": smooth_shift}


@dataclass(frozen=True)
class _SamplerPosterior:
    """:func:`sampler_posterior`'s posterior (a module-level class, so that process pools can
    pickle it)."""

    method: str
    n_draws: int | None
    kw: dict

    def __call__(self, model, audio, labels, seed, smooth_shift=None):
        from bayes_talk.posterior.sampling import sample_synthesis

        r = sample_synthesis(model, audio, labels, method=self.method, n_draws=self.n_draws, seed=seed,
                             log_warnings=False, audio_view=True, **_smooth_kw(smooth_shift), **self.kw)
        return r.latent_draws.reshape(-1, r.latent_draws.shape[-2] * r.latent_draws.shape[-1]), r.diagnostics


@dataclass(frozen=True)
class _ScaledLaplace:
    """:func:`scaled_laplace`'s posterior (picklable, as :class:`_SamplerPosterior`)."""

    scale: float
    n_draws: int

    def __call__(self, model, audio, labels, seed, smooth_shift=None):
        from bayes_talk.posterior.sampling import sample_synthesis

        r = sample_synthesis(model, audio, labels, method="laplace", n_draws=self.n_draws, seed=seed,
                             log_warnings=False, audio_view=True, **_smooth_kw(smooth_shift))
        X = r.latent_draws.reshape(-1, r.latent_draws.shape[-2] * r.latent_draws.shape[-1])
        x_map = r.map_latents.reshape(-1)
        return x_map + np.sqrt(self.scale) * (X - x_map), r.diagnostics


def sampler_posterior(method: str, n_draws: int | None = None, **kw) -> SynthesisPosterior:
    """A posterior for :func:`synthesis_sbc`: ``sample_synthesis(method=...)`` on the
    simulated audio as the audio view it is (``audio_view=True``: with ``audio_context`` > 0
    it must not be spliced and projected again), smoothness off when ``smooth_shift`` is None
    and on with the simulated pseudo-observations u otherwise; returns (pooled latent draws
    (M, T·d), diagnostics)."""
    return _SamplerPosterior(method, n_draws, dict(kw))


def scaled_laplace(scale: float, n_draws: int = 200) -> SynthesisPosterior:
    """Laplace draws x_MAP + √scale (x − x_MAP): the Laplace posterior with its covariance
    multiplied by ``scale`` (a deliberately wrong posterior for ``scale`` ≠ 1)."""
    return _ScaledLaplace(float(scale), int(n_draws))


def _posterior_chunk(job: tuple) -> list[tuple[np.ndarray, dict]]:
    """The posterior runs of one chunk of SBC simulations (module-level: process pools pickle it)."""
    post, model, labels, runs = job
    return [post(model, audio, labels, seed, u) for audio, seed, u in runs]


#: SBC simulations' posterior runs per worker process when they run in parallel
SBC_CHUNKS_PER_WORKER = 4


def synthesis_sbc(model: SwitchingSGPDM, labels, posterior: SynthesisPosterior | str = "nuts", n_sims: int = 200,
                  n_draws: int = 19, seed: int = 0, bins: int | None = None, alpha: float = ALPHA,
                  smoothness: str = "frame", executor=None, **sampler_kw) -> SBCResult:
    """SBC of the synthesis model of ``model`` on the frame labels ``labels`` (T frames; keep T
    small: every simulation runs the sampler once). ``posterior``: a method name for
    :func:`sampler_posterior` (with ``sampler_kw``) or a callable
    (model, audio, labels, seed, smooth_shift) -> (draws (M, T·d), diagnostics), ``audio``
    (T, D_y) being the model's audio *view* (``model.audio_input`` of MFCCs; what the
    synthesis model simulates), to be passed on with ``audio_view=True``, and
    ``smooth_shift`` the simulated pseudo-observations u (T, D_z) of the smoothness factors
    (None with ``smoothness="off"``), to be passed on as ``sample_synthesis(...,
    smoothness="frame", smooth_shift=u)``. ``n_draws`` (L): draws
    ranked per simulation, after thinning. ``info`` records the sampler diagnostics
    (worst R-hat, smallest bulk ESS, k̂, divergences over the simulations) and seconds.

    ``executor`` (bayes_talk.base.executor, e.g. ``ProcessExecutor(2)``): when it runs tasks in
    other processes, the simulations' posterior runs go to it in contiguous chunks (a
    posterior must then be picklable: :func:`sampler_posterior` and :func:`scaled_laplace`
    are). Each run is seeded by its simulation (seed + 1000 + i), so the ranks do not depend
    on the executor."""
    import time

    from bayes_talk.posterior.predictive_checks import prior_predictive
    from bayes_talk.synthesis.joint import make_plan

    labels = list(labels)
    check_bins(n_draws, n_sims, bins)
    post = sampler_posterior(posterior, **sampler_kw) if isinstance(posterior, str) else posterior
    # the plan's audio is a placeholder: the prior predictive simulates it (and u)
    plan = make_plan(model, np.zeros((len(labels), model.dims_[0])), labels, smoothness=smoothness)
    X, audio, U = prior_predictive(plan, n_sims, seed, with_smoothness=True)
    smooth_on = any(b.smooth for b in plan.blocks)
    diags: list[dict] = []
    it = iter(range(n_sims))
    t0 = time.perf_counter()

    def simulate(rng):
        i = next(it)
        return X[i].reshape(-1), i

    runs = [(audio[i], seed + 1000 + i, U[i] if smooth_on else None) for i in range(n_sims)]
    done: dict[int, tuple[np.ndarray, dict]] = {}
    if getattr(executor, "parallel", False) and n_sims > 1:
        n_chunks = min(n_sims, SBC_CHUNKS_PER_WORKER * max(1, int(getattr(executor, "n_workers", 2))))
        bounds = np.linspace(0, n_sims, n_chunks + 1).round().astype(int)
        outs = executor.map(_posterior_chunk, [(post, model, labels, runs[a:b]) for a, b in pairwise(bounds)])
        done = {i: r for a, rs in zip(bounds, outs) for i, r in enumerate(rs, start=int(a))}

    def sample(i, s):
        a, run_seed, u = runs[i]
        draws, diag = done.pop(i) if i in done else post(model, a, labels, run_seed, u)
        diags.append(diag)
        return draws

    res = run_sbc(simulate, sample, n_sims, n_draws, seed, bins, alpha)
    res.info.update(_summarise(diags))
    res.info.update(seconds=time.perf_counter() - t0, n_frames=plan.n_frames, latent_dim=plan.latent_dim,
                    n_blocks=len(plan.blocks), method=posterior if isinstance(posterior, str) else "custom",
                    smoothness=smoothness, n_smoothness_factors=sum(b.smooth for b in plan.blocks))
    return res


def _summarise(diags: list[dict]) -> dict:
    out: dict = {}
    for key, fn in (("rhat_max", max), ("ess_bulk_min", min), ("ess_tail_min", min), ("khat", max),
                    ("ebfmi_min", min), ("autocorr_time_max", max)):
        v = [d[key] for d in diags if key in d and d[key] is not None and np.isfinite(d[key])]
        if v:
            out[f"worst_{key}"] = float(fn(v))
    if any("divergences" in d for d in diags):
        out["divergences"] = int(sum(d.get("divergences", 0) for d in diags))
    if any("khat" in d for d in diags):
        out["khat_above_0.7"] = float(np.mean([d["khat"] > 0.7 for d in diags if "khat" in d]))
    out["map_converged"] = int(sum(bool(d.get("map_converged")) for d in diags))
    return out


__all__ = ["ALPHA", "SBCResult", "default_bins", "holm", "ranks", "run_sbc", "sampler_posterior", "scaled_laplace",
           "synthesis_sbc", "thin", "uniformity_test"]
