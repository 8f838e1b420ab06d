"""``nuts``: Pyro NUTS with mode-jumping Metropolis moves (docs/uncertainty.md, "Inference").

In the whitened coordinates (the default), X = X_MAP + L z with L Lᵀ the Laplace covariance:
an affine map, so the target is unchanged and close to N(0, I) where the Laplace
approximation is good. Chains start overdispersed at z ~ N(0, 2²I). The density is
multimodal, so every iteration is followed by mode-jumping moves along displacements between
known modes (:func:`~bayes_talk.posterior.mode_search.mode_jumps`), and the first ``pilot``
warm-up iterations are a pilot: the MAP is then maximised from each chain's state, the
highest mode found becomes the whitening point and the jumps are rebuilt from all modes
found (:func:`~bayes_talk.posterior.mode_search.nuts_with_mode_search`).

``coords="noncentred"`` moves in the standardised dynamics innovations ε instead
(:func:`~bayes_talk.posterior.noncentred.nuts_noncentred`; "noncentred-whitened": ε whitened
by its own Laplace), with no pilot, and takes the particle Gibbs options (``pg_*``) that
``pg-nuts`` (:mod:`bayes_talk.posterior.methods.pg_nuts`) sets by default.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bayes_talk.posterior.diagnostics import sampler_diagnostics
from bayes_talk.posterior.methods import NUTS_DEFAULTS, Context, Output
from bayes_talk.posterior.mode_search import nuts_with_mode_search
from bayes_talk.posterior.noncentred import nuts_noncentred
from bayes_talk.posterior.samplers import INIT_SCALE
from bayes_talk.posterior.sampling import TargetCheck

#: coordinates NUTS moves in: X = X_MAP + L z (whitened at the mode, with the pilot mode
#: search) or the standardised dynamics innovations ε (:mod:`bayes_talk.posterior.noncentred`),
#: optionally whitened by their own Laplace
NUTS_COORDS = ("whitened", "noncentred", "noncentred-whitened")
NONCENTRED = ("noncentred", "noncentred-whitened")
#: the particle Gibbs options (non-centred coordinates only; None: off, or
#: :func:`~bayes_talk.posterior.noncentred.nuts_noncentred`'s default)
PG_OPTIONS = ("pg_every", "pg_particles", "pg_h", "pg_lookahead", "pg_mode_centres", "pg_backward",
              "pg_frame_tries", "pg_frame_modes", "pg_block_len", "pg_neighbours", "pg_pairs", "pg_mode_delta",
              "pg_mode_scale", "pg_mode_starts", "pg_adapt_weights", "pg_block_sweeps", "pg_adapt_moments",
              "pg_adapt_clusters")


@dataclass(frozen=True)
class Options:
    """coords: one of :data:`NUTS_COORDS`; target_accept, max_tree_depth: NUTS's step-size
    target and tree depth; jump_attempts: mode-jumping attempts per displacement per
    iteration; pilot: warm-up iterations of the pilot mode search (whitened coordinates; at
    most a third of the warm-up); workers, executor: where the chains run
    (:func:`bayes_talk.base.executor.executor_for`; the draws do not depend on it);
    stop_at_targets: stop drawing once the R-hat and ESS targets are met (non-centred
    coordinates; :class:`~bayes_talk.posterior.sampling.TargetCheck`), asked after
    min_draws_per_chain draws (None: half the most) and every check_every after; ``pg_*``: the
    particle Gibbs sweep and block updates (:data:`~bayes_talk.posterior.methods.PG_NUTS_DEFAULTS`;
    None: off, the defaults of :func:`~bayes_talk.posterior.noncentred.nuts_noncentred`)."""

    coords: str = "whitened"
    target_accept: float = NUTS_DEFAULTS["target_accept"]
    max_tree_depth: int = NUTS_DEFAULTS["max_tree_depth"]
    jump_attempts: int = NUTS_DEFAULTS["jump_attempts"]
    pilot: int = NUTS_DEFAULTS["pilot"]
    workers: int = 1
    executor: Any = None
    stop_at_targets: bool = False
    min_draws_per_chain: int | None = None
    check_every: int = 50
    pg_every: int | None = None
    pg_particles: int | None = None
    pg_h: Any = None
    pg_lookahead: bool | None = None
    pg_mode_centres: bool | None = None
    pg_backward: bool | None = None
    pg_frame_tries: int | None = None
    pg_frame_modes: bool | None = None
    pg_block_len: int | None = None
    pg_neighbours: bool | None = None
    pg_pairs: bool | None = None
    pg_mode_delta: float | None = None
    pg_mode_scale: Any = None
    pg_mode_starts: int | None = None
    pg_adapt_weights: bool | None = None
    pg_block_sweeps: int | None = None
    pg_adapt_moments: bool | None = None
    pg_adapt_clusters: bool | None = None

    def __post_init__(self):
        if self.coords not in NUTS_COORDS:
            raise ValueError(f"sampler_kw['coords'] must be one of {NUTS_COORDS}, got {self.coords!r}")
        if self.stop_at_targets and self.coords not in NONCENTRED:
            raise ValueError("sampler_kw['stop_at_targets'] needs the non-centred coordinates (pg-nuts, or "
                             f"nuts with coords='noncentred'), got coords={self.coords!r}")
        pg = [k for k in PG_OPTIONS if getattr(self, k) is not None]
        if pg and self.coords not in NONCENTRED:
            raise ValueError(f"sampler_kw {pg}: the particle Gibbs options need the non-centred coordinates "
                             f"(coords='noncentred'), got coords={self.coords!r}")

    def sampler_kw(self) -> dict:
        """The keywords of the NUTS runner (:func:`~bayes_talk.posterior.samplers.run_nuts`; in
        the non-centred coordinates also the ``pg_*`` of
        :func:`~bayes_talk.posterior.noncentred.nuts_noncentred` that are set)."""
        kw = {"target_accept": self.target_accept, "max_tree_depth": self.max_tree_depth,
              "jump_attempts": self.jump_attempts, "workers": self.workers, "executor": self.executor}
        if self.coords in NONCENTRED:
            kw.update({k: getattr(self, k) for k in PG_OPTIONS if getattr(self, k) is not None})
        else:
            kw["pilot"] = self.pilot
        return kw


def run(context: Context, options: Options) -> Output:
    """NUTS's draws: warm-up ``context.warmup`` (default ``NUTS_DEFAULTS["warmup"]``)."""
    return sample(context, options, NUTS_DEFAULTS["warmup"])


