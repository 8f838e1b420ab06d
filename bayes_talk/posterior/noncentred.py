"""The synthesis density in non-centred coordinates: standardised dynamics innovations.

Inside a stretch of one state model's dynamics the latents follow (deena2010, Eq. (7);
docs/model.md)

    x_t = μ_x(x_{t−1}) + σ_x(x_{t−1}) ⊙ ε_t,   σ_x,m(x)² = s(x) / w_m²                  (1)

with s(x) = α − ‖L⁻¹k(x)‖² + β⁻¹ the dynamics GP's predictive variance (β_x = 10⁶, so
σ_x ≈ 10⁻³): in x the path is almost a deterministic function of the stretch's first
frame, and a sampler in x (whitened or not) meets scales 10³ apart along the stretch.
In the innovations ε the dynamics prior is N(0, I) whatever β_x — the non-centred
parameterisation (Papaspiliopoulos, Roberts & Sköld 2007; Betancourt & Girolami 2015). The
roots of the recursion are the frames without a dynamics parent: a stretch's first frame
with an entry distribution is standardised by it, x_a = μ_π + L_π ε_a (L_π L_πᵀ = Σ_π),
and a frame of a state model without dynamics stays in x (x = ε).

The map ε ↦ x is triangular (x_t depends on ε_t and x_{t−1}), so

    ln p_ε(ε) = ln p(x(ε) | Ŷ) + ln |det ∂x/∂ε|,
    ln |det ∂x/∂ε| = Σ_entries Σ_i ln (L_π)_ii + Σ_dynamics steps Σ_m ½ ln (s(x_{t−1}) / w_m²)   (2)

(the Jacobian's diagonal blocks are L_π, diag σ_x(x_{t−1}) and I). The dynamics terms of
ln p and of (2) cancel to Σ −½‖ε_t‖² − (d/2) ln 2π, but :class:`NonCentred` evaluates (2)
as written, on top of the existing numpy density
(:class:`~bayes_talk.synthesis.joint.UtteranceDensity`), so the two coordinate
systems share one density. Its gradient is the reverse pass of (1): with x̄ = ∂/∂x of
ln p + (2) (x treated as free),

    ε̄_t = x̄_t ⊙ σ_t,   x̄_{t−1} += J_μᵀ x̄_t + (∂s/∂x_{t−1})ᵀ ḡ_s,   ḡ_s = Σ_m x̄_tm ε_tm σ_tm/(2s) + d/(2s)

(∂s/∂x = 2γ Σ_i (K⁻¹k)_i k_i (x − X_i), 0 where s is floored at β⁻¹), taken level by level
from the deepest frames of every stretch: all frames at one depth go through one compiled
call over the packed dynamics GPs (:class:`~bayes_talk.gp.predictive_fused.PackedGPs`).
The inverse, x ↦ ε, is one call: ε_t = (x_t − μ_x(x_{t−1})) / σ_x(x_{t−1}).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from bayes_talk.gp.predictive_fused import Runs
from bayes_talk.synthesis.joint import UtteranceDensity
from bayes_talk.synthesis.whitening import Potential


class NonCentred:
    """ε ↦ (ln p_ε(ε), ∂ ln p_ε/∂ε) of the module docstring's (2), for ε (T·d,) or (T, d).

    ``to_x(E)`` / ``to_eps(X)`` map (…, T, d) or (…, T·d) arrays between the coordinates;
    ``log_jacobian(X)`` is ln |det ∂x/∂ε| at x."""

    def __init__(self, dens: UtteranceDensity):
        self.dens = dens
        self.T, self.d = dens.T, dens.d
        tm = dens.terms
        self.gps = tm.dyn_gps
        gp_of = dict(zip(tm.d_dst.tolist(), tm.d_runs.row_gp(1).tolist(), strict=True))
        depth = np.zeros(self.T, dtype=np.int64)
        for t in range(self.T):                     # d_src = t − 1 always
            if t in gp_of:
                depth[t] = depth[t - 1] + 1
        self.levels: list[tuple[np.ndarray, Runs]] = []
        for lev in range(1, int(depth.max()) + 1):
            rows = sorted((gp_of[t], t) for t in np.flatnonzero(depth == lev))
            self.levels.append((np.array([t for _, t in rows], dtype=np.int64),
                                Runs.of(np.array([g for g, _ in rows], dtype=np.int64))))
        self.dyn_rows = tm.d_dst
        self.dyn_runs = tm.d_runs
        self.e_idx = tm.e_idx
        self.e_mean = tm.e_mean
        self.e_chol = np.linalg.inv(tm.e_chol_inv) if len(tm.e_idx) else tm.e_chol_inv
        self.e_logdet = float(np.sum(np.log(np.abs(np.diagonal(self.e_chol, axis1=1, axis2=2)))))
        self.n_evals = 0

    # ------------------------------------------------------------------ maps
    def _sigma(self, runs: Runs, s: np.ndarray) -> np.ndarray:
        return np.sqrt(s[:, None] / self.gps.w2[runs.row_gp(1)])

    def _forward(self, E: np.ndarray):
        """x(ε) and, per level, (μ, s, σ) at its rows (for the reverse pass)."""
        X = E.copy()
        if len(self.e_idx):
            X[self.e_idx] = self.e_mean + np.einsum("eij,ej->ei", self.e_chol, E[self.e_idx])
        cache = []
        for rows, runs in self.levels:
            mu, s = self.gps.mean_var(runs, X[rows - 1])
            sig = self._sigma(runs, s)
            X[rows] = mu + sig * E[rows]
            cache.append((s, sig))
        return X, cache

    def to_x(self, E: np.ndarray) -> np.ndarray:
        """x(ε) for every (T, d) or (T·d,) slice of E (…)."""
        E = np.asarray(E, dtype=np.float64)
        flat = E.reshape(-1, self.T, self.d)
        return np.stack([self._forward(e)[0] for e in flat]).reshape(E.shape)

    def to_eps(self, X: np.ndarray) -> np.ndarray:
        """ε(x), the inverse of :meth:`to_x`: ε_t = (x_t − μ_x(x_{t−1})) / σ_x(x_{t−1}) in one call."""
        X = np.asarray(X, dtype=np.float64)
        out = []
        for x in X.reshape(-1, self.T, self.d):
            e = x.copy()
            if len(self.e_idx):
                e[self.e_idx] = np.linalg.solve(self.e_chol, (x[self.e_idx] - self.e_mean)[..., None])[..., 0]
            if len(self.dyn_rows):
                mu, s = self.gps.mean_var(self.dyn_runs, x[self.dyn_rows - 1])
                e[self.dyn_rows] = (x[self.dyn_rows] - mu) / self._sigma(self.dyn_runs, s)
            out.append(e)
        return np.stack(out).reshape(X.shape)

    def log_jacobian(self, X: np.ndarray) -> float:
        """ln |det ∂x/∂ε| at x (T, d): the module docstring's (2)."""
        X = np.asarray(X, dtype=np.float64).reshape(self.T, self.d)
        lj = self.e_logdet
        if len(self.dyn_rows):
            _, s = self.gps.mean_var(self.dyn_runs, X[self.dyn_rows - 1])
            lj += float(np.sum(np.log(self._sigma(self.dyn_runs, s))))
        return lj

    # ------------------------------------------------------------------ density
    def __call__(self, eps: np.ndarray) -> tuple[float, np.ndarray]:
        """(ln p_ε(ε), ∂ ln p_ε/∂ε) at ε (T·d,) or (T, d); the gradient has ε's shape."""
        shape = np.shape(eps)
        E = np.asarray(eps, dtype=np.float64).reshape(self.T, self.d)
        self.n_evals += 1
        X, cache = self._forward(E)
        lp, Xbar = self.dens(X)
        Xbar = Xbar.copy()
        lp += self.e_logdet
        Ebar = np.zeros_like(E)
        for (rows, runs), (s, sig) in zip(reversed(self.levels), reversed(cache), strict=True):
            lp += float(np.sum(np.log(sig)))
            xb = Xbar[rows]
            Ebar[rows] = xb * sig
            gs = (np.sum(xb * E[rows] * sig, axis=1) + self.d) / (2.0 * s)
            Xbar[rows - 1] += self.gps.mean_var_vjp(runs, X[rows - 1], xb, gs)
        roots = np.ones(self.T, dtype=bool)
        for rows, _ in self.levels:
            roots[rows] = False
        Ebar[roots] = Xbar[roots]
        if len(self.e_idx):
            Ebar[self.e_idx] = np.einsum("eji,ej->ei", self.e_chol, Xbar[self.e_idx])
        if not math.isfinite(lp):
            return -math.inf, np.zeros(shape)
        return float(lp), Ebar.reshape(shape)


    def torch_fn(self):
        """ε (torch, (T·d,)) ↦ ln p_ε(ε) as a differentiable torch scalar, for Pyro's NUTS."""
        return _TorchNonCentred(self)


