"""The synthesis posterior of the switching SGPDM and its sampling (DESIGN.md §6).

With hyperparameters and training latents fixed at their MAP values, the posterior of a
segment's latent points given the audio is the normalised form of the objective that
Algorithm 1 optimises (:func:`bayes_talk.synthesis.optimise.sequence_log_density`, with
the same ``first`` and ``extra`` terms as :mod:`bayes_talk.synthesis.sequential`):

    p(X*_seg | Ŷ) ∝ N(x_first; μ_π, Σ_π) · Π_t p_π(x_t | x_{t−1}) · Π_t p_π(ŷ_t | x_t) · s(x_first)

s is the smoothness factor N(z̄_{a−1}; μ_Z(x_a), σ²_Z(x_a)/w² + s²_Δ) under π's visual GP,
where z̄_{a−1} is the *posterior-mean* visual of the previous segment's last frame (the
MAP path uses its MAP visual there). Segments are walked in order as in Algorithm 1:

1. the segment's MAP point by L-BFGS from the nearest-neighbour initialisation
   (:func:`~bayes_talk.synthesis.sequential.optimise_segment`, the point Algorithm 1 uses);
2. draws of the segment's latents by ``method``: Pyro NUTS, emcee or the Laplace
   approximation at the MAP point (:mod:`bayes_talk.synthesis.samplers`); NUTS chains
   start at draws of the Laplace approximation (overdispersed around the MAP point),
   emcee walkers in a small ball around it;
3. per draw s, the visual predictive N(μ_Z(x_t^s), σ²_Z(x_t^s)/w²); the segment's
   posterior-mean visual conditions the next segment's smoothness factor.

With ``algorithm="predict"`` (Algorithm 2) only the first latent point of a segment is
sampled (its one-frame posterior: entry prior, audio likelihood, smoothness factor) and
each draw is rolled forward by the dynamics mean.

Segments are sampled independently given the previous segment's posterior mean, so the
s-th utterance-level draw concatenates the s-th draw of every segment.

The visual predictive of frame t is the mixture (1/S) Σ_s N(μ_Z(x_t^s), σ²_Z(x_t^s)/w²):
:attr:`PosteriorSynthesis.mean` is its mean, :attr:`PosteriorSynthesis.var` its variance
(mean of the GP variances + variance of the GP means), and
:meth:`PosteriorSynthesis.quantiles` gives central bands from samples of the mixture.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from bayes_talk.evaluation.diagnostics import chain_diagnostics, summarise_segments
from bayes_talk.gp.threads import torch_threads
from bayes_talk.models.vlmm import Segment
from bayes_talk.synthesis.optimise import sequence_log_density
from bayes_talk.synthesis.samplers import METHODS, Draws, laplace_gaussian, run_sampler
from bayes_talk.synthesis.sequential import ALGORITHMS, SMOOTHNESS, _check_inputs, optimise_segment

if TYPE_CHECKING:
    from bayes_talk.models.switching import SwitchingSGPDM

DEFAULT_LEVELS = (0.5, 0.8, 0.9, 0.95)


@dataclass
class SegmentDensity:
    """The log posterior of one segment as a function of its flattened latents (n_free·d,)."""

    model: object  # the state's SGPDM
    Y: torch.Tensor  # audio frames whose latents are free (n_free, D_y)
    first: tuple[torch.Tensor, torch.Tensor]  # entry mean, Cholesky factor of Σ_π
    extra: object  # smoothness term or None
    d: int

    @property
    def n_free(self) -> int:
        return int(self.Y.shape[0])

    @property
    def dynamics(self):
        return self.model.dynamics_predictor_ if self.n_free > 1 else None

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        X = x.reshape(self.n_free, self.d)
        return sequence_log_density(X, self.Y, self.model.predictors_["audio"], self.dynamics,
                                    self.first, self.extra)


def segment_density(m, Y: np.ndarray, entry: tuple[np.ndarray, np.ndarray], z_prev: np.ndarray | None,
                    motion_var: np.ndarray, smoothness: str = "frame") -> SegmentDensity:
    """The segment posterior with the terms :func:`sequential._optimise_segment` uses."""
    mu, cov = entry
    first = (torch.as_tensor(mu, dtype=torch.float64),
             torch.linalg.cholesky(torch.as_tensor(cov, dtype=torch.float64)))
    extra = None
    if z_prev is not None and smoothness != "off":
        vis = m.predictors_["visual"]
        z = torch.as_tensor(np.asarray(z_prev, dtype=np.float64).reshape(1, -1))
        mv = torch.as_tensor(np.asarray(motion_var, dtype=np.float64))
        extra = lambda Xs: vis.log_lik(z, Xs[:1], mv).sum()
    return SegmentDensity(m, torch.as_tensor(np.asarray(Y, dtype=np.float64)), first, extra,
                          int(m.X_.shape[1]))


@dataclass
class PosteriorSynthesis:
    """Posterior synthesis of one utterance.

    latents: (S, T, d) latent draws; draw_mean / draw_var: (S, T, D_z) the visual GP mean
    and per-dimension variance σ²_Z/w² at each draw; map_latents: (T, d) the segment MAP
    points the samplers started from; diagnostics: one dict per segment; summary: the
    worst case over segments.
    """

    method: str
    algorithm: str
    latents: np.ndarray
    draw_mean: np.ndarray
    draw_var: np.ndarray
    map_latents: np.ndarray
    segments: list[Segment]
    model_states: list[tuple[str, ...]]
    diagnostics: list[dict]
    seed: int
    seconds: float
    summary: dict = field(default_factory=dict)

    @property
    def n_draws(self) -> int:
        return int(self.draw_mean.shape[0])

    @property
    def mean(self) -> np.ndarray:
        """Mixture mean (T, D_z)."""
        return self.draw_mean.mean(0)

    @property
    def var(self) -> np.ndarray:
        """Mixture variance (T, D_z) = mean of the GP variances + variance of the GP means."""
        return self.draw_var.mean(0) + self.draw_mean.var(0)

    @property
    def gp_var(self) -> np.ndarray:
        """Average GP variance over draws (T, D_z) (the mixture variance without the spread)."""
        return self.draw_var.mean(0)

    def sample(self, n: int = 2000, seed: int | None = None) -> np.ndarray:
        """n samples (n, T, D_z) of the visual mixture: component k mod S, then its Gaussian."""
        rng = np.random.default_rng(self.seed + 1 if seed is None else seed)
        S = self.n_draws
        comp = np.resize(rng.permutation(S), n)
        return self.draw_mean[comp] + np.sqrt(self.draw_var[comp]) * rng.standard_normal(
            (n,) + self.draw_mean.shape[1:])

    def quantiles(self, levels=DEFAULT_LEVELS, n_samples: int = 2000,
                  seed: int | None = None) -> dict[float, tuple[np.ndarray, np.ndarray]]:
        """Central bands {level: (lower, upper)} of each (T, D_z) entry's mixture, from
        ``n_samples`` mixture samples (the same samples for every level, so nested)."""
        levels = [float(q) for q in levels]
        if any(not 0 < q < 1 for q in levels):
            raise ValueError(f"levels must be in (0, 1), got {levels}")
        s = self.sample(n_samples, seed)
        out = {}
        for q in levels:
            lo, hi = np.quantile(s, [0.5 - q / 2, 0.5 + q / 2], axis=0)
            out[q] = (lo, hi)
        return out


def sample_synthesis(
    model: SwitchingSGPDM,
    mfcc: np.ndarray,
    labels,
    method: str = "nuts",
    n_draws: int = 200,
    seed: int = 0,
    algorithm: str = "optimise",
    smoothness: str | bool = "frame",
    warmup: int | None = None,
    chains: int = 2,
    map_iter: int = 100,
    emcee_thin: int = 5,
    precondition: bool = True,
    sampler_kw: dict | None = None,
) -> PosteriorSynthesis:
    """Sample the synthesis posterior of one utterance segment by segment.

    method: "nuts" (Pyro NUTS, ``chains`` chains of ceil(n_draws / chains) draws after
        ``warmup`` adaptation steps, default 200), "emcee" (walkers max(32, 4·dim), burn-in
        ``warmup`` steps, default 500, then draws thinned by ``emcee_thin``) or "laplace"
        (n_draws iid Gaussian draws at the MAP point).
    n_draws: draws kept per segment (pooled over chains / walkers, evenly subsampled).
    map_iter: L-BFGS iterations of the segment MAP (the sampler start / Laplace centre).
    precondition: NUTS and emcee sample z with x = x_MAP + L z, L the Cholesky factor of
        the Laplace covariance (an affine map: the target is unchanged, its geometry is
        close to N(0, I)); NUTS chains then start at z ~ N(0, I), emcee walkers in a ball
        of radius 0.1 around z = 0.
    sampler_kw: extra keywords for the sampler (e.g. ``max_tree_depth``, ``n_walkers``).
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if algorithm not in ALGORITHMS:
        raise ValueError(f"algorithm must be one of {ALGORITHMS}, got {algorithm!r}")
    smoothness = "frame" if smoothness is True else "off" if smoothness is False else smoothness
    if smoothness not in SMOOTHNESS:
        raise ValueError(f"smoothness must be one of {SMOOTHNESS}, got {smoothness!r}")
    if n_draws < 8:
        raise ValueError(f"n_draws must be >= 8, got {n_draws}")
    mfcc = _check_inputs(model, mfcc, labels)
    t0 = time.perf_counter()
    with torch_threads(1):
        res = _sample(model, mfcc, labels, method, n_draws, seed, algorithm, smoothness, warmup, chains,
                      map_iter, emcee_thin, precondition, dict(sampler_kw or {}))
    res.seconds = time.perf_counter() - t0
    return res


