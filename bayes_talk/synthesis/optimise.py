"""Point and sequence optimisation of latent points (deena2009 §4.1, deena2010 Alg. 1).

* point optimisation: x̂_t = argmax_x ln p(ŷ_t | x), each frame alone;
* sequence optimisation (deena2009 eq. 9):

      X̂* = argmax Σ_t ln p(ŷ_t | x_t) + Σ_{t≥2} ln N(x_t; μ_x(x_{t−1}), σ²_x(x_{t−1}) I)
                 [+ ln N(x_1; μ_π, Σ_π)]  [+ extra terms, e.g. the smoothness term]

The density is written once as a torch function (:func:`sequence_log_density`, which the
samplers differentiate); the optimisers maximise it through its closed-form twin in
:mod:`bayes_talk.synthesis.segment_objective` with scipy's L-BFGS-B (about 5x faster on
2-5 frame segments than torch autograd + torch L-BFGS), falling back to torch for
kernels the closed form does not cover. float64 throughout.

One verb: every function that finds latents by maximising a log density is called
``maximise_*`` (:func:`maximise_points`, :func:`maximise_sequence`,
:func:`~bayes_talk.synthesis.segment_objective.maximise_segment`,
:func:`~bayes_talk.synthesis.sequential.maximise_state_segment`,
:func:`~bayes_talk.synthesis.joint_map.maximise_utterance`).
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from bayes_talk.gp.predictive import GPPredictor

ExtraTerm = Callable[[torch.Tensor], torch.Tensor]


def sequence_log_density(
    X: torch.Tensor,
    Y: torch.Tensor,
    obs: GPPredictor,
    dynamics: GPPredictor | None = None,
    first: tuple[torch.Tensor, torch.Tensor] | None = None,
    extra: ExtraTerm | None = None,
) -> torch.Tensor:
    """The unnormalised log posterior of eq. 9 for one segment (a scalar tensor).

    first: optional (mean, Cholesky factor of the covariance) of the entry distribution
    N(μ_π, Σ_π) of the first latent point (deena2010 eq. 12).
    """
    lp = obs.log_lik(Y, X).sum()
    if dynamics is not None and X.shape[0] > 1:
        lp = lp + dynamics.log_lik(X[1:], X[:-1]).sum()
    if first is not None:
        mu, Lc = first
        r = torch.linalg.solve_triangular(Lc, (X[0] - mu)[:, None], upper=False)[:, 0]
        lp = lp - 0.5 * (r * r).sum() - torch.log(Lc.diagonal()).sum() - 0.5 * len(mu) * np.log(2 * np.pi)
    if extra is not None:
        lp = lp + extra(X)
    return lp


def _maximise(fn: Callable[[torch.Tensor], torch.Tensor], X0: np.ndarray, max_iter: int,
              tol_grad: float = 1e-5) -> np.ndarray:
    """Maximise fn from X0 by L-BFGS; stops when max |gradient| < tol_grad (per unit of ln p)."""
    X = torch.as_tensor(np.array(X0, dtype=np.float64)).requires_grad_(True)
    opt = torch.optim.LBFGS([X], lr=1.0, max_iter=max_iter, history_size=20,
                            line_search_fn="strong_wolfe", tolerance_grad=tol_grad, tolerance_change=1e-9)

    def closure():
        opt.zero_grad()
        loss = -fn(X)
        loss.backward()
        return loss

    with torch.no_grad():
        start = float(fn(X))
    opt.step(closure)
    with torch.no_grad():
        end = float(fn(X))
    if not np.isfinite(end) or end < start:  # never return a worse point than the start
        return np.asarray(X0, dtype=np.float64).copy()
    return X.detach().numpy().copy()


def _closed_form_ok(*predictors: GPPredictor | None) -> bool:
    return all(p is None or p.alpha_lin is None for p in predictors)


def maximise_points(obs: GPPredictor, Y: np.ndarray, X0: np.ndarray, max_iter: int = 100) -> np.ndarray:
    """Point optimisation of every frame (independent problems, solved jointly)."""
    return maximise_sequence(obs, Y, X0, None, max_iter=max_iter)


def maximise_sequence(
    obs: GPPredictor,
    Y: np.ndarray,
    X0: np.ndarray,
    dynamics: GPPredictor | None,
    first: tuple[np.ndarray, np.ndarray] | None = None,
    smooth: tuple[GPPredictor, np.ndarray, np.ndarray] | None = None,
    max_iter: int = 100,
) -> np.ndarray:
    """Sequence optimisation (eq. 9) from the initial latents X0 (T×d).

    first: (μ_π, Σ_π) of the entry distribution on x_1; smooth: (visual predictor,
    ẑ_prev (1×D), extra variance (D,)) for the smoothness term on x_1. Uses the closed-form
    objective of :mod:`bayes_talk.synthesis.segment_objective` with scipy's L-BFGS-B, or
    torch autograd on :func:`sequence_log_density` for kernels it does not cover (a linear
    term in the dynamics kernel).
    """
    from bayes_talk.synthesis.segment_objective import maximise_segment

    Y = np.asarray(Y, dtype=np.float64)
    if _closed_form_ok(obs, dynamics) and (smooth is None or _closed_form_ok(smooth[0])):
        return maximise_segment(np.asarray(X0, dtype=np.float64), Y, obs, dynamics, first, smooth, max_iter)
    Yt = torch.as_tensor(Y)
    first_t = None
    if first is not None:
        mu, cov = first
        first_t = (torch.as_tensor(mu, dtype=torch.float64),
                   torch.linalg.cholesky(torch.as_tensor(cov, dtype=torch.float64)))
    extra = None
    if smooth is not None:
        vis, z, e = smooth
        zt, et = torch.as_tensor(z), torch.as_tensor(e)
        extra = lambda X: vis.log_lik(zt, X[:1], et).sum()
    return _maximise(lambda X: sequence_log_density(X, Yt, obs, dynamics, first_t, extra), X0, max_iter)