class _TorchNonCentred:
    """:class:`NonCentred` as a torch function (the gradient from its reverse pass)."""

    def __init__(self, nc: NonCentred):
        self.nc = nc

    def __call__(self, e: torch.Tensor) -> torch.Tensor:
        return Potential.apply(e, self.nc)


def eps_hessian(nc: NonCentred, e: np.ndarray, step: float = 1e-5) -> np.ndarray:
    """∇² ln p_ε at ε (T·d,) by central differences of the reverse-pass gradient (2·T·d
    evaluations), symmetrised."""
    e = np.asarray(e, dtype=np.float64).reshape(-1)
    H = np.empty((e.size, e.size))
    for i in range(e.size):
        up, dn = e.copy(), e.copy()
        up[i] += step
        dn[i] -= step
        H[i] = (nc(up)[1].reshape(-1) - nc(dn)[1].reshape(-1)) / (2.0 * step)
    return 0.5 * (H + H.T)


class WhitenedNonCentred:
    """u ↦ (ln p_ε(ε_0 + L_ε u), L_εᵀ ∇_ε ln p_ε): the innovations ε of :class:`NonCentred`
    whitened by the Laplace covariance *in ε* at ε_0 = ε(X_MAP), L_ε L_εᵀ = (−∇² ln p_ε(ε_0))⁻¹
    (eigenvalues floored as for the x-Laplace; :func:`eps_hessian`). An affine map of ε, so
    the target is p_ε pushed through it (constant Jacobian). Non-centring removes the
    state-dependent stiffness of the dynamics, which a whitening at one point cannot; the
    whitening removes what the diagonal mass matrix NUTS adapts cannot: within-frame
    correlations (up to 0.9 at the isolated frames of the toy utterance) and scales whose
    diagonal-scaled condition number is ~90 there (docs/uncertainty.md)."""

    def __init__(self, nc: NonCentred, e0: np.ndarray, L: np.ndarray):
        self.nc, self.e0, self.L = nc, np.asarray(e0, dtype=np.float64).reshape(-1), L
        self.L_inv = np.linalg.inv(L)

    def __call__(self, u: np.ndarray) -> tuple[float, np.ndarray]:
        f, g = self.nc(self.e0 + self.L @ np.asarray(u, dtype=np.float64).reshape(-1))
        return f, (self.L.T @ g.reshape(-1)).reshape(np.shape(u))

    def to_eps(self, U: np.ndarray) -> np.ndarray:
        """ε_0 + L_ε u for every row of U (…, T·d)."""
        return self.e0 + np.asarray(U, dtype=np.float64) @ self.L.T

    def to_u(self, X: np.ndarray) -> np.ndarray:
        """u(x) = L_ε⁻¹ (ε(x) − ε_0) for latents X (…, T, d) or (…, T·d)."""
        shape = np.shape(X)
        lead = shape[:-2] if shape[-2:] == (self.nc.T, self.nc.d) else shape[:-1]
        E = self.nc.to_eps(X).reshape(-1, self.e0.size)
        return ((E - self.e0) @ self.L_inv.T).reshape(lead + (self.e0.size,))

    def to_x(self, U: np.ndarray) -> np.ndarray:
        """x(ε(u)) for every (T·d,) row of U (…)."""
        U = np.asarray(U, dtype=np.float64)
        return self.nc.to_x(self.to_eps(U.reshape(-1, self.e0.size))).reshape(U.shape)

    def torch_fn(self):
        """u (torch, (T·d,)) ↦ the log density as a differentiable torch scalar, for Pyro's NUTS."""
        return _TorchNonCentred(self)


