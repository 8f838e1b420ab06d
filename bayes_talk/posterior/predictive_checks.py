"""Prior and posterior predictive checks of the synthesis model (docs/uncertainty.md) through
``pyro.infer.Predictive`` on :func:`~bayes_talk.synthesis.joint.synthesis_model`.

* :func:`prior_predictive` - latents X and audio frames simulated from the model with the
  audio unobserved: X by ancestral sampling of the entry distributions and switching
  dynamics (:class:`~bayes_talk.synthesis.joint.SwitchingLatents`), each block's audio
  from its state's audio GP predictive; with ``with_smoothness=True`` also the smoothness
  factors' pseudo-observations u (:mod:`bayes_talk.synthesis.joint`, (S)), so that
  (X, audio, u) is a draw of the joint whose posterior p(X | audio, u) the samplers target
  with smoothness on (``make_plan(..., smooth_shift=u)``).
* :func:`posterior_predictive` - audio frames replicated at the latent draws of a
  synthesis posterior (``Predictive(..., posterior_samples={"X": draws})``).
* :func:`predictive_check` - the observed audio against replicated audio: for each
  statistic T (frame-wise mean, standard deviation, frame-to-frame difference energy
  of the MFCCs, and the per-entry PIT) the predictive p-value Pr(T(y_rep) ≥ T(y))
  (Gelman, Meng & Stern 1996), and the coverage of the central 50 % and 90 %
  predictive intervals of every audio entry. p-values near 0 or 1 and coverage far from
  nominal mean the model does not reproduce that aspect of the data.

The audio the model simulates and replicates is the **audio view** the state models
explain, ``plan.audio`` = ``model.audio_input(mfcc)``: the MFCCs themselves when the
model's ``audio_context`` is 0, the PCA-projected context window otherwise
(:mod:`bayes_talk.features.audio_context`). Compare replications with ``plan.audio``, never
with the raw MFCCs; and give simulated audio back to the samplers with ``audio_view=True``
(:func:`~bayes_talk.posterior.sampling.sample_synthesis`,
:func:`~bayes_talk.synthesis.joint.make_plan`), so that it is not spliced and projected a
second time.

Both simulations run on one torch thread (:func:`~bayes_talk.gp.threads.torch_threads`, as
the samplers do): every site is a small GP predictive, and a second thread cost more than it
gave (200 prior simulations of a 20-frame toy plan: 6x slower on two threads with the other
core busy, the same numbers).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyro
import torch
from pyro.infer import Predictive

from bayes_talk.gp.threads import torch_threads
from bayes_talk.synthesis.joint import UtterancePlan, synthesis_model


def _audio_sites(plan: UtterancePlan) -> list[str]:
    return [f"audio_{i}" for i in range(len(plan.blocks))]


def _stack_audio(plan: UtterancePlan, out: dict) -> np.ndarray:
    return np.concatenate([out[s].detach().numpy() for s in _audio_sites(plan)], axis=1)


def _smooth_sites(plan: UtterancePlan) -> dict[str, int]:
    return {f"smooth_{i}": b.start for i, b in enumerate(plan.blocks) if b.smooth}


def prior_predictive(plan: UtterancePlan, n: int, seed: int = 0, with_smoothness: bool = False):
    """n simulations (X (n, T, d), audio (n, T, D_y)) from the synthesis model's prior; the
    audio is in the plan's audio view (module docstring). ``with_smoothness``: also the
    smoothness factors' pseudo-observations u (n, T, D_z) (row a of a block start with a
    factor; zero elsewhere), returned third."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    sm = _smooth_sites(plan) if with_smoothness else {}
    pyro.set_rng_seed(seed)
    with torch.no_grad(), torch_threads(1):
        out = Predictive(synthesis_model, num_samples=n, return_sites=["X"] + _audio_sites(plan) + list(sm))(plan, None)
    X = out["X"].detach().numpy().reshape(n, plan.n_frames, plan.latent_dim)
    if not with_smoothness:
        return X, _stack_audio(plan, out)
    U = np.zeros((n, plan.n_frames, len(plan.motion_var)))
    for site, a in sm.items():
        U[:, a] = out[site].detach().numpy().reshape(n, -1)
    return X, _stack_audio(plan, out), U


def posterior_predictive(plan: UtterancePlan, latents: np.ndarray, seed: int = 0) -> np.ndarray:
    """Audio (S, T, D_y) replicated at latent draws ``latents`` (..., T, d) (chains pooled), in
    the plan's audio view: compare with ``plan.audio``."""
    X = np.asarray(latents, dtype=np.float64).reshape(-1, plan.n_frames, plan.latent_dim)
    pyro.set_rng_seed(seed)
    with torch.no_grad(), torch_threads(1):
        out = Predictive(synthesis_model, posterior_samples={"X": torch.as_tensor(X)},
                         return_sites=_audio_sites(plan))(plan, None)
    return _stack_audio(plan, out)


def _statistics(Y: np.ndarray) -> dict[str, np.ndarray]:
    """Test statistics of audio (..., T, D): mean and sd over frames, mean squared
    frame-to-frame difference, per MFCC coefficient."""
    return {"mean": Y.mean(-2), "sd": Y.std(-2), "delta_energy": np.mean(np.diff(Y, axis=-2) ** 2, axis=-2)}


@dataclass
class PredictiveCheck:
    """p_values: {statistic: (D,) Pr(T(y_rep) ≥ T(y)) per coefficient}; coverage: {level:
    fraction of audio entries inside the central predictive interval}; pit: (T, D) fraction
    of replications below each observed entry; n_rep: replications."""

    p_values: dict[str, np.ndarray]
    coverage: dict[float, float]
    pit: np.ndarray
    n_rep: int

    def extreme(self, alpha: float = 0.01) -> dict[str, int]:
        """Per statistic, the coefficients whose p-value lies outside [alpha, 1 − alpha]."""
        return {k: int(np.sum((p < alpha) | (p > 1 - alpha))) for k, p in self.p_values.items()}

    def to_dict(self) -> dict:
        """JSON-able form of the check (p-values, coverage, PIT)."""
        return {"p_values": {k: v.tolist() for k, v in self.p_values.items()},
                "coverage": {str(k): v for k, v in self.coverage.items()}, "n_rep": self.n_rep,
                "extreme_p_values": self.extreme(), "pit_mean": float(self.pit.mean())}


def predictive_check(observed: np.ndarray, replicated: np.ndarray, levels=(0.5, 0.9)) -> PredictiveCheck:
    """Compare the observed audio (T, D) with replications (S, T, D) of the prior or posterior
    predictive (see the module docstring)."""
    y = np.asarray(observed, dtype=np.float64)
    rep = np.asarray(replicated, dtype=np.float64)
    if rep.ndim != 3 or rep.shape[1:] != y.shape:
        raise ValueError(f"replicated: expected (S, {y.shape[0]}, {y.shape[1]}), got {rep.shape}")
    if rep.shape[0] < 2:
        raise ValueError(f"need at least 2 replications, got {rep.shape[0]}")
    t_obs, t_rep = _statistics(y), _statistics(rep)
    p = {k: np.mean(t_rep[k] >= t_obs[k][None], axis=0) for k in t_obs}
    cov = {}
    for q in levels:
        lo, hi = np.quantile(rep, [0.5 - q / 2, 0.5 + q / 2], axis=0)
        cov[float(q)] = float(np.mean((y >= lo) & (y <= hi)))
    return PredictiveCheck(p, cov, np.mean(rep < y[None], axis=0), int(rep.shape[0]))


__all__ = ["PredictiveCheck", "posterior_predictive", "predictive_check", "prior_predictive"]
