"""The shared GPDM as a generative model: its settings (:class:`SGPDMConfig`), the Pyro
program whose log joint MAP training maximises (:func:`sgpdm_model`, deena2010 eq. 1-7;
the module docstring of :mod:`bayes_talk.models.sgpdm` has the equations), the PCA
initialisation of the latents and the record of a fit."""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pyro
import pyro.distributions as dist
import torch
from pyro import poutine

from bayes_talk.gp.distributions import GPDynamics, GPObservation
from bayes_talk.gp.terms import W_PRIOR_VARIANCE, dynamics_loglik, observation_loglik

__all__ = ["FitHistory", "SGPDMConfig", "median_sq_dist", "pca_scores", "sgpdm_log_joint", "sgpdm_model",
           "trace_log_joint", "view_in_dims", "view_latents"]

@dataclass
class SGPDMConfig:
    """Settings of an :class:`SGPDM` (all documented in docs/model.md).

    latent_dim: d (8 in deena2009, 6 in deena2010).
    dynamics: GP dynamics on X (eq. 7); False gives a shared GPLVM with X ~ N(0, I).
    learn_dynamics: learn α_x, γ_x, β_x (then they carry the 1/θ prior) instead of fixing
        them at the signal-to-noise ratio 100:1 of deena2010 §4.1.
    dyn_alpha, dyn_gamma, dyn_beta: α_x, γ_x, β_x (precision) of the dynamics kernel.
    dyn_linear: α_lin of an optional linear term in the dynamics kernel (None: off).
    balanced: λ = D/d on ln p(X) (balanced GPDM, D = total observed dimension);
        False: λ = 1 (plain GPDM).
    back_constraint: name of the view g(·) maps from (deena2009 eq. 4–5), or None.
    bc_hidden: hidden tanh units of the back-constraint MLP.
    init: "pca-average" (PCA of each view to d, each scaled to unit variance per
        dimension, then averaged: deena2010 §4.1) or "pca-concat" (PCA of the
        concatenated standardised views).
    init_scale: the initial latent std per dimension; None gives √α_x with dynamics
        (the dynamics signal std, 0.1 by default) and 1 without.
    learn_w: learn the per-dimension output scales W (else W = 1/std of the data, fixed).
    max_iter: L-BFGS iterations; tol: stop when an outer step improves L by < tol·|L|.
    seed: seeds the back-constraint weights and anything random in fitting.
    view_dims: view name → k, the number of leading latent dimensions that view's GP reads
        (views not named read all d). A view given k < d leaves the last d − k dimensions
        *private* to the other views: shared and private latent spaces (Ek, Rihan, Torr,
        Rogez & Lawrence 2008, "Ambiguity modeling in latent spaces"). With
        ``{"audio": k}`` the audio constrains only the shared dimensions, and at synthesis
        the face's private dimensions are left to the dynamics and the entry density, so
        the posterior spreads where the audio does not determine the face. None: every view
        reads all d (the papers' model).
    """

    latent_dim: int = 8
    dynamics: bool = True
    learn_dynamics: bool = False
    dyn_alpha: float = 0.01
    dyn_gamma: float = 0.2
    dyn_beta: float = 1e6
    dyn_linear: float | None = None
    balanced: bool = False
    back_constraint: str | None = None
    bc_hidden: int = 20
    init: str = "pca-average"
    init_scale: float | None = None
    learn_w: bool = True
    max_iter: int = 300
    tol: float = 1e-9
    seed: int = 0
    view_dims: dict[str, int] | None = None


def view_in_dims(cfg: SGPDMConfig, view: str) -> int | None:
    """k when ``view``'s GP reads only the first k < d latent dimensions (``cfg.view_dims``),
    None when it reads all d (``GPPredictor.in_dims``)."""
    k = (cfg.view_dims or {}).get(view)
    return None if k is None or k >= cfg.latent_dim else k


def view_latents(X, cfg: SGPDMConfig, view: str):
    """The columns of the latents X (N, d) that ``view``'s GP reads (:func:`view_in_dims`)."""
    k = view_in_dims(cfg, view)
    if k is None:
        return X
    return X[:, :k].contiguous() if isinstance(X, torch.Tensor) else np.ascontiguousarray(X[:, :k])


