"""Latent points for new observations of one view of a fitted SGPDM (deena2009 §4.1).

Inference given a fitted :class:`~bayes_talk.models.sgpdm.SGPDM` (the model itself only
defines and fits the generative model): an initialiser from
:mod:`bayes_talk.synthesis.initialisers`, then L-BFGS-B on the negative log posterior of
eq. 9 (observation and dynamics terms, ``method="sequence"``) or on each frame alone
(``method="point"``), :mod:`bayes_talk.synthesis.optimise`. :func:`predict_across` adds
the predictive of another view at those latents (eq. 10).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from bayes_talk.synthesis.initialisers import initialise
from bayes_talk.synthesis.optimise import maximise_points, maximise_sequence

if TYPE_CHECKING:
    from bayes_talk.models.sgpdm import SGPDM

__all__ = ["METHODS", "infer_latents", "predict_across"]

#: ways to maximise the posterior of the latents: all frames jointly with the dynamics
#: (eq. 9), or each frame alone
METHODS = ("sequence", "point")


def infer_latents(model: SGPDM, view: str, Y: np.ndarray, X_init: np.ndarray | str = "nn",
                  method: str = "sequence", max_iter: int = 100) -> np.ndarray:
    """Latent points (T, d) for new observations ``Y`` (T, D) of ``view``.

    method: "sequence" (eq. 9: observation + dynamics terms) or "point" (each frame
    alone). X_init: an array, or the name of an initialiser ("nn", "back-constraint",
    "hmm"; see :mod:`bayes_talk.synthesis.initialisers`).
    """
    Y = model.check_new_observations(view, Y)
    X0 = initialise(X_init, model, view, Y) if isinstance(X_init, str) else np.asarray(X_init, float)
    if method == "sequence":
        return maximise_sequence(model.predictors_[view], Y, X0, model.dynamics_predictor_, max_iter=max_iter)
    if method == "point":
        return maximise_points(model.predictors_[view], Y, X0, max_iter=max_iter)
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")


def predict_across(model: SGPDM, Y: np.ndarray, view_in: str = "audio", view_out: str = "visual",
                   X_init: np.ndarray | str = "nn", method: str = "sequence",
                   max_iter: int = 100) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Prediction of ``view_out`` from new observations of ``view_in`` (eq. 10): returns
    (mean (T, D_out), per-dimension variance (T, D_out), latents (T, d))."""
    X = infer_latents(model, view_in, Y, X_init, method, max_iter)
    mu, var = model.predict_view(view_out, X)
    return mu, var, X
