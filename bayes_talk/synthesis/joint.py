"""The synthesis model of a whole utterance, as one Pyro program (docs/uncertainty.md).

Given a trained switching SGPDM (hyperparameters, training latents and entry
distributions fixed at their MAP values) and an utterance's audio Ŷ (T×D_y) and frame
labels, the latent trajectory X* (T×d) has the density

    p(X* | Ŷ) ∝ Π_blocks [ p(x_a | ·) · Π_{t=a+1}^{b−1} p_π(x_t | x_{t−1}) · Π_{t=a}^{b−1} p_π(ŷ_t | x_t) ]
                · Π_boundaries s(x_{a−1}, x_a)

over the segmentation into blocks [a, b) with state model π (deena2010 §4.2.1, after
back-off to the longest suffix with a model):

* p_π(x_t | x_{t−1}) = N(x_t; μ_x(x_{t−1}), σ²_x(x_{t−1}) I): π's dynamics GP predictive
  (deena2010 eq. 11; docs/model.md);
* p_π(ŷ_t | x_t) = Π_m N(ŷ_tm; μ_Y,m(x_t), σ²_Y(x_t)/w_m²): π's audio GP predictive
  (deena2009 eq. 9's likelihood term);
* the block's first point: the entry distribution N(μ_π, Σ_π) (deena2010 eq. 12) when the
  state model changes at a (or a = 0); when the previous block has the *same* state model
  (long phones give runs of one VLMM state; back-off maps several states to one model),
  the blocks are one stretch of π's dynamics: p(x_a | ·) = p_π(x_a | x_{a−1});
* s: the smoothness factor across a change of state model (deena2010 §4.2.3, our reading
  in docs/switching.md) — the new block's first point must explain the last frame of the
  previous one: s = N(μ_Z^{π'}(x_{a−1}); μ_Z^π(x_a), σ²_Z^π(x_a)/w² + s²_Δ), π' the previous
  block's model, s²_Δ the mean square frame-to-frame motion of the training visual features.

**The smoothness factor as a pseudo-observation.** s is the density at u_a = 0 of

    u_a | X ~ N(μ_Z^π(x_a) − μ_Z^{π'}(x_{a−1}), σ²_Z^π(x_a)/w² + s²_Δ)                    (S)

(the jump between the new block's visual frame, drawn from its visual predictive plus the
frame-to-frame motion, and the previous block's last mean frame), since
N(0; μ − μ', V) = N(μ'; μ, V). So the product is p(X | Ŷ, u = 0) of the generative model
X ~ entries and dynamics, Ŷ | X ~ audio predictives, u | X ~ (S): the latents' prior has no
smoothness term and can be simulated ancestrally, and simulation-based calibration with
smoothness on simulates (X, Ŷ, u) and samples p(X | Ŷ, u) (``UtterancePlan.smooth_shift`` = u;
zero, the product of the papers, by default).

Relation to deena2010's Algorithm 1: Algorithm 1 maximises this density one block at a
time, left to right, each block given the previous block's result (so it ignores a
block's effect on the next one's smoothness factor), and it puts the entry density on
every block's first point, also after a block of the same model. The MAP of this model
is the joint maximum; Algorithm 1's path is where :mod:`bayes_talk.posterior.sampling`
starts the joint optimisation.

Two implementations of the same log density:

* :func:`synthesis_model` — the Pyro program: ``X`` is a sample site of
  :class:`SwitchingLatents` (entries and dynamics; ancestral sampling for simulation), the
  audio frames are observed sites, the smoothness factors are ``pyro.factor`` sites.
  :func:`pyro_log_density` is its trace's log joint. This is the reference.
* :class:`UtteranceDensity` — the closed-form numpy twin with its gradient, a value-only
  variant and its Hessian, used by the optimiser and the samplers for speed: every GP
  predictive through the compiled, packed predictives of :mod:`bayes_talk.gp.predictive_fused`.
  A test checks it equals the Pyro log joint to 1e-8 relative (``tests/posterior/test_posterior.py``).

This module stays above ~500 lines because the two are one density and live in one module: a
change to a term of the program must be made to its twin in the same edit. The program's face
sites (:func:`face_model`) are the observation term of :mod:`bayes_talk.synthesis.face_noise`.

Every GP predictive goes through Cholesky factors and triangular solves, float64.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import pyro
import pyro.distributions as dist
import torch
from pyro.distributions import TorchDistribution
from torch.distributions import constraints

from bayes_talk.gp.distributions import NO_SHAPE
from bayes_talk.gp.numpy_gp import numpy_gp
from bayes_talk.gp.predictive_fused import LOG_2PI, PackedGPs, Runs
from bayes_talk.models.vlmm import Segment
from bayes_talk.synthesis.banded import BlockTridiagonal

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
    #: the pseudo-observations u_a of the smoothness factors (module docstring, (S)), row a
    #: for a block starting at a with a factor, other rows unused; None: u = 0 (the product)
    smooth_shift: np.ndarray | None = None  # (T, D_z)

    @property
    def n_frames(self) -> int:
        """Frames T of the utterance."""
        return int(self.audio.shape[0])

    @property
    def model_states(self) -> list[tuple[str, ...]]:
        """The state whose model synthesises each block (after back-off)."""
        return [b.key for b in self.blocks]


def make_plan(model: SwitchingModel, mfcc: np.ndarray, labels, smoothness: str = "frame",
              audio_view: bool = False, smooth_shift: np.ndarray | None = None) -> UtterancePlan:
    """Segment ``labels`` with the model's states and assemble the blocks of the density.

    ``mfcc`` is the utterance's MFCCs (T, D_y), turned into the audio view the state models
    explain by ``model.audio_input`` (the identity, or the context window of
    :mod:`bayes_talk.features.audio_context`); with ``audio_view=True`` it is that view
    already (``plan.audio`` of another plan, audio simulated by
    :func:`~bayes_talk.posterior.predictive_checks.prior_predictive`) and is used as it is.
    ``smooth_shift`` (T, D_z): the smoothness factors' pseudo-observations u (module
    docstring (S); simulated ones in simulation-based calibration); None: u = 0."""
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
    motion_var = np.asarray(model.motion_var_, np.float64)
    if smooth_shift is not None:
        smooth_shift = np.asarray(smooth_shift, dtype=np.float64)
        want = (audio.shape[0], motion_var.shape[0])
        if smooth_shift.shape != want or not np.all(np.isfinite(smooth_shift)):
            raise ValueError(f"smooth_shift: expected finite values of shape (frames, visual dims) = {want}, "
                             f"got shape {smooth_shift.shape}")
    return UtterancePlan(blocks, audio, motion_var, int(model.config.latent_dim), segments, offset, smooth_shift)


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


def _smooth_dist(prev_vis, vis, x_prev: torch.Tensor, x: torch.Tensor, motion_var: torch.Tensor) -> dist.Distribution:
    """(S) of the module docstring: N(μ_Z^π(x_a) − μ_Z^{π'}(x_{a−1}), σ²_Z^π(x_a)/w² + s²_Δ) over (D_z,)."""
    z_prev, _ = prev_vis.mean_var(x_prev)
    mu, var = vis.mean_var(x)
    return dist.Normal((mu - z_prev)[0], (vis.dim_var(var)[0] + motion_var).sqrt()).to_event(1)


def synthesis_model(plan: UtterancePlan, audio: torch.Tensor | None = None) -> torch.Tensor:
    """The whole-utterance synthesis model as a Pyro program (see the module docstring).

    ``audio`` given: the frames are observed (conditioning), and so are the smoothness
    factors' pseudo-observations ``smooth_{i}`` at ``plan.smooth_shift`` (zero by default:
    the factor s); None: both are sampled (the prior predictive; (S) of the module docstring).
    """
    X = pyro.sample("X", SwitchingLatents(plan))
    mv = torch.as_tensor(plan.motion_var)
    for i, b in enumerate(plan.blocks):
        a, e = b.start, b.stop
        obs = None if audio is None else audio[a:e]
        pyro.sample(f"audio_{i}", _obs_dist(b.model.predictors_["audio"], X[a:e]), obs=obs)
        if b.smooth:
            prev = plan.blocks[i - 1].model.predictors_["visual"]
            u = None if audio is None else (torch.zeros(len(plan.motion_var), dtype=torch.float64)
                                            if plan.smooth_shift is None else torch.as_tensor(plan.smooth_shift[a]))
            pyro.sample(f"smooth_{i}", _smooth_dist(prev, b.model.predictors_["visual"], X[a - 1:a], X[a:a + 1], mv),
                        obs=u)
    return X


def face_model(plan: UtterancePlan, X: torch.Tensor, noise, labels) -> torch.Tensor:
    """The face given the latent path X: the visual GP predictive of each block's state
    model followed by the observation term ``noise`` (a
    :class:`~bayes_talk.synthesis.face_noise.FaceNoise`; (N1) of that module), as Pyro
    sites ``face_gp_{i}`` and ``face_{i}`` per block; returns the face (T, D_z). Nothing
    here is observed at synthesis (the audio is), so these sites leave the posterior of X
    unchanged; run after :func:`synthesis_model`, they draw the face that every inference
    method's predictive describes (:meth:`FaceNoise.apply`)."""
    shrink, gp_scale = torch.as_tensor(noise.shrink), torch.as_tensor(noise.gp_scale)
    tau = torch.as_tensor(noise.class_scale(labels))
    dof = torch.as_tensor(np.minimum(noise.dof, 1e6))
    faces = []
    for i, b in enumerate(plan.blocks):
        a, e = b.start, b.stop
        vis = b.model.predictors_["visual"]
        mu, var = vis.mean_var(X[a:e])
        c = (torch.zeros_like(mu) if plan.visual_offset is None
             else torch.as_tensor(plan.visual_offset[a:e]))
        f = pyro.sample(f"face_gp_{i}", dist.Normal(c + shrink * mu, (gp_scale * vis.dim_var(var)).sqrt()
                                                    .clamp_min(1e-150)).to_event(2))
        faces.append(pyro.sample(f"face_{i}", dist.StudentT(dof.expand_as(f), f, tau[a:e]).to_event(2)))
    return torch.cat(faces)


def pyro_log_density(plan: UtterancePlan, X: torch.Tensor | np.ndarray) -> torch.Tensor:
    """ln p(X, Ŷ) of :func:`synthesis_model`'s trace at X (the unnormalised log posterior)."""
    X = torch.as_tensor(np.asarray(X, dtype=np.float64)) if not torch.is_tensor(X) else X
    audio = torch.as_tensor(plan.audio)
    tr = pyro.poutine.trace(pyro.poutine.condition(synthesis_model, data={"X": X})).get_trace(plan, audio)
    return tr.log_prob_sum()


__all__ = ["Block", "SwitchingLatents", "UtteranceDensity", "UtterancePlan", "face_model", "make_plan",
           "pyro_log_density", "synthesis_model"]


# ---------------------------------------------------------------------------------------
# the closed-form numpy twin
# ---------------------------------------------------------------------------------------

class UtteranceDensity:
    """The same log density in closed form with its gradient (numpy), for speed.

    ``__call__(X)`` returns (ln p, ∂ ln p/∂X) for X of shape (T, d); :meth:`batch` does K
    points at once. The terms are grouped once per plan (:class:`_Terms`): all audio terms
    of the utterance go through one compiled call over the packed audio GPs of its state
    models (:class:`~bayes_talk.gp.predictive_fused.PackedGPs`), all dynamics steps through
    another, the smoothness factors through three, each model's Cholesky factor read once
    per call. ``hessian(X)`` is exact-gradient central differences term by term: each term
    depends on one frame (audio) or one pair of neighbouring frames (dynamics, smoothness),
    so its d×d or 2d×2d Hessian block comes from 2·d or 2·2d perturbed copies of its own
    rows; the entry densities' blocks are exact (−Σ_π⁻¹). The result is block-tridiagonal
    and is kept so (:class:`~bayes_talk.synthesis.banded.BlockTridiagonal`).
    """

    def __init__(self, plan: UtterancePlan, terms: _Terms | None = None, n_frames: int | None = None):
        self.plan = plan
        self.T, self.d = plan.n_frames if n_frames is None else int(n_frames), plan.latent_dim
        self.n_evals = 0
        self.terms = _Terms(plan) if terms is None else terms

    def window(self, lo: int, hi: int) -> tuple[UtteranceDensity, slice]:
        """The part of ln p that depends on frames [lo, hi): a density over frames
        [lo − 1, hi + 1) ∩ [0, T) (the window and the neighbour each side, which its conditional
        holds fixed) made of the terms that read a frame of the window, and where the window's
        frames sit in it. Its gradient and Hessian in the window's frames are those of the
        whole density (the other terms do not depend on them)."""
        if not 0 <= lo < hi <= self.T:
            raise ValueError(f"window [{lo}, {hi}) is not inside the utterance's {self.T} frames")
        a, b = max(lo - 1, 0), min(hi + 1, self.T)
        return UtteranceDensity(self.plan, self.terms.restricted(lo, hi, a), b - a), slice(lo - a, hi - a)

    def __call__(self, X: np.ndarray) -> tuple[float, np.ndarray]:
        X = np.asarray(X, dtype=np.float64).reshape(self.T, self.d)
        lp, G = self.batch(X[None])
        return float(lp[0]), G[0]

    def batch(self, Xb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ln p, ∂ ln p/∂X) at K points at once: Xb (K, T, d) → ((K,), (K, T, d)).
        The K copies of each term's row are laid out next to each other (one GP run)."""
        Xb = np.asarray(Xb, dtype=np.float64).reshape(-1, self.T, self.d)
        K, d = Xb.shape[0], self.d
        self.n_evals += K
        tm = self.terms
        lp = np.zeros(K)
        G = np.zeros_like(Xb)

        def rows(idx: np.ndarray) -> np.ndarray:      # frames idx of every point, row-major by frame
            return Xb[:, idx].transpose(1, 0, 2).reshape(-1, d)

        def add(idx: np.ndarray, g: np.ndarray) -> None:
            G[:, idx] += g.reshape(len(idx), K, d).transpose(1, 0, 2)

        if len(tm.a_idx):
            ll, gx = tm.audio_grad(rows(tm.a_idx), K)
            lp += ll.reshape(-1, K).sum(0)
            add(tm.a_idx, gx)
        if len(tm.d_src):
            ll, g = tm.dynamics_grad(np.concatenate([rows(tm.d_src), rows(tm.d_dst)], 1), K)
            lp += ll.reshape(-1, K).sum(0)
            add(tm.d_src, g[:, :d])
            add(tm.d_dst, g[:, d:])
        if len(tm.e_idx):
            ll, g = tm.entry_grad(Xb[:, tm.e_idx])
            lp += ll
            G[:, tm.e_idx] += g
        if len(tm.s_idx):
            ll, g = tm.smooth_grad(np.concatenate([rows(tm.s_idx - 1), rows(tm.s_idx)], 1), K)
            lp += ll.reshape(-1, K).sum(0)
            add(tm.s_idx - 1, g[:, :d])
            add(tm.s_idx, g[:, d:])
        return lp, G

    def values(self, Xb: np.ndarray) -> np.ndarray:
        """ln p at K points (K, T, d) → (K,), without the gradient: only the forward
        substitutions of the predictive variances (emcee's walkers, the k̂ draws)."""
        Xb = np.asarray(Xb, dtype=np.float64).reshape(-1, self.T, self.d)
        K, d = Xb.shape[0], self.d
        self.n_evals += K
        tm = self.terms

        def rows(idx: np.ndarray) -> np.ndarray:
            return Xb[:, idx].transpose(1, 0, 2).reshape(-1, d)

        def gauss(y: np.ndarray, mu: np.ndarray, var: np.ndarray) -> np.ndarray:   # per-row ln N, summed per point
            r = y - mu
            return (-0.5 * (LOG_2PI + np.log(var) + r * r / var)).sum(1).reshape(-1, K).sum(0)

        lp = np.zeros(K)
        if len(tm.a_idx):
            mu, s = tm.audio_gps.mean_var(tm.a_runs.repeat(K), rows(tm.a_idx))
            lp += gauss(np.repeat(tm.a_Y, K, axis=0), mu, s[:, None] / tm.audio_gps.w2[tm.a_runs.row_gp(K)])
        if len(tm.d_src):
            mu, s = tm.dyn_gps.mean_var(tm.d_runs.repeat(K), rows(tm.d_src))
            lp += gauss(rows(tm.d_dst), mu, s[:, None] / tm.dyn_gps.w2[tm.d_runs.row_gp(K)])
        if len(tm.e_idx):
            lp += tm.entry_grad(Xb[:, tm.e_idx])[0]
        if len(tm.s_idx):
            lp += tm.smooth_grad(np.concatenate([rows(tm.s_idx - 1), rows(tm.s_idx)], 1), K)[0].reshape(-1, K).sum(0)
        return lp

    def hessian(self, X: np.ndarray, h: float = 1e-6) -> BlockTridiagonal:
        """The Hessian of ln p at X, block-tridiagonal (T blocks of d×d on the diagonal and the
        first off-diagonals; :class:`~bayes_talk.synthesis.banded.BlockTridiagonal`), term by
        term (class docstring), symmetrised: O(T·d²) memory, linear in the length."""
        X = np.asarray(X, dtype=np.float64).reshape(self.T, self.d)
        d = self.d
        H = BlockTridiagonal.zeros(self.T, d)
        tm = self.terms
        if len(tm.a_idx):
            H.diag[tm.a_idx] += _fd_blocks(lambda R, k: tm.audio_grad(R, k)[1], X[tm.a_idx], h)
        if len(tm.d_src):
            Hb = _fd_blocks(lambda R, k: tm.dynamics_grad(R, k)[1], np.concatenate([X[tm.d_src], X[tm.d_dst]], 1), h)
            _add_pairs(H, tm.d_src, Hb, d)
        if len(tm.e_idx):                                              # −Σ⁻¹ = −L⁻ᵀL⁻¹
            H.diag[tm.e_idx] -= np.einsum("eki,ekj->eij", tm.e_chol_inv, tm.e_chol_inv)
        if len(tm.s_idx):
            Hb = _fd_blocks(lambda R, k: tm.smooth_grad(R, k)[1], np.concatenate([X[tm.s_idx - 1], X[tm.s_idx]], 1), h)
            _add_pairs(H, tm.s_idx - 1, Hb, d)
        # the off-diagonal blocks of a pair term are ∂²/∂x_src∂x_dst and the transpose of the
        # other; their mean is the symmetric part, as ½(H + Hᵀ) of the dense matrix
        return H.symmetrised()


def _fd_blocks(grad, R: np.ndarray, h: float) -> np.ndarray:
    """Per-row Hessian blocks (n, m, m) of a sum of row-wise terms, by central differences:
    ``grad(rows, k)`` is the gradient of every row of a layout in which each of the n rows
    is repeated k times in place; here k = 2m (each coordinate perturbed by ±h)."""
    n, m = R.shape
    E = np.concatenate([h * np.eye(m), -h * np.eye(m)])              # (2m, m)
    Gp = grad((R[:, None, :] + E[None]).reshape(-1, m), 2 * m).reshape(n, 2 * m, m)
    return np.transpose((Gp[:, :m] - Gp[:, m:]) / (2 * h), (0, 2, 1))  # (n, i, j): ∂g_i/∂r_j


def _add_pairs(H: BlockTridiagonal, src: np.ndarray, Hb: np.ndarray, d: int) -> None:
    """Add 2d×2d blocks over the pairs (x_src, x_src+1) to the block-tridiagonal Hessian: the
    off-diagonal block (src, src+1) is the mean of ∂²/∂x_src∂x_dst and the transpose of
    ∂²/∂x_dst∂x_src (finite differences make them differ at round-off)."""
    H.diag[src] += Hb[:, :d, :d]
    H.diag[src + 1] += Hb[:, d:, d:]
    H.upper[src] += 0.5 * (Hb[:, :d, d:] + np.transpose(Hb[:, d:, :d], (0, 2, 1)))


class _Terms:
    """The density's terms as rows, grouped by GP once per plan.

    Audio rows: frames ``a_idx`` (sorted by state model) under the packed audio GPs;
    dynamics rows: steps x_src → x_dst (``d_src`` = ``d_dst`` − 1, inside blocks and across
    linked boundaries) under the packed dynamics GPs; smoothness rows: block starts
    ``s_idx`` (pairs x_{a−1}, x_a) under the packed visual GPs; entries: frames ``e_idx``
    (unlinked block starts) with μ_π and the inverse Cholesky factor of Σ_π. No frame repeats within a kind of row,
    so scattered gradients are added with fancy indexing. The ``*_grad`` methods take rows
    in which each term's row is repeated k times in place (k batched points or k perturbed
    copies) and return per-row (ℓ, gradient)."""

    def __init__(self, plan: UtterancePlan):
        packs: dict[str, dict[int, object]] = {"audio": {}, "dyn": {}, "vis": {}}

        def gp_index(kind: str, pred) -> int:
            """The index of predictor ``pred`` in the pack of its kind (added if new)."""
            pack = packs[kind]
            if id(pred) not in pack:
                pack[id(pred)] = numpy_gp(pred)
            return list(pack).index(id(pred))

        audio, dyn, smooth, entries = [], [], [], []
        blocks = plan.blocks
        for i, b in enumerate(blocks):
            a, e = b.start, b.stop
            g = gp_index("audio", b.model.predictors_["audio"])
            audio += [(g, t) for t in range(a, e)]
            lo = a - 1 if b.linked else a
            if b.model.dynamics_predictor_ is not None and e - lo > 1:
                g = gp_index("dyn", b.model.dynamics_predictor_)
                dyn += [(g, t) for t in range(lo + 1, e)]
            if not b.linked:
                entries.append(b)
            if b.smooth:
                smooth.append((gp_index("vis", blocks[i - 1].model.predictors_["visual"]),
                               gp_index("vis", b.model.predictors_["visual"]), a))
        audio.sort()
        dyn.sort()
        smooth.sort()
        self.audio_gps = PackedGPs(list(packs["audio"].values()))
        self.a_idx = np.array([t for _, t in audio], dtype=np.int64)
        self.a_runs = Runs.of(np.array([g for g, _ in audio]))
        self.a_Y = plan.audio[self.a_idx]
        self.dyn_gps = PackedGPs(list(packs["dyn"].values())) if dyn else None
        self.d_dst = np.array([t for _, t in dyn], dtype=np.int64)
        self.d_src = self.d_dst - 1
        self.d_runs = Runs.of(np.array([g for g, _ in dyn]))
        self.vis_gps = PackedGPs(list(packs["vis"].values())) if smooth else None
        self.s_idx = np.array([a for _, _, a in smooth], dtype=np.int64)   # sorted by the previous model
        self.s_prev_runs = Runs.of(np.array([p for p, _, _ in smooth]))
        order = np.argsort([v for _, v, _ in smooth], kind="stable")        # the same rows by this block's model
        self.s_order = order
        self.s_vis_runs = Runs.of(np.array([smooth[j][1] for j in order]))
        self.motion_var = plan.motion_var
        # pseudo-observations u_a per smoothness row (s_idx order): z_prev + u is the factor's "observation"
        self.s_shift = (np.zeros((len(self.s_idx), len(plan.motion_var))) if plan.smooth_shift is None
                        else np.asarray(plan.smooth_shift, dtype=np.float64)[self.s_idx].reshape(len(self.s_idx), -1))
        self.e_idx = np.array([b.start for b in entries], dtype=np.int64)
        self.e_mean = np.array([b.entry_mean for b in entries]).reshape(len(entries), plan.latent_dim)
        self.e_chol_inv = np.array([np.linalg.inv(b.entry_chol) for b in entries]).reshape(
            len(entries), plan.latent_dim, plan.latent_dim)
        self.e_consts = np.array([b.entry_logdet_half + 0.5 * plan.latent_dim * LOG_2PI for b in entries])
        self.e_const = float(self.e_consts.sum())

    def restricted(self, lo: int, hi: int, shift: int) -> _Terms:
        """The terms that read a frame of [lo, hi) (audio and entries there; the dynamics steps
        and smoothness pairs with either frame there), their frame indices less ``shift``: the
        window's own terms, which alone depend on its frames when the others are held fixed."""
        sub = copy.copy(self)

        def inside(idx: np.ndarray) -> np.ndarray:
            return (idx >= lo) & (idx < hi)

        m = inside(self.a_idx)
        sub.a_idx, sub.a_Y, sub.a_runs = self.a_idx[m] - shift, self.a_Y[m], Runs.of(self.a_runs.row_gp()[m])
        m = inside(self.d_dst) | inside(self.d_src)
        sub.d_dst, sub.d_runs = self.d_dst[m] - shift, Runs.of(self.d_runs.row_gp()[m])
        sub.d_src = sub.d_dst - 1
        m = inside(self.e_idx)
        sub.e_idx, sub.e_mean, sub.e_chol_inv = self.e_idx[m] - shift, self.e_mean[m], self.e_chol_inv[m]
        sub.e_consts = self.e_consts[m]
        sub.e_const = float(sub.e_consts.sum())
        m = inside(self.s_idx) | inside(self.s_idx - 1)
        vis_gp = np.empty(len(self.s_idx), dtype=np.int64)
        vis_gp[self.s_order] = self.s_vis_runs.row_gp()                    # this block's visual GP, by row
        sub.s_idx, sub.s_shift = self.s_idx[m] - shift, self.s_shift[m]
        sub.s_prev_runs = Runs.of(self.s_prev_runs.row_gp()[m])
        sub.s_order = np.argsort(vis_gp[m], kind="stable")
        sub.s_vis_runs = Runs.of(vis_gp[m][sub.s_order])
        return sub

    def entry_grad(self, Xe: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Σ_e ln N(x_e; μ_e, Σ_e) (K,) and its gradient (K, E, d) at the entry frames Xe (K, E, d)."""
        u = np.einsum("eij,kej->kei", self.e_chol_inv, Xe - self.e_mean)        # L_e⁻¹ (x − μ)
        return -0.5 * (u * u).sum((1, 2)) - self.e_const, -np.einsum("eji,kej->kei", self.e_chol_inv, u)

    def audio_grad(self, R: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-row ℓ and ∂ℓ/∂x of the audio terms at rows R (len(a_idx)·k, d)."""
        ll, gx, _ = self.audio_gps.loglik(self.a_runs.repeat(k), np.repeat(self.a_Y, k, axis=0), R)
        return ll, gx

    def dynamics_grad(self, R: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-row ℓ and ∂ℓ/∂(x_src, x_dst) of the dynamics steps at rows R = [x_src, x_dst]."""
        d = R.shape[1] // 2
        ll, g_in, g_out = self.dyn_gps.loglik(self.d_runs.repeat(k), R[:, d:], R[:, :d])
        return ll, np.concatenate([g_in, g_out], 1)

    def smooth_grad(self, R: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-row smoothness factor ln N(μ_Z^{π'}(x_{a−1}) + u_a; μ_Z^π(x_a), σ²_Z^π(x_a)/w² + s²_Δ)
        (u_a the pseudo-observation, 0 by default) and its gradient in (x_{a−1}, x_a) at rows
        R = [x_{a−1}, x_a] (through π''s visual mean)."""
        d = R.shape[1] // 2
        prev_runs = self.s_prev_runs.repeat(k)
        z_prev, _ = self.vis_gps.mean_var(prev_runs, R[:, :d])
        z_prev = z_prev + np.repeat(self.s_shift, k, axis=0)
        perm = (self.s_order[:, None] * k + np.arange(k)).reshape(-1)   # rows in this block's model order
        ll_p, g_a_p, g_z_p = self.vis_gps.loglik(self.s_vis_runs.repeat(k), z_prev[perm], R[perm, d:], self.motion_var)
        ll, g_a, g_z = np.empty_like(ll_p), np.empty_like(g_a_p), np.empty_like(g_z_p)
        ll[perm], g_a[perm], g_z[perm] = ll_p, g_a_p, g_z_p
        return ll, np.concatenate([self.vis_gps.mean_vjp(prev_runs, R[:, :d], g_z), g_a], 1)


__all__ = ["UtteranceDensity"]
