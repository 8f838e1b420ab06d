"""The synthesis model of a whole utterance, as one Pyro program (DESIGN.md §6).

Given a trained switching SGPDM (hyperparameters, training latents and entry
distributions fixed at their MAP values) and an utterance's audio Ŷ (T×D_y) and frame
labels, the latent trajectory X* (T×d) has the density

    p(X* | Ŷ) ∝ Π_blocks [ p(x_a | ·) · Π_{t=a+1}^{b−1} p_π(x_t | x_{t−1}) · Π_{t=a}^{b−1} p_π(ŷ_t | x_t) ]
                · Π_boundaries s(x_{a−1}, x_a)

over the segmentation into blocks [a, b) with state model π (deena2010 §4.2.1, after
back-off to the longest suffix with a model):

* p_π(x_t | x_{t−1}) = N(x_t; μ_x(x_{t−1}), σ²_x(x_{t−1}) I): π's dynamics GP predictive
  (deena2010 eq. 11, DESIGN.md §4);
* p_π(ŷ_t | x_t) = Π_m N(ŷ_tm; μ_Y,m(x_t), σ²_Y(x_t)/w_m²): π's audio GP predictive
  (deena2009 eq. 9's likelihood term);
* the block's first point: the entry distribution N(μ_π, Σ_π) (deena2010 eq. 12) when the
  state model changes at a (or a = 0); when the previous block has the *same* state model
  (long phones give runs of one VLMM state; back-off maps several states to one model),
  the blocks are one stretch of π's dynamics: p(x_a | ·) = p_π(x_a | x_{a−1});
* s: the smoothness factor across a change of state model (deena2010 §4.2.3, our reading
  in DESIGN.md §5) — the new block's first point must explain the last frame of the
  previous one: s = N(μ_Z^{π'}(x_{a−1}); μ_Z^π(x_a), σ²_Z^π(x_a)/w² + s²_Δ), π' the previous
  block's model, s²_Δ the mean square frame-to-frame motion of the training visual features.

Relation to deena2010's Algorithm 1: Algorithm 1 maximises this density one block at a
time, left to right, each block given the previous block's result (so it ignores a
block's effect on the next one's smoothness factor), and it puts the entry density on
every block's first point, also after a block of the same model. The MAP of this model
is the joint maximum; Algorithm 1's path is where :mod:`bayes_talk.synthesis.posterior`
starts the joint optimisation.

Two implementations of the same log density:

* :func:`synthesis_model` — the Pyro program: ``X`` is a sample site of
  :class:`SwitchingLatents` (entries and dynamics; ancestral sampling for simulation), the
  audio frames are observed sites, the smoothness factors are ``pyro.factor`` sites.
  :func:`pyro_log_density` is its trace's log joint. This is the reference.
* :class:`~bayes_talk.synthesis.joint_density.UtteranceDensity` (re-exported here) — the closed-form numpy twin with its gradient
  (:class:`~bayes_talk.synthesis.segment_objective._NumpyGP`), used by the optimiser and
  the samplers for speed; a test checks it equals the Pyro log joint to 1e-8 relative.

Every GP predictive goes through Cholesky factors and triangular solves, float64.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import pyro
import pyro.distributions as dist
import torch
from pyro.distributions import TorchDistribution
from torch.distributions import constraints

from bayes_talk.gp.distributions import NO_SHAPE
from bayes_talk.models.vlmm import Segment
from bayes_talk.synthesis.joint_density import UtteranceDensity

if TYPE_CHECKING:
    from bayes_talk.models.switching import SwitchingModel

SMOOTHNESS = ("frame", "off")


@dataclass
class Block:
    """One segment [start, stop) of the utterance and the state model that explains it.

    linked: the previous block has the same state model, so x_start follows its dynamics
    from x_{start−1} (no entry density, no smoothness factor). smooth: a smoothness factor
    couples x_{start−1} (previous block's visual GP) and x_start (this block's).
    """

    start: int
    stop: int
    key: tuple[str, ...]
    model: object  # the state's fitted SGPDM
    entry_mean: np.ndarray
    entry_cov: np.ndarray
    linked: bool
    smooth: bool

    def __post_init__(self) -> None:
        self.entry_chol = np.linalg.cholesky(self.entry_cov)
        self.entry_logdet_half = float(np.log(np.diag(self.entry_chol)).sum())

    @property
    def length(self) -> int:
        """Number of frames of the block."""
        return self.stop - self.start


@dataclass
class UtterancePlan:
    """Everything the synthesis density needs besides X: the blocks, the audio, the
    motion variance s²_Δ of the smoothness factor, the latent dimension, and the explicit
    mean function c_t of the visual mapping (``SwitchingConfig.context_mean``; None: zero),
    which the visual predictive adds to every component."""

    blocks: list[Block]
    audio: np.ndarray  # (T, D_y)
    motion_var: np.ndarray  # (D_z,)
    latent_dim: int
    segments: list[Segment]
    visual_offset: np.ndarray | None = None  # (T, D_z)

    @property
    def n_frames(self) -> int:
        """Frames T of the utterance."""
        return int(self.audio.shape[0])

    @property
    def model_states(self) -> list[tuple[str, ...]]:
        """The state whose model synthesises each block (after back-off)."""
        return [b.key for b in self.blocks]


def make_plan(model: SwitchingModel, mfcc: np.ndarray, labels, smoothness: str = "frame",
              audio_view: bool = False) -> UtterancePlan:
    """Segment ``labels`` with the model's states and assemble the blocks of the density.

    ``mfcc`` is the utterance's MFCCs (T, D_y), turned into the audio view the state models
    explain by ``model.audio_input`` (the identity, or the context window of
    :mod:`bayes_talk.features.audio_context`); with ``audio_view=True`` it is that view
    already (``plan.audio`` of another plan, audio simulated by
    :func:`~bayes_talk.synthesis.predictive_checks.prior_predictive`) and is used as it is."""
    if smoothness not in SMOOTHNESS:
        raise ValueError(f"smoothness must be one of {SMOOTHNESS}, got {smoothness!r}")
    segments = model.segment(list(labels))
    blocks: list[Block] = []
    for seg in segments:
        key, m = model.model_for(seg.state)
        linked = bool(blocks) and blocks[-1].key == key and m.dynamics_predictor_ is not None
        smooth = bool(blocks) and not linked and smoothness == "frame"
        mu, cov = model.entry_[key]
        blocks.append(Block(seg.start, seg.stop, key, m, np.asarray(mu, np.float64),
                            np.asarray(cov, np.float64), linked, smooth))
    audio = np.asarray(mfcc, dtype=np.float64) if audio_view else model.audio_input(mfcc, labels)
    offset = model.visual_offset(audio) if model.config.context_mean else None
    return UtterancePlan(blocks, audio, np.asarray(model.motion_var_, np.float64),
                         int(model.config.latent_dim), segments, offset)


# ------------------------------------------------------------------------------ Pyro program
class SwitchingLatents(TorchDistribution):
    """The prior part of the density: entry distributions and switching GP dynamics of X (T×d).

    ``log_prob`` sums, over blocks, ln N(x_a; μ_π, Σ_π) (or ln p_π(x_a | x_{a−1}) for a linked
    block) and ln p_π(x_t | x_{t−1}) inside the block. ``sample`` draws X ancestrally.
    """

    arg_constraints: ClassVar[dict] = {}
    support = constraints.real

    def __init__(self, plan: UtterancePlan):
        self.plan = plan
        super().__init__(torch.Size(), torch.Size((plan.n_frames, plan.latent_dim)), validate_args=False)

    def log_prob(self, X: torch.Tensor) -> torch.Tensor:
        """Joint log density of the utterance's latents (the class docstring's sum)."""
        lp = X.new_zeros(())
        for b in self.plan.blocks:
            a, e = b.start, b.stop
            dyn = b.model.dynamics_predictor_
            if b.linked:
                lp = lp + dyn.log_lik(X[a:a + 1], X[a - 1:a]).sum()
            else:
                mvn = dist.MultivariateNormal(torch.as_tensor(b.entry_mean), torch.as_tensor(b.entry_cov))
                lp = lp + mvn.log_prob(X[a])
            if e - a > 1 and dyn is not None:
                lp = lp + dyn.log_lik(X[a + 1:e], X[a:e - 1]).sum()
        return lp

    def sample(self, sample_shape: torch.Size = NO_SHAPE) -> torch.Tensor:
        """Ancestral draws: entry distribution at each unlinked block start, then the block model's GP dynamics."""
        if sample_shape != torch.Size():
            return torch.stack([self.sample() for _ in range(int(np.prod(sample_shape)))]).reshape(
                sample_shape + self.event_shape)
        T, d = self.event_shape
        X = torch.zeros(T, d, dtype=torch.float64)
        with torch.no_grad():
            for b in self.plan.blocks:
                dyn = b.model.dynamics_predictor_
                for t in range(b.start, b.stop):
                    if t == b.start and not b.linked:
                        mvn = dist.MultivariateNormal(torch.as_tensor(b.entry_mean), torch.as_tensor(b.entry_cov))
                        X[t] = mvn.sample()
                    elif dyn is None:
                        X[t] = X[t - 1]
                    else:
                        mu, var = dyn.mean_var(X[t - 1:t])
                        X[t] = mu[0] + var.sqrt() * torch.randn(d, dtype=torch.float64)
        return X