def pca_scores(Y: np.ndarray, d: int) -> np.ndarray:
    """Scores of the first d principal components, each scaled to unit variance."""
    Yc = Y - Y.mean(0)
    U, S, _ = np.linalg.svd(Yc, full_matrices=False)
    Z = U[:, :d] * S[:d]
    # fix the sign so the largest-magnitude loading is positive (deterministic init)
    Z *= np.sign(Z[np.abs(Z).argmax(0), range(Z.shape[1])])
    return Z / np.maximum(Z.std(0), 1e-12)


def median_sq_dist(X: np.ndarray, block_elems: int = 1 << 20) -> float:
    """Median of ‖x_i − x_j‖² over the pairs i < j of the rows of X (N ≥ 2): the initial
    inverse width γ₀ = 1/median of the kernels. Computed a block of rows at a time (about
    ``block_elems`` differences each, 8 MB) instead of through the N×N×d array of all
    differences (144 MB at N = 1,500, d = 8); each distance is the same sum, so the
    median is the same bit for bit."""
    N, d = X.shape
    rows = max(1, block_elems // max(1, N * d))
    upper = []
    for a in range(0, N - 1, rows):
        b = min(a + rows, N - 1)
        sq = ((X[a:b, None, :] - X[None, :, :]) ** 2).sum(-1)  # rows a..b-1 against all
        upper.extend(sq[k, a + k + 1:] for k in range(b - a))
    return float(np.median(np.concatenate(upper)))


def sgpdm_model(
    views: Mapping[str, torch.Tensor],
    X: torch.Tensor,
    hyper: Mapping[str, torch.Tensor],
    seq_lengths: Sequence[int],
    cfg: SGPDMConfig,
    learned: Sequence[str],
) -> None:
    """The SGPDM as a Pyro program; every site is observed at MAP training.

    ``hyper`` maps names to constrained values: ``alpha/<v>``, ``gamma/<v>``,
    ``beta/<v>``, ``w/<v>`` for each view and ``alpha/dyn``, ``gamma/dyn``, ``beta/dyn``
    (and ``lin/dyn``); ``learned`` lists the kernel hyperparameters that carry the 1/θ
    prior.
    """
    d = X.shape[1]
    if cfg.dynamics:
        lam = sum(Y.shape[1] for Y in views.values()) / d if cfg.balanced else 1.0
        with poutine.scale(scale=lam):
            pyro.sample(
                "X",
                GPDynamics(
                    seq_lengths, d, hyper["alpha/dyn"], hyper["gamma/dyn"], hyper["beta/dyn"],
                    hyper.get("lin/dyn"),
                ),
                obs=X,
            )
    else:
        pyro.sample("X", dist.Normal(torch.zeros_like(X), 1.0).to_event(2), obs=X)
    for v, Y in views.items():
        w = hyper[f"w/{v}"]
        if cfg.learn_w:
            pyro.sample(
                f"w/{v}", dist.HalfNormal(torch.full_like(w, math.sqrt(W_PRIOR_VARIANCE))).to_event(1),
                obs=w,
            )
        pyro.sample(
            f"Y/{v}",
            GPObservation(view_latents(X, cfg, v), hyper[f"alpha/{v}"], hyper[f"gamma/{v}"], hyper[f"beta/{v}"], w,
                          what=f"{v} kernel matrix"),
            obs=Y,
        )
    if learned:
        pyro.factor("hyperprior", -sum(torch.log(hyper[k]) for k in learned))


def _half_normal_log_prob(w: torch.Tensor) -> torch.Tensor:
    """``dist.HalfNormal(κ).to_event(1).log_prob(w)`` with κ² = W_PRIOR_VARIANCE, written out
    operation for operation as torch computes it (Normal(0, κ).log_prob + ln 2, −inf below 0,
    summed over the last axis), so the bits are the same, without building the distribution
    objects at every evaluation (a third of the direct objective's time at N = 25)."""
    scale = torch.full_like(w, math.sqrt(W_PRIOR_VARIANCE))
    loc = torch.zeros_like(scale)
    lp = -((w - loc) ** 2) / (2 * scale**2) - scale.log() - math.log(math.sqrt(2 * math.pi))
    lp = torch.where(w >= 0, lp + math.log(2), -math.inf)
    return lp.reshape(w.shape[:-1] + (-1,)).sum(-1)


def _standard_normal_log_prob(X: torch.Tensor) -> torch.Tensor:
    """``dist.Normal(torch.zeros_like(X), 1.0).to_event(2).log_prob(X)`` (X: N×d) written out
    as torch computes it, −(x − 0)²/(2·1²) − ln 1 − ln √(2π) summed over both axes, without
    the operations on the constant loc and scale (x − 0 = x, /(2·1) = /2 and − ln 1 = − 0 are
    exact), so the same bits; no distribution objects, and no vectorised-math ``log`` of an
    N×d tensor of ones, at every evaluation."""
    lp = -(X**2) / 2.0 - math.log(math.sqrt(2 * math.pi))
    return lp.reshape(X.shape[:-2] + (-1,)).sum(-1)


def sgpdm_log_joint(
    views: Mapping[str, torch.Tensor],
    X: torch.Tensor,
    hyper: Mapping[str, torch.Tensor],
    seq_lengths: Sequence[int],
    cfg: SGPDMConfig,
    learned: Sequence[str],
) -> torch.Tensor:
    """The log joint of :func:`sgpdm_model`'s trace, ``trace.log_prob_sum()``, without
    running the Pyro program (the trace machinery costs more than the GP algebra at the few
    hundred frames of a switching state):

        L = λ·ln p(X) + Σ_v [ln HalfNormal(w_v) + ln p(Y_v | X)] − Σ_θ ln θ,

    the same site log-densities (deena2010 eq. 7 and eq. 5, the w prior, the 1/θ factor),
    computed by the same functions and added in the trace's site order from 0.0, so the
    value and its gradient equal the trace's bit for bit (tests/gp/test_gp_core.py).
    """
    d = X.shape[1]
    total = 0.0
    if cfg.dynamics:
        lam = sum(Y.shape[1] for Y in views.values()) / d if cfg.balanced else 1.0
        lx = dynamics_loglik(X, seq_lengths, hyper["alpha/dyn"], hyper["gamma/dyn"], hyper["beta/dyn"],
                             hyper.get("lin/dyn"))
        total = total + (lx if lam == 1.0 else lx * lam)
    else:
        total = total + _standard_normal_log_prob(X)
    for v, Y in views.items():
        w = hyper[f"w/{v}"]
        if cfg.learn_w:
            total = total + _half_normal_log_prob(w)
        total = total + observation_loglik(Y, view_latents(X, cfg, v), hyper[f"alpha/{v}"], hyper[f"gamma/{v}"], hyper[f"beta/{v}"], w,
                                           None, f"{v} kernel matrix")
    if learned:
        total = total + -sum(torch.log(hyper[k]) for k in learned)
    return total


def trace_log_joint(views: Mapping[str, torch.Tensor], X: torch.Tensor, hyper: Mapping[str, torch.Tensor],
                    seq_lengths: Sequence[int], cfg: SGPDMConfig, learned: Sequence[str]) -> torch.Tensor:
    """The log joint of :func:`sgpdm_model` as its Pyro trace's ``log_prob_sum()``: the
    reference that :func:`sgpdm_log_joint` (the MAP objective, the same sites summed without
    running the program) equals bit for bit (tests/gp/test_gp_core.py).

    Run with Pyro's validation off (``pyro.validation_enabled(False)``): the same program and
    the same numbers, without the argument and support checks of every distribution and the
    NaN/inf checks on every site's log-density and, through hooks, on its gradient (a third
    of the trace's own cost at 200 frames)."""
    with pyro.validation_enabled(False):
        tr = poutine.trace(sgpdm_model).get_trace(views, X, hyper, seq_lengths, cfg, learned)
        tr.compute_log_prob()
        return tr.log_prob_sum()


@dataclass
class FitHistory:
    """Objective (log joint) after each outer L-BFGS step; with a monitor, its value after
    each step (``monitor``), the step whose parameters were kept (``best_step``, 1-based) and
    the L-BFGS iterations run in all (``n_iter``, at most the model's ``max_iter``)."""

    log_joint: list[float] = field(default_factory=list)
    monitor: list[float] = field(default_factory=list)
    best_step: int | None = None
    n_iter: int = 0