def sample(context: Context, options: Options, default_warmup: int) -> Output:
    """NUTS (and, with ``pg_every``, the particle Gibbs moves) from ``context`` with ``options``:
    ``context.chains`` chains of ceil(n_draws / chains) draws after ``context.warmup``
    (None: ``default_warmup``) warm-up iterations."""
    T, d = context.shape
    chains = context.chains
    z0 = INIT_SCALE * context.rng.standard_normal((chains, T * d)) if chains > 1 else np.zeros(T * d)
    warmup = default_warmup if context.warmup is None else context.warmup
    skw = options.sampler_kw()
    diag: dict = {}
    check = None
    if options.stop_at_targets:
        check = TargetCheck(context.plan)
        skw.update(enough=check, check_every=int(options.check_every), min_draws=options.min_draws_per_chain)
    mp, per_chain = context.map, -(-context.n_draws // chains)
    if options.coords in NONCENTRED:
        draws, g = nuts_noncentred(context.density, mp, context.modes, z0, context.scale, per_chain, warmup,
                                   chains, context.seed, skw, whiten=options.coords == "noncentred-whitened")
        found = []
    else:
        draws, mp, g, found = nuts_with_mode_search(context.density, mp, context.modes, z0, per_chain, warmup,
                                                     chains, context.seed, context.map_iter, skw)
    diag["coords"] = options.coords
    if check is not None:
        diag["stop_checks"] = check.history
    diag.update({"map_log_density": mp.log_density, "map_converged": mp.converged, "map_grad_norm": mp.grad_norm,
                 "map_decrement": mp.decrement, "hessian_modified": mp.hessian_modified,
                 "pilot_mode_log_densities": [r.log_density for r in found]})
    Xs = g.to_x(draws.samples).reshape(draws.samples.shape[0], draws.samples.shape[1], T, d)
    diag.update(sampler_diagnostics(draws, Xs))
    return Output(Xs, diag, draws.sample_stats, map=mp)


__all__ = ["NONCENTRED", "NUTS_COORDS", "PG_OPTIONS", "Options", "run", "sample"]
