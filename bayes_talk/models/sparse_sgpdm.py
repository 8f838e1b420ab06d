"""One sparse shared GPDM on a whole training corpus (what deena2010 §4.1 found
"intractable": a single SGPDM on all 250 sequences costs O(N³) with N ≈ 15,000 frames).

The model is the SGPDM of :mod:`bayes_talk.models.sgpdm` (same shared latent space X,
same views, same dynamics, same priors and MAP reading) with every N×N kernel replaced
by an inducing-point approximation on M ≪ N inducing inputs Z in the latent space
(one set shared by the two views and the dynamics; the kernels differ, so K_mm differs):

    L_sparse = Σ_v F_v(Y_v W_v | X, Z) + N Σ_v Σ_m ln w_vm                 (views, Titsias 2009 eq. 9)
             + λ·[Σ_s ln N(x^s_1; 0, I) + ln p_FITC(X_out | X_in, Z)]      (dynamics, FITC)
             − Σ_θ ln θ + Σ_v Σ_m ln HalfNormal(w_vm; κ² = 10⁶)

    F_v = ln N(Y_v W_v; 0, Q_nn + β_v⁻¹ I) − (D_v β_v / 2) tr(K_nn − Q_nn),  Q_nn = K_nm K_mm⁻¹ K_mn

(:mod:`bayes_talk.gp.sparse` has the evaluation and the predictive.) Why Titsias's
variational bound for the two mappings: it is a lower bound on exactly the marginal
likelihood deena2010 eq. 5 that the exact model maximises (F_v ≤ ln p(Y_v | X), equal when
Z = X), so the sparse objective approximates the exact MAP objective from below, and the
inducing inputs are variational parameters — optimising them only tightens the bound,
there is no overfitting through Z (which DTC/FITC marginal likelihoods allow). That is the
closest to this project's Bayesian reading short of the Bayesian GPLVM's q(X); the latents
stay MAP points as in the papers. Why FITC for the dynamics: see :mod:`bayes_talk.gp.sparse`
(the fixed dynamics noise σ_x² = 10⁻⁶ makes the Titsias trace penalty 10⁶ tr(K − Q)/2).
With Z = X (M = N) and no jitter the sparse objective equals the exact SGPDM log joint.

Training: torch L-BFGS (the exact model's optimiser) over X, Z, log θ, log w; Z starts
at the k-means centres of the initial latents (PCA-average, as every GP model here), γ at
the inverse median squared distance of a random subsample of those latents.

Synthesis (:class:`bayes_talk.estimators.sparse_sgpdm.CorpusSparseSGPDM`): the whole utterance's latents by
sequence optimisation (deena2009 eq. 9) under the sparse predictives, from the
nearest-neighbour initialiser (the training latent whose audio frame is closest):

    X̂* = argmax_X Σ_t ln p_sparse(ŷ_t | x_t) + Σ_{t≥2} ln N(x_t; μ_x(x_{t−1}), σ²_x(x_{t−1}) I)

then ẑ_t = μ_Z(x̂_t) with variance σ²_Z(x̂_t)/w² (the sparse predictive of the visual view).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pyro
import torch
from pyro import poutine

from bayes_talk.gp.sparse import fitc_loglik, kmeans_inducing, sparse_predictor, titsias_bound
from bayes_talk.gp.terms import LOG_2PI, dynamics_split, log_w_prior
from bayes_talk.models.sgpdm import SGPDM, SGPDMConfig

log = logging.getLogger(__name__)


@dataclass
class SparseSGPDMConfig(SGPDMConfig):
    """:class:`SGPDMConfig` plus the sparse settings.

    n_inducing: M, inducing inputs (all frames when N ≤ M: then the model is exact).
    learn_inducing: optimise Z with the rest (Titsias: Z are variational parameters).
    jitter: K_mm + jitter·α·I (relative to the kernel's signal variance α).
    gamma_init_frames: frames of the random subsample whose median squared latent distance
        sets the initial γ of each view.
    """

    n_inducing: int = 200
    learn_inducing: bool = True
    jitter: float = 1e-6
    gamma_init_frames: int = 2000


def _sparse_model(terms: Mapping[str, torch.Tensor]) -> None:
    """The sparse objective as a Pyro program: one ``pyro.factor`` per term."""
    for name, value in terms.items():
        pyro.factor(name, value)


class SparseSGPDM(SGPDM):
    """Sparse shared GPDM (module docstring): the exact SGPDM's API (``fit``,
    ``predict_view``, ``infer_latents``, ``predict``, ``save``/``load``) with inducing
    inputs ``Z_`` (M×d)."""

    format_name = "bayes_talk.sparse_sgpdm"
    format_version = 1
    config_class = SparseSGPDMConfig

    def __init__(self, *, n_inducing: int = 200, learn_inducing: bool = True, jitter: float = 1e-6,
                 gamma_init_frames: int = 2000, **base) -> None:
        """The sparse settings of :class:`SparseSGPDMConfig`; ``base``: those of
        :class:`~bayes_talk.models.sgpdm.SGPDM`."""
        self.n_inducing, self.learn_inducing, self.jitter = n_inducing, learn_inducing, jitter
        self.gamma_init_frames = gamma_init_frames
        super().__init__(**base)
        cfg = self.config
        if cfg.view_dims:
            raise ValueError(f"the sparse SGPDM reads all latent dimensions in every view; view_dims={cfg.view_dims} "
                             "(private latent dimensions) needs the exact SGPDM")
        if cfg.back_constraint is not None:
            raise ValueError("SparseSGPDM has no back-constraint (the MLP would map every training frame); "
                             "set back_constraint=None")
        if cfg.dyn_linear is not None:
            raise ValueError("SparseSGPDM supports the RBF dynamics kernel only; set dyn_linear=None")
        if int(cfg.n_inducing) < 1:
            raise ValueError(f"n_inducing must be >= 1, got {cfg.n_inducing}")
        if not cfg.jitter >= 0.0:
            raise ValueError(f"jitter must be >= 0, got {cfg.jitter}")

    # ------------------------------------------------------------------ parameters
    def _init_params(self, centred: Mapping[str, np.ndarray], X0: np.ndarray) -> None:
        cfg = self.config
        super()._init_params(centred, X0)
        rng = np.random.default_rng(cfg.seed)
        sub = X0 if len(X0) <= cfg.gamma_init_frames else X0[rng.choice(len(X0), cfg.gamma_init_frames, replace=False)]
        sq = ((sub[:, None, :] - sub[None, :, :]) ** 2).sum(-1)[np.triu_indices(len(sub), 1)]
        gamma0 = 1.0 / max(float(np.median(sq)) if sq.size else 1.0, 1e-12)
        for v in centred:
            self._log[f"gamma/{v}"] = torch.tensor(math.log(gamma0), dtype=torch.float64, requires_grad=True)
        Z0 = kmeans_inducing(X0, int(cfg.n_inducing), cfg.seed)
        self._Z = torch.as_tensor(Z0).clone().requires_grad_(cfg.learn_inducing)

    def _free_tensors(self) -> list[torch.Tensor]:
        free = super()._free_tensors()
        return free + [self._Z] if self.config.learn_inducing else free

    def terms(self) -> dict[str, torch.Tensor]:
        """Every term of the sparse objective (module docstring) at the current parameters."""
        cfg = self.config
        h = self._hyper()
        X, Z, jit = self._latents(), self._Z, cfg.jitter
        out: dict[str, torch.Tensor] = {}
        d = X.shape[1]
        if cfg.dynamics:
            lam = sum(Y.shape[1] for Y in self._Y.values()) / d if cfg.balanced else 1.0
            i_in, i_out, i_first = dynamics_split(self.seq_lengths_)
            X1 = X[i_first]
            lx = -0.5 * (X1 * X1).sum() - 0.5 * X1.numel() * LOG_2PI
            if len(i_in) > 0:
                lx = lx + fitc_loglik(X[i_out], X[i_in], Z, h["alpha/dyn"], h["gamma/dyn"], h["beta/dyn"], jit)
            out["X"] = lam * lx
        else:
            out["X"] = -0.5 * (X * X).sum() - 0.5 * X.numel() * LOG_2PI
        for v, Y in self._Y.items():
            w = h[f"w/{v}"]
            if cfg.learn_w:
                out[f"w/{v}"] = log_w_prior(w)
            out[f"Y/{v}"] = Y.shape[0] * torch.log(w).sum() + titsias_bound(
                Y * w, X, Z, h[f"alpha/{v}"], h[f"gamma/{v}"], h[f"beta/{v}"], jit)
        learned = self._learned_thetas()
        if learned:
            out["hyperprior"] = -sum(torch.log(h[k]) for k in learned)
        return out

    def log_joint(self) -> torch.Tensor:
        """The sparse MAP objective L_sparse (a lower bound on the exact log joint in Y)."""
        return sum(self.terms().values())

    def trace(self) -> pyro.poutine.Trace:
        """The objective as a Pyro trace of ``pyro.factor`` sites (one per term)."""
        tr = poutine.trace(_sparse_model).get_trace(self.terms())
        tr.compute_log_prob()
        return tr

    # ------------------------------------------------------------------ predictors
    def _finalise(self) -> None:
        cfg = self.config
        with torch.no_grad():
            self.X_ = self._latents().detach().numpy().copy()
            self.Z_ = self._Z.detach().numpy().copy()
            h = {k: v.detach() for k, v in self._hyper().items()}
        self.hyper_ = {k: (v.numpy().copy() if v.ndim else float(v)) for k, v in h.items()}
        X, Z = torch.as_tensor(self.X_), torch.as_tensor(self.Z_)
        self.predictors_ = {
            v: sparse_predictor(X, self._Y[v], Z, float(h[f"alpha/{v}"]), float(h[f"gamma/{v}"]),
                                float(h[f"beta/{v}"]), h[f"w/{v}"], torch.as_tensor(self.means_[v]),
                                jitter=cfg.jitter, what=f"{v} view")
            for v in self.view_names
        }
        self.dynamics_predictor_ = None
        if cfg.dynamics:
            i_in, i_out, _ = dynamics_split(self.seq_lengths_)
            if len(i_in) > 0:
                self.dynamics_predictor_ = sparse_predictor(
                    X[i_in], X[i_out], Z, float(h["alpha/dyn"]), float(h["gamma/dyn"]), float(h["beta/dyn"]),
                    fitc=True, jitter=cfg.jitter, what="dynamics")
        self._fitted = True

    # ------------------------------------------------------------------ persistence
    def state(self) -> tuple[dict, dict[str, np.ndarray]]:
        """The exact SGPDM's state plus the inducing inputs ``Z``."""
        meta, arrays = super().state()
        arrays["Z"] = self.Z_
        return meta, arrays

    def _restore_extra(self, arrays: Mapping[str, np.ndarray]) -> None:
        if "Z" not in arrays:
            raise ValueError("sparse SGPDM model is incomplete or corrupt: missing 'Z' (inducing inputs)")
        self._Z = torch.as_tensor(np.asarray(arrays["Z"], dtype=np.float64))
