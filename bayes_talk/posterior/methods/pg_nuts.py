"""``pg-nuts``: particle Gibbs ∘ NUTS ∘ mode jumps (docs/uncertainty.md, "Which sampler").

NUTS in the non-centred coordinates, the standardised dynamics innovations ε
(:func:`~bayes_talk.posterior.noncentred.nuts_noncentred`: the stiffness of the fixed dynamics
noise leaves the geometry), the mode-jumping moves, and after every iteration one
conditional-SMC sweep with ancestor sampling over the frames
(:class:`~bayes_talk.posterior.particle_gibbs.ParticleGibbsMove`), then multiple-try
Metropolis updates of every isolated frame and every short dynamics run, their tries from the
block's own modes (:class:`~bayes_talk.posterior.frame_updates.BlockModeProposal`). Each kernel
leaves the posterior invariant, so the composition does (tests/posterior/test_composition_invariance.py).
The same as ``nuts`` with ``coords="noncentred"`` and the settings of
:data:`~bayes_talk.posterior.methods.PG_NUTS_DEFAULTS` and
:data:`~bayes_talk.posterior.methods.PG_NUTS_BUDGET` (no pilot mode search); its warm-up and
draws per chain are :data:`~bayes_talk.posterior.methods.PG_NUTS_BUDGET`'s.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bayes_talk.posterior.methods import PG_NUTS_BUDGET, PG_NUTS_DEFAULTS, Context, Output, nuts
from bayes_talk.posterior.methods.nuts import NONCENTRED

_PG = PG_NUTS_DEFAULTS


@dataclass(frozen=True)
class Options(nuts.Options):
    """NUTS's options (:class:`bayes_talk.posterior.methods.nuts.Options`) in the non-centred
    coordinates, the particle Gibbs options on at :data:`~bayes_talk.posterior.methods.PG_NUTS_DEFAULTS`
    and the stopping rule on (:data:`~bayes_talk.posterior.methods.PG_NUTS_BUDGET`)."""

    coords: str = "noncentred"
    stop_at_targets: bool = PG_NUTS_BUDGET["stop_at_targets"]
    min_draws_per_chain: int | None = PG_NUTS_BUDGET["min_draws_per_chain"]
    check_every: int = PG_NUTS_BUDGET["check_every"]
    pg_every: int = _PG["pg_every"]
    pg_particles: int = _PG["pg_particles"]
    pg_h: Any = _PG["pg_h"]
    pg_lookahead: bool = _PG["pg_lookahead"]
    pg_mode_centres: bool = _PG["pg_mode_centres"]
    pg_backward: bool = _PG["pg_backward"]
    pg_frame_tries: int = _PG["pg_frame_tries"]
    pg_frame_modes: bool = _PG["pg_frame_modes"]
    pg_block_len: int = _PG["pg_block_len"]
    pg_neighbours: bool = _PG["pg_neighbours"]
    pg_pairs: bool = _PG["pg_pairs"]
    pg_mode_delta: float = _PG["pg_mode_delta"]
    pg_mode_scale: Any = _PG["pg_mode_scale"]
    pg_mode_starts: int = _PG["pg_mode_starts"]
    pg_adapt_weights: bool = _PG["pg_adapt_weights"]
    pg_block_sweeps: int = _PG["pg_block_sweeps"]
    pg_adapt_moments: bool = _PG["pg_adapt_moments"]
    pg_adapt_clusters: bool = _PG["pg_adapt_clusters"]

    def __post_init__(self):
        if self.coords not in NONCENTRED:
            raise ValueError(f"pg-nuts samples in the non-centred coordinates; got sampler_kw['coords'] = "
                             f"{self.coords!r} (use method='nuts' for the whitened ones)")
        if int(self.pg_every) < 1 or int(self.pg_particles) < 2:
            raise ValueError(f"pg-nuts needs pg_every >= 1 and pg_particles >= 2, got "
                             f"{self.pg_every} and {self.pg_particles}")
        scales = self.mode_scales()
        if not (0 < float(self.pg_mode_delta) <= 1 and scales.ndim == 1 and scales.size and np.all(scales > 0)
                and int(self.pg_mode_starts) >= 1 and int(self.pg_block_sweeps) >= 1):
            raise ValueError(f"pg-nuts needs 0 < pg_mode_delta <= 1, pg_mode_scale > 0, pg_mode_starts "
                             f">= 1 and pg_block_sweeps >= 1, got {self.pg_mode_delta}, "
                             f"{self.pg_mode_scale}, {self.pg_mode_starts} and {self.pg_block_sweeps}")
        super().__post_init__()

    def mode_scales(self) -> np.ndarray:
        """``pg_mode_scale`` as a 1-D array (one copy of each mode per scale)."""
        return np.atleast_1d(np.asarray(self.pg_mode_scale, dtype=np.float64))

    def settings(self) -> dict:
        """The particle Gibbs settings, JSON-ready, as the diagnostics record them."""
        return {"pg_every": int(self.pg_every), "pg_particles": int(self.pg_particles),
                "pg_h": [float(h) for h in np.atleast_1d(self.pg_h)],
                "pg_lookahead": bool(self.pg_lookahead), "pg_mode_centres": bool(self.pg_mode_centres),
                "pg_backward": bool(self.pg_backward), "pg_frame_tries": int(self.pg_frame_tries),
                "pg_frame_modes": bool(self.pg_frame_modes), "pg_block_len": int(self.pg_block_len),
                "pg_neighbours": bool(self.pg_neighbours), "pg_pairs": bool(self.pg_pairs),
                "pg_adapt_weights": bool(self.pg_adapt_weights), "pg_block_sweeps": int(self.pg_block_sweeps),
                "pg_adapt_moments": bool(self.pg_adapt_moments), "pg_adapt_clusters": bool(self.pg_adapt_clusters),
                "pg_mode_delta": float(self.pg_mode_delta),
                "pg_mode_scale": [float(c) for c in self.mode_scales()],
                "pg_mode_starts": int(self.pg_mode_starts)}


def run(context: Context, options: Options) -> Output:
    """NUTS with the particle Gibbs moves (:func:`bayes_talk.posterior.methods.nuts.sample`),
    warm-up ``context.warmup`` (default ``PG_NUTS_BUDGET["warmup"]``); the particle Gibbs
    settings first in the diagnostics."""
    out = nuts.sample(context, options, PG_NUTS_BUDGET["warmup"])
    out.diagnostics = {**options.settings(), **out.diagnostics}
    return out