def nuts_noncentred(dens: UtteranceDensity, mp, modes: list, z0: np.ndarray, L: np.ndarray, per_chain: int,
                    warmup: int, chains: int, seed: int, skw: dict, run=None, whiten: bool = False):
    """NUTS on the innovations ε (module docstring) of the synthesis density, the
    ``sampler_kw={"coords": "noncentred"}`` option of
    :func:`~bayes_talk.posterior.sampling.sample_synthesis`; ``whiten`` (``coords``
    "noncentred-whitened"): NUTS moves in u, ε = ε(X_MAP) + L_ε u (:class:`WhitenedNonCentred`).

    Chains start at ε(X_MAP + L z0_c), z0 the overdispersed whitened starts (L Lᵀ the
    Laplace covariance at the mode ``mp``); the mode-jumping displacements between the
    modes found (:func:`~bayes_talk.posterior.mode_search.mode_jumps`) become fixed
    displacements in ε, ε(X_MAP + δ_k) − ε(X_MAP) (a symmetric, state-independent proposal
    in ε: the Metropolis move keeps p_ε invariant). No pilot mode search. ``skw["pg_every"]``
    = k > 0 adds a particle Gibbs sweep (``skw["pg_particles"]`` particles, default 64;
    :class:`~bayes_talk.posterior.particle_gibbs.ParticleGibbsMove`) after every k-th
    iteration: particle Gibbs ∘ NUTS ∘ mode jumps. Its proposal: kernel bandwidths
    ``skw["pg_h"]`` (default 0.05), lookahead weights ``skw["pg_lookahead"]`` (default False),
    and with ``skw["pg_mode_centres"]`` (default False) the joint MAP and the modes of its
    restarts as extra centres (:class:`~bayes_talk.posterior.particle_gibbs.MixtureProposal`);
    ``skw["pg_backward"]`` (default False): backward simulation instead of ancestor sampling
    (:func:`~bayes_talk.posterior.particle_gibbs.csmc_as`); ``skw["pg_frame_tries"]`` = K > 0
    (default 0): after each sweep a K-try Metropolis update of every isolated frame and, with
    ``skw["pg_block_len"]`` = L (default 1), every dynamics run of at most L frames
    (:func:`~bayes_talk.posterior.frame_updates.block_mtm`); ``skw["pg_frame_modes"]`` (default False):
    those tries from the block's own modes
    (:class:`~bayes_talk.posterior.frame_updates.BlockModeProposal`), with ``skw["pg_neighbours"]``
    (default False) conditioned on the block's neighbours' smoothness factors, with
    ``skw["pg_pairs"]`` (default False) the pairs of consecutive blocks updated together too
    (:class:`~bayes_talk.posterior.frame_updates.PairModeProposal`), with ``skw["pg_adapt_weights"]``
    (default False) the modes' weights learnt during the warm-up and then frozen,
    ``skw["pg_block_sweeps"]`` (default 1) passes of the block and pair updates after each sweep, and
    ``skw["pg_mode_delta"]``, ``["pg_mode_scale"]``, ``["pg_mode_starts"]``, ``["pg_adapt_moments"]``, ``["pg_adapt_clusters"]``
    its ``delta``, ``scale``, ``n_starts``, ``moments`` (its defaults when absent); the blocks without modes are in the draws'
    ``stats["pg_blocks_without_modes"]``. ``skw["enough"]``: a stopping rule on the latent draws
    so far (chains, n, T·d) (:class:`~bayes_talk.posterior.sampling.TargetCheck`), asked by
    the runner on the draws mapped to x (with ``skw["min_draws"]``, ``skw["check_every"]``,
    :func:`~bayes_talk.posterior.samplers.run_nuts`). ``run``: the NUTS
    runner (default :func:`~bayes_talk.posterior.samplers.run_nuts`); it and the blocks' mode
    searches share one executor (``skw["executor"]``, else one for ``skw["workers"]``).
    Returns (draws in ε, the :class:`NonCentred` map)."""
    from bayes_talk.posterior.mode_search import mode_jumps
    from bayes_talk.posterior.samplers import run_nuts

    skw = dict(skw)
    skw.pop("pilot", None)
    nc = NonCentred(dens)
    T, d = dens.T, dens.d
    x_map = mp.latents.reshape(-1)
    e_map = nc.to_eps(x_map).reshape(-1)
    starts = nc.to_eps((x_map + np.atleast_2d(z0) @ L.T).reshape(-1, T, d)).reshape(-1, T * d)
    deltas = mode_jumps(mp, modes).reshape(-1, T * d)
    jumps = np.array([nc.to_eps(x_map + dl).reshape(-1) - e_map for dl in deltas]).reshape(-1, T * d)
    target = nc
    if whiten:
        from bayes_talk.posterior.samplers import laplace_scale

        L_e, _ = laplace_scale(eps_hessian(nc, e_map))
        target = WhitenedNonCentred(nc, e_map, L_e)
        starts = (starts - e_map) @ target.L_inv.T
        jumps = jumps @ target.L_inv.T
    enough = skw.pop("enough", None)
    if enough is not None:   # a stopping rule on the latents (posterior.TargetCheck), asked in NUTS's coordinates
        skw["enough"] = lambda S: enough(target.to_x(S))
    pg_every = int(skw.pop("pg_every", 0))
    pg_particles = int(skw.pop("pg_particles", 64))
    pg_h = skw.pop("pg_h", 0.05)
    pg_lookahead = bool(skw.pop("pg_lookahead", False))
    pg_mode_centres = bool(skw.pop("pg_mode_centres", False))
    pg_backward = bool(skw.pop("pg_backward", False))
    pg_frame_tries = int(skw.pop("pg_frame_tries", 0))
    pg_frame_modes = bool(skw.pop("pg_frame_modes", False))
    pg_block_len = int(skw.pop("pg_block_len", 1))
    pg_neighbours = bool(skw.pop("pg_neighbours", False))
    pg_pairs = bool(skw.pop("pg_pairs", False))
    pg_adapt_weights = bool(skw.pop("pg_adapt_weights", False))
    pg_block_sweeps = int(skw.pop("pg_block_sweeps", 1))
    mode_kw = {k: skw.pop(key) for k, key in (("delta", "pg_mode_delta"), ("scale", "pg_mode_scale"),
                                               ("n_starts", "pg_mode_starts"), ("moments", "pg_adapt_moments"),
                                               ("clusters", "pg_adapt_clusters"))
               if key in skw}
    from bayes_talk.base.executor import executor_for

    run = run_nuts if run is None else run
    # one executor for the blocks' mode searches and the chains (its workers started once)
    with executor_for(skw.pop("executor", None), int(skw.get("workers", 1))) as ex:
        if pg_every > 0:   # particle Gibbs ∘ NUTS: a CSMC-AS sweep in x after every pg_every-th iteration
            from bayes_talk.posterior.particle_gibbs import ParticleGibbsMove

            extra = (np.stack([np.reshape(m.latents, (T, d)) for m in [mp, *modes]]) if pg_mode_centres else None)
            to_u = target.to_u if whiten else nc.to_eps
            skw["extra_move"] = ParticleGibbsMove.for_density(
                dens, dens.plan, target.to_x, to_u, pg_particles, h=pg_h, lookahead=pg_lookahead,
                extra_centres=extra, backward=pg_backward, frame_tries=pg_frame_tries,
                tries_from_modes=pg_frame_modes, block_len=pg_block_len, neighbours=pg_neighbours,
                mode_kw=mode_kw, pairs=pg_pairs, adapt_weights=pg_adapt_weights, block_sweeps=pg_block_sweeps,
                executor=ex)
            skw["extra_every"] = pg_every
        draws = run(target.torch_fn(), starts if len(starts) > 1 else starts[0], n_draws=per_chain, warmup=warmup,
                    chains=chains, seed=seed, jumps=jumps, executor=ex, **skw)
    draws.stats["pilot"] = 0
    if pg_every > 0:
        draws.stats["pg_blocks_without_modes"] = [list(b) for b in skw["extra_move"].blocks_without_modes]
    draws.stats["coords"] = "noncentred-whitened" if whiten else "noncentred"
    return draws, target


__all__ = ["NonCentred", "WhitenedNonCentred", "eps_hessian", "nuts_noncentred"]