class _Whitened:
    """log p(x_MAP + L z) as a function of z (the constant Jacobian |L| is dropped)."""

    def __init__(self, dens, x_map: np.ndarray, cov: np.ndarray):
        self.dens = dens
        self.x_map = np.asarray(x_map, dtype=np.float64)
        self.L = np.linalg.cholesky(cov + 1e-12 * np.trace(cov) / len(cov) * np.eye(len(cov)))
        self._x, self._L = torch.as_tensor(self.x_map), torch.as_tensor(self.L)

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        return self.dens(self._x + self._L @ z)

    def to_x(self, Z: np.ndarray) -> np.ndarray:
        return self.x_map + Z @ self.L.T


def _pool(draws: Draws, n: int) -> np.ndarray:
    """n draws evenly spaced through the pooled (chain-major) draws."""
    flat = draws.flat
    idx = np.linspace(0, len(flat) - 1, n).round().astype(int)
    return flat[idx]


def _sample(model, mfcc, labels, method, n_draws, seed, algorithm, smoothness, warmup, chains, map_iter,
            emcee_thin, precondition, skw) -> PosteriorSynthesis:
    segments = model.segment(list(labels))
    T, Dz, d = mfcc.shape[0], model.dims_[1], model.config.latent_dim
    S = n_draws
    lat = np.zeros((S, T, d))
    zm, zv = np.zeros((S, T, Dz)), np.zeros((S, T, Dz))
    xmap = np.zeros((T, d))
    used, diags = [], []
    for i, seg in enumerate(segments):
        a, b = seg.start, seg.stop
        key, m = model.model_for(seg.state)
        used.append(key)
        z_prev = zm[:, a - 1].mean(0) if a > 0 else None
        n_free = b - a if algorithm == "optimise" else 1
        dens = segment_density(m, mfcc[a:a + n_free], model.entry_[key], z_prev, model.motion_var_, smoothness)
        # the MAP point of Algorithm 1 itself (same density, closed-form objective)
        Xm = optimise_segment(m, mfcc[a:a + n_free], z_prev, model.entry_[key], smoothness, map_iter,
                              model.motion_var_)
        xmap[a:a + n_free] = Xm
        seg_seed = int(seed) * 1_000_003 + 7919 * i
        x_flat = Xm.reshape(-1)
        # precondition by the Laplace approximation: x = x_MAP + L z, L L^T = (-∇² log p)^-1.
        # The latent posteriors are badly conditioned (posterior sds spanning ~2 orders of
        # magnitude, strongly correlated), which a diagonal mass matrix cannot fix.
        _, cov_l, info_l = laplace_gaussian(dens, x_flat)
        g = _Whitened(dens, x_flat, cov_l) if (precondition and method != "laplace") else None
        if method == "nuts":
            kw = dict(warmup=200 if warmup is None else warmup, chains=chains)
            rng = np.random.default_rng(seg_seed + 1)
            n = x_flat.size
            if g is not None:  # chains start at draws of the Laplace approximation (z ~ N(0, I))
                x0 = rng.standard_normal((chains, n)) if chains > 1 else np.zeros(n)
            else:
                x0 = rng.multivariate_normal(x_flat, cov_l, size=chains, method="eigh") if chains > 1 else x_flat
            per_chain = -(-S // chains)
            draws = run_sampler("nuts", g or dens, x0, per_chain, seg_seed, **kw, **skw)
        elif method == "emcee":
            W = skw.get("n_walkers") or max(32, 4 * x_flat.size)
            W += W % 2
            per_walker = max(20, -(-S // W))
            x0, ball = (np.zeros(x_flat.size), 0.1) if g is not None else (x_flat, 1e-3)
            draws = run_sampler("emcee", g or dens, x0, per_walker, seg_seed,
                                warmup=500 if warmup is None else warmup, thin=emcee_thin,
                                **{"ball": ball, **skw, "n_walkers": W})
        else:
            draws = run_sampler("laplace", dens, x_flat, S, seg_seed, **skw)
        if g is not None:
            draws.samples = g.to_x(draws.samples)
        Xs = _pool(draws, S).reshape(S, n_free, d)
        if n_free < b - a:
            Xs = _roll(m, Xs, b - a)
        lat[:, a:b] = Xs
        with torch.no_grad():
            mu, var = m.predictors_["visual"].mean_var(torch.as_tensor(Xs.reshape(-1, d)))
            v = m.predictors_["visual"].dim_var(var)
        zm[:, a:b] = mu.numpy().reshape(S, b - a, Dz)
        zv[:, a:b] = v.numpy().reshape(S, b - a, Dz)
        diag = {k: v for k, v in chain_diagnostics(draws.samples).items() if k not in ("rhat", "ess_bulk",
                                                                                     "ess_tail")}
        st = draws.stats
        if "divergences" in st:
            diag["divergences"] = int(sum(st["divergences"]))
            diag["accept_prob"] = float(np.mean(st["accept_prob"]))
        if "acceptance_fraction" in st:
            diag["acceptance_fraction"] = st["acceptance_fraction"]
            diag["n_walkers"] = st["n_walkers"]
        diag["hessian_floored"] = info_l["n_floored"]
        diag["min_eig_precision"] = info_l["min_eig_precision"]
        diag.update(start=a, stop=b, state=" ".join(key), dim=int(x_flat.size), seconds=draws.seconds)
        diags.append(diag)
    return PosteriorSynthesis(method, algorithm, lat, zm, zv, xmap, segments, used, diags, int(seed), 0.0,
                              summarise_segments(diags))


def _roll(m, X1: np.ndarray, n: int) -> np.ndarray:
    """Algorithm 2 for every draw: X1 (S, 1, d) first points, then x_{t+1} = μ_x(x_t)."""
    dyn = m.dynamics_predictor_
    out = [X1[:, 0]]
    with torch.no_grad():
        for _ in range(n - 1):
            if dyn is None:
                out.append(out[-1].copy())
            else:
                out.append(dyn.mean_var(torch.as_tensor(out[-1]))[0].numpy())
    return np.stack(out, axis=1)


__all__ = ["DEFAULT_LEVELS", "PosteriorSynthesis", "SegmentDensity", "sample_synthesis", "segment_density"]