def _obs_dist(pred, X: torch.Tensor) -> dist.Distribution:
    """Π_t Π_m N(·; μ_m(x_t), σ²(x_t)/w_m²) as one distribution over a (T, D) block."""
    mu, var = pred.mean_var(X)
    return dist.Normal(mu, (pred.dim_var(var)).sqrt()).to_event(2)


def _smooth_factor(prev_vis, vis, x_prev: torch.Tensor, x: torch.Tensor, motion_var: torch.Tensor) -> torch.Tensor:
    z_prev, _ = prev_vis.mean_var(x_prev)
    return vis.log_lik(z_prev, x, motion_var).sum()


def synthesis_model(plan: UtterancePlan, audio: torch.Tensor | None = None) -> torch.Tensor:
    """The whole-utterance synthesis model as a Pyro program (see the module docstring).

    ``audio`` given: the frames are observed (conditioning); None: they are sampled (prior
    predictive). The smoothness factors are ``pyro.factor`` sites: they shape the posterior
    but are not part of ancestral simulation.
    """
    X = pyro.sample("X", SwitchingLatents(plan))
    mv = torch.as_tensor(plan.motion_var)
    for i, b in enumerate(plan.blocks):
        a, e = b.start, b.stop
        obs = None if audio is None else audio[a:e]
        pyro.sample(f"audio_{i}", _obs_dist(b.model.predictors_["audio"], X[a:e]), obs=obs)
        if b.smooth:
            prev = plan.blocks[i - 1].model.predictors_["visual"]
            pyro.factor(f"smooth_{i}", _smooth_factor(prev, b.model.predictors_["visual"], X[a - 1:a], X[a:a + 1], mv))
    return X


def pyro_log_density(plan: UtterancePlan, X: torch.Tensor | np.ndarray) -> torch.Tensor:
    """ln p(X, Ŷ) of :func:`synthesis_model`'s trace at X (the unnormalised log posterior)."""
    X = torch.as_tensor(np.asarray(X, dtype=np.float64)) if not torch.is_tensor(X) else X
    audio = torch.as_tensor(plan.audio)
    tr = pyro.poutine.trace(pyro.poutine.condition(synthesis_model, data={"X": X})).get_trace(plan, audio)
    return tr.log_prob_sum()


__all__ = ["Block", "SwitchingLatents", "UtteranceDensity", "UtterancePlan", "make_plan", "pyro_log_density",
           "synthesis_model"]
