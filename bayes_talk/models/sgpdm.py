"""The shared Gaussian-process dynamical model (SGPDM): the model class and its MAP fit.

The settings and the Pyro program are in :mod:`bayes_talk.models.sgpdm_program`,
inference of latents for new observations in :mod:`bayes_talk.synthesis.latents`.
The module is above ~500 lines because persistence (:meth:`SGPDM.state` /
:meth:`SGPDM.from_state`) is here, with the class whose fitted attributes it writes and
restores; the direct fit's objective and optimiser are in
:mod:`bayes_talk.models.sgpdm_objective` and :mod:`bayes_talk.gp.lbfgs`.

deena2010 §2.1.1 (eq. 1–7), deena2009 §2; the conventions where they leave a choice are in
docs/model.md.

Generative model, for views v (audio MFCCs, visual AAM parameters) of N frames that come
in sequences s of lengths T_s, sharing latent points X (N×d):

    X   ~ GPDynamics                          (eq. 7; or X = g(Y_audio; φ), eq. 8)
    Y_v ~ GPObservation(X; α_v, γ_v, β_v, W_v)  for every view v (eq. 5)
    p(θ) ∝ 1/θ for every learned kernel hyperparameter θ, w_m ~ HalfNormal(κ² = 10⁶)

MAP training maximises the log joint of that program's trace,

    L = Σ_v ln p(Y_v|X) + λ·ln p(X) − Σ_θ ln θ + Σ_v Σ_m ln HalfNormal(w_m),

with torch L-BFGS over log θ, log w and X (or the back-constraint weights φ). The log
joint is taken in θ-space: log θ is only the parametrisation, no Jacobian is added.

Example
-------
>>> import numpy as np
>>> from bayes_talk.models.sgpdm import SGPDM
>>> rng = np.random.default_rng(0)
>>> t = np.linspace(0, 6, 60)[:, None]
>>> audio = np.hstack([np.sin(t), np.cos(t), np.sin(2 * t)]) + 0.01 * rng.standard_normal((60, 3))
>>> video = np.hstack([np.cos(t), np.sin(3 * t)]) + 0.01 * rng.standard_normal((60, 2))
>>> m = SGPDM(latent_dim=2, max_iter=50).fit({"audio": audio, "visual": video})
>>> m.X_.shape
(60, 2)
"""
from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np
import pyro
import torch
from pyro import poutine

from bayes_talk.base.errors import not_fitted
from bayes_talk.base.files import check_format, read_model_files, write_model_files
from bayes_talk.gp.backconstraint import MLPBackConstraint
from bayes_talk.gp.predictive import GPPredictor
from bayes_talk.gp.terms import dynamics_split
from bayes_talk.gp.threads import problem_threads
from bayes_talk.models.sgpdm_objective import SGPDMObjective, fit_direct
from bayes_talk.models.sgpdm_objective import supports as objective_supports
from bayes_talk.models.sgpdm_program import (
    FitHistory,
    SGPDMConfig,
    pca_scores,
    sgpdm_model,
    view_in_dims,
    view_latents,
)
from bayes_talk.models.sgpdm_program import median_sq_dist as _median_sq_dist
from bayes_talk.models.sgpdm_program import sgpdm_log_joint as program_log_joint

log = logging.getLogger(__name__)

_DEFAULTS = SGPDMConfig()

FORMAT_VERSION = 1
FORMAT_NAME = "bayes_talk.sgpdm"


class SGPDM:
    """Shared GPDM with any number of observed views; scikit-learn-like ``fit``.

    The keyword arguments are the fields of :class:`SGPDMConfig` (their one source of
    defaults), stored as given; :attr:`config` gathers them. :meth:`from_config` builds
    a model from a config. Inference for new observations is in
    :mod:`bayes_talk.synthesis.latents`.

    Subclasses (e.g. a sparse SGPDM) set :attr:`config_class` to a dataclass extending
    :class:`SGPDMConfig` and take its extra fields as keyword arguments too; they save under
    their own :attr:`format_name` / :attr:`format_version` and restore extra arrays in
    :meth:`_restore_extra`.
    """

    #: the settings dataclass whose fields are the constructor arguments
    config_class: type[SGPDMConfig] = SGPDMConfig
    #: saved-model format written by :meth:`state`
    format_name: str = FORMAT_NAME
    format_version: int = FORMAT_VERSION

    def __init__(self, *, latent_dim: int = _DEFAULTS.latent_dim, dynamics: bool = _DEFAULTS.dynamics,
                 learn_dynamics: bool = _DEFAULTS.learn_dynamics, dyn_alpha: float = _DEFAULTS.dyn_alpha,
                 dyn_gamma: float = _DEFAULTS.dyn_gamma, dyn_beta: float = _DEFAULTS.dyn_beta,
                 dyn_linear: float | None = _DEFAULTS.dyn_linear, balanced: bool = _DEFAULTS.balanced,
                 back_constraint: str | None = _DEFAULTS.back_constraint, bc_hidden: int = _DEFAULTS.bc_hidden,
                 init: str = _DEFAULTS.init, init_scale: float | None = _DEFAULTS.init_scale,
                 learn_w: bool = _DEFAULTS.learn_w, max_iter: int = _DEFAULTS.max_iter,
                 tol: float = _DEFAULTS.tol, seed: int = _DEFAULTS.seed,
                 view_dims: dict[str, int] | None = _DEFAULTS.view_dims):
        self.latent_dim, self.dynamics, self.learn_dynamics = latent_dim, dynamics, learn_dynamics
        self.dyn_alpha, self.dyn_gamma, self.dyn_beta, self.dyn_linear = dyn_alpha, dyn_gamma, dyn_beta, dyn_linear
        self.balanced, self.back_constraint, self.bc_hidden = balanced, back_constraint, bc_hidden
        self.init, self.init_scale, self.learn_w = init, init_scale, learn_w
        self.max_iter, self.tol, self.seed = max_iter, tol, seed
        self.view_dims = None if view_dims is None else {str(v): int(k) for v, k in dict(view_dims).items()}
        self.view_names: list[str] = []
        self.history = FitHistory()
        self._fitted = False
        self.var_scale_: dict[str, np.ndarray] = {}

    @classmethod
    def from_config(cls, config: SGPDMConfig) -> SGPDM:
        """An unfitted model with the settings of ``config``."""
        return cls(**asdict(config))

    @property
    def config(self) -> SGPDMConfig:
        """The settings, gathered from the constructor arguments."""
        return self.config_class(**{f.name: getattr(self, f.name) for f in fields(self.config_class)})

    # ------------------------------------------------------------------ validation/init
    def _check_views(self, views: Mapping[str, np.ndarray], seq_lengths) -> tuple[dict, list[int]]:
        if not views:
            raise ValueError("no views given: pass e.g. {'audio': Y, 'visual': Z}")
        arrs: dict[str, np.ndarray] = {}
        n = None
        for v, Y in views.items():
            Y = np.asarray(Y, dtype=np.float64)
            if Y.ndim != 2:
                raise ValueError(f"view {v!r}: expected a 2-D array (frames, dims), got shape {Y.shape}")
            if not np.all(np.isfinite(Y)):
                bad = np.argwhere(~np.isfinite(Y))[0]
                raise ValueError(f"view {v!r} contains NaN or inf (first at frame {bad[0]}, dim {bad[1]})")
            if n is None:
                n = Y.shape[0]
            elif Y.shape[0] != n:
                lens = {k: np.asarray(a).shape[0] for k, a in views.items()}
                raise ValueError(f"views have different numbers of frames: {lens}")
            arrs[v] = Y
        assert n is not None
        if seq_lengths is None:
            seq_lengths = [n]
        seq_lengths = [int(t) for t in seq_lengths]
        if any(t < 1 for t in seq_lengths) or sum(seq_lengths) != n:
            raise ValueError(
                f"sequence lengths {seq_lengths[:10]}{'...' if len(seq_lengths) > 10 else ''} add up to "
                f"{sum(seq_lengths)}, but the views have {n} frames (lengths must be >= 1)"
            )
        d = self.config.latent_dim
        dims = {v: Y.shape[1] for v, Y in arrs.items()}
        limit = sum(dims.values()) if self.config.init == "pca-concat" else min(dims.values())
        if d > limit or d > n:
            raise ValueError(
                f"latent_dim={d} is larger than the data allow (view dimensions {dims}, {n} frames; "
                f"init {self.config.init!r} needs d <= {min(limit, n)})"
            )
        if self.config.init not in ("pca-average", "pca-concat"):
            raise ValueError(f"init must be 'pca-average' or 'pca-concat', got {self.config.init!r}")
        bc = self.config.back_constraint
        if bc is not None and bc not in arrs:
            raise ValueError(f"back_constraint view {bc!r} is not among the views {list(arrs)}")
        for v, k in (self.view_dims or {}).items():
            if v not in arrs:
                raise ValueError(f"view_dims names view {v!r}, which is not among the views {list(arrs)}")
            if not 1 <= k <= d:
                raise ValueError(f"view_dims[{v!r}] = {k}: a view reads 1 to latent_dim = {d} latent dimensions")
        if self.view_dims and bc is not None:
            raise ValueError("view_dims (private latent dimensions) cannot be combined with a back-constraint")
        return arrs, seq_lengths

    def _init_latents(self, centred: Mapping[str, np.ndarray]) -> np.ndarray:
        cfg = self.config
        d = cfg.latent_dim
        if cfg.init == "pca-average":
            X = np.mean([pca_scores(Y, d) for Y in centred.values()], axis=0)
            X = X / np.maximum(X.std(0), 1e-12)
        else:
            Z = np.hstack([Y / np.maximum(Y.std(0), 1e-12) for Y in centred.values()])
            X = pca_scores(Z, d)
        k = min((view_in_dims(cfg, v) or d for v in centred), default=d)
        if k < d:
            # private dimensions k..d−1 (SGPDMConfig.view_dims): the shared ones as above at
            # k, the private ones the principal components of what the shared ones leave of
            # the views that read them (each standardised; least squares on the shared scores)
            X = X[:, :k] if cfg.init == "pca-concat" else np.mean([pca_scores(Y, k) for Y in centred.values()], axis=0)
            X = X / np.maximum(X.std(0), 1e-12)
            readers = [Y / np.maximum(Y.std(0), 1e-12) for v, Y in centred.items() if (view_in_dims(cfg, v) or d) > k]
            R = np.hstack(readers)
            R = R - X @ np.linalg.lstsq(X, R, rcond=None)[0]
            X = np.hstack([X, pca_scores(R, d - k)])
        scale = cfg.init_scale
        if scale is None:
            scale = math.sqrt(cfg.dyn_alpha) if cfg.dynamics else 1.0
        return X * scale

    # ------------------------------------------------------------------ parameters
    def _hyper(self) -> dict[str, torch.Tensor]:
        """Constrained hyperparameters from the free (log-space) ones."""
        h = {k: torch.exp(v) for k, v in self._log.items()}
        h.update(self._fixed)
        return h

    def _latents(self) -> torch.Tensor:
        if self.backconstraint is not None:
            return self.backconstraint(self._Y[self.config.back_constraint], self._bc_params)
        return self._X

    def _learned_thetas(self) -> list[str]:
        return [k for k in self._log if not k.startswith("w/")]

    def log_joint(self) -> torch.Tensor:
        """Log joint of the Pyro program at the current parameters (= the MAP objective;
        :func:`~bayes_talk.models.sgpdm_program.sgpdm_log_joint`); on one thread below
        :data:`~bayes_talk.gp.threads.THREADED_MIN_N` frames (:func:`~bayes_talk.gp.threads.problem_threads`)."""
        with problem_threads(sum(self.seq_lengths_)):
            return program_log_joint(self._Y, self._latents(), self._hyper(), self.seq_lengths_, self.config,
                                     self._learned_thetas())

    def trace(self) -> pyro.poutine.Trace:
        """The executed Pyro trace; ``trace().nodes[site]['log_prob_sum']`` per term."""
        tr = poutine.trace(sgpdm_model).get_trace(
            self._Y, self._latents(), self._hyper(), self.seq_lengths_, self.config,
            self._learned_thetas(),
        )
        tr.compute_log_prob()
        return tr

    def _free_tensors(self) -> list[torch.Tensor]:
        free = list(self._log.values())
        free += self._bc_params if self.backconstraint is not None else [self._X]
        return free

    # ------------------------------------------------------------------ fit
    def fit(
        self,
        views: Mapping[str, np.ndarray],
        seq_lengths: Sequence[int] | None = None,
        X_init: np.ndarray | None = None,
        monitor: Callable[[SGPDM], float] | None = None,
        monitor_every: int = 10,
        patience: int = 3,
    ) -> SGPDM:
        """MAP training (torch L-BFGS on the log joint of :func:`sgpdm_model`).

        views: name -> (N, D_v) array, rows frame-synchronous across views.
        seq_lengths: lengths of the sequences stacked in the rows (default: one sequence).
        X_init: optional (N, d) initial latents (default: PCA, see ``config.init``).
        monitor: optional early stopping. ``monitor(model)`` (lower is better, e.g. an error
            on held-out frames) is called on the fitted-so-far model after every
            ``monitor_every`` L-BFGS iterations; training stops after ``patience`` calls
            without improvement and the parameters of the best call are kept. Why this
            exists: the MAP objective of a back-constrained GPDM is maximised by shrinking
            the latents towards a point (docs/model.md, "Latent collapse").
        """
        cfg = self.config
        arrs, seq_lengths = self._check_views(views, seq_lengths)
        torch.manual_seed(cfg.seed)
        self.view_names = list(arrs)
        self.seq_lengths_ = seq_lengths
        self.means_ = {v: Y.mean(0) for v, Y in arrs.items()}
        centred = {v: Y - self.means_[v] for v, Y in arrs.items()}
        self._Y = {v: torch.as_tensor(Y) for v, Y in centred.items()}
        if X_init is None:
            X0 = self._init_latents(centred)
        else:
            X0 = np.asarray(X_init, dtype=np.float64)
            if X0.shape != (sum(seq_lengths), cfg.latent_dim):
                raise ValueError(f"X_init has shape {X0.shape}, expected {(sum(seq_lengths), cfg.latent_dim)}")
        self._init_params(centred, X0)
        self._optimise(monitor, monitor_every, patience)
        self._finalise()
        self._check_collapse()
        return self

    def _init_params(self, centred: Mapping[str, np.ndarray], X0: np.ndarray) -> None:
        cfg = self.config
        med = _median_sq_dist(X0) if 1 < len(X0) <= 2000 else 1.0
        gamma0 = 1.0 / max(med, 1e-12)
        self._log: dict[str, torch.Tensor] = {}
        self._fixed: dict[str, torch.Tensor] = {}
        f64 = lambda x: torch.tensor(float(x), dtype=torch.float64)
        for v, Y in centred.items():
            self._log[f"alpha/{v}"] = torch.log(f64(1.0))
            self._log[f"gamma/{v}"] = torch.log(f64(gamma0))
            self._log[f"beta/{v}"] = torch.log(f64(100.0))
            w0 = torch.as_tensor(1.0 / np.maximum(Y.std(0), 1e-8))
            if cfg.learn_w:
                self._log[f"w/{v}"] = torch.log(w0)
            else:
                self._fixed[f"w/{v}"] = w0
        dyn = {"alpha/dyn": cfg.dyn_alpha, "gamma/dyn": cfg.dyn_gamma, "beta/dyn": cfg.dyn_beta}
        if cfg.dyn_linear is not None:
            dyn["lin/dyn"] = cfg.dyn_linear
        for k, val in dyn.items():
            if cfg.dynamics and cfg.learn_dynamics:
                self._log[k] = torch.log(f64(val))
            else:
                self._fixed[k] = f64(val)
        for t in self._log.values():
            t.requires_grad_(True)
        self.backconstraint = None
        if cfg.back_constraint is not None:
            bc = MLPBackConstraint(centred[cfg.back_constraint].shape[1], cfg.latent_dim, cfg.bc_hidden, cfg.seed)
            Yb = self._Y[cfg.back_constraint]
            bc.set_input_scaling(Yb)
            bc.fit_to(Yb, torch.as_tensor(X0))
            self.backconstraint = bc
            self._bc_params = [p.clone().requires_grad_(True) for p in bc.parameters()]
        else:
            self._X = torch.as_tensor(X0).clone().requires_grad_(True)

    def _optimise(self, monitor: Callable[[SGPDM], float] | None = None, monitor_every: int = 10,
                  patience: int = 3) -> None:
        cfg = self.config
        if monitor is not None and (monitor_every < 1 or patience < 1):
            raise ValueError(f"monitor_every and patience must be >= 1, got {monitor_every} and {patience}")
        step_iter = min(monitor_every if monitor is not None else 20, max(1, cfg.max_iter))
        # the direct objective is this class's log joint: a subclass with its own keeps torch's path
        own_objective = type(self).log_joint is SGPDM.log_joint and type(self)._free_tensors is SGPDM._free_tensors
        if monitor is None and self.backconstraint is None and own_objective and objective_supports(cfg):
            self._optimise_direct(step_iter)
            return
        free = self._free_tensors()
        opt = torch.optim.LBFGS(free, lr=1.0, max_iter=step_iter, history_size=50, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            loss = -self.log_joint()
            loss.backward()
            return loss.detach()  # L-BFGS keeps it all step: its graph's N×N buffers go now

        self.history = FitHistory([float(self.log_joint().detach())])
        best, best_params, since = math.inf, None, 0
        for step in range(1, max(1, math.ceil(cfg.max_iter / step_iter)) + 1):
            # L-BFGS iterations in blocks of step_iter, the last block the remainder: max_iter in all
            opt.param_groups[0]["max_iter"] = min(step_iter, max(1, cfg.max_iter - (step - 1) * step_iter))
            opt.step(closure)
            with torch.no_grad():
                cur = float(self.log_joint())
            if not math.isfinite(cur):
                raise RuntimeError("the SGPDM objective became non-finite during training")
            prev = self.history.log_joint[-1]
            self.history.log_joint.append(cur)
            if monitor is not None:
                self._finalise()
                score = float(monitor(self))
                self.history.monitor.append(score)
                if score < best:
                    best, since, self.history.best_step = score, 0, step
                    best_params = [t.detach().clone() for t in free]
                else:
                    since += 1
                    if since >= patience:
                        break
            if abs(cur - prev) <= cfg.tol * max(1.0, abs(cur)):
                break
        self.history.n_iter = int(opt.state[free[0]].get("n_iter", 0)) if free else 0
        if best_params is not None:
            with torch.no_grad():
                for t, b in zip(free, best_params):
                    t.copy_(b)
        log.info("SGPDM fit: log joint %.6g -> %.6g in %d steps%s", self.history.log_joint[0],
                 self.history.log_joint[-1], len(self.history.log_joint) - 1,
                 "" if monitor is None else f"; kept step {self.history.best_step} (monitor {best:.6g})")

    def _optimise_direct(self, step_iter: int) -> None:
        """:meth:`_optimise` without a monitor through the hand-written gradient and the NumPy
        port of torch's L-BFGS (:func:`~bayes_talk.models.sgpdm_objective.fit_direct`; the
        same path to rounding)."""
        obj = SGPDMObjective({v: Y.numpy() for v, Y in self._Y.items()}, self.seq_lengths_, self.config,
                             {k: tuple(t.shape) for k, t in self._log.items()},
                             {k: t.detach().numpy() for k, t in self._fixed.items()}, self._learned_thetas())
        self.history = fit_direct(obj, self._free_tensors(), self.log_joint, self.config, step_iter)
        log.info("SGPDM fit: log joint %.6g -> %.6g in %d steps", self.history.log_joint[0],
                 self.history.log_joint[-1], len(self.history.log_joint) - 1)

    def _check_collapse(self) -> None:
        """Warn when the latents have shrunk to the scale of the dynamics noise (the MAP
        objective's degenerate optimum, docs/model.md "Latent collapse")."""
        if not self.config.dynamics:
            return
        noise_std = float(self.hyper_["beta/dyn"]) ** -0.5
        spread = float(self.X_.std(0).mean())
        if spread < 3.0 * noise_std:
            log.warning("SGPDM latents have collapsed: mean latent std %.3g is below 3x the dynamics noise "
                        "std %.3g, so the visual mapping predicts little more than the mean; train with a "
                        "monitor (early stopping) or fewer iterations", spread, noise_std)

    def _finalise(self) -> None:
        """Detach parameters and build the predictors used at synthesis."""
        with torch.no_grad():
            self.X_ = self._latents().detach().numpy().copy()
            h = {k: v.detach() for k, v in self._hyper().items()}
        if self.backconstraint is not None:
            self.backconstraint.W1, self.backconstraint.b1, self.backconstraint.W2, self.backconstraint.b2 = (
                p.detach() for p in self._bc_params
            )
        self.hyper_ = {k: (v.numpy().copy() if v.ndim else float(v)) for k, v in h.items()}
        X = torch.as_tensor(self.X_)
        self.predictors_, self.dynamics_predictor_ = {}, None  # old N×N factors go first
        self.predictors_ = {
            v: GPPredictor(
                view_latents(X, self.config, v), self._Y[v], float(h[f"alpha/{v}"]), float(h[f"gamma/{v}"]),
                float(h[f"beta/{v}"]), h[f"w/{v}"], torch.as_tensor(self.means_[v]), what=f"{v} kernel matrix",
                in_dims=view_in_dims(self.config, v),
            )
            for v in self.view_names
        }
        self.dynamics_predictor_ = None
        if self.config.dynamics:
            i_in, i_out, _ = dynamics_split(self.seq_lengths_)
            if len(i_in) > 0:
                lin = h.get("lin/dyn")
                self.dynamics_predictor_ = GPPredictor(
                    X[i_in], X[i_out], float(h["alpha/dyn"]), float(h["gamma/dyn"]), float(h["beta/dyn"]),
                    alpha_lin=None if lin is None else float(lin), what="dynamics kernel matrix",
                )
        self._fitted = True

    # ------------------------------------------------------------------ prediction
    def _require_fitted(self) -> None:
        if not self._fitted:
            raise not_fitted(self)

    def predict_view(self, view: str, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictive mean (T, D) and per-dimension variance σ²(x)/w² (T, D) of a view (eq. 10),
        times the view's calibration factors when :meth:`calibrate_variance` has set them."""
        self._require_fitted()
        if view not in self.predictors_:
            raise ValueError(f"unknown view {view!r}; this model has {self.view_names}")
        p = self.predictors_[view]
        with torch.no_grad():
            mu, var = p.mean_var(torch.as_tensor(np.asarray(X, dtype=np.float64)))
        var = p.dim_var(var).numpy()
        if view in self.var_scale_:
            var = var * self.var_scale_[view]
        return mu.numpy(), var

    def calibrate_variance(self, view: str, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """Post-hoc variance calibration on held-out data: factors c_m = mean_t (y_tm − μ_tm)² /
        v_tm of the uncalibrated predictive at latents X (one per dimension), applied by
        :meth:`predict_view` from then on (saved with the model). The MAP objective, the
        latents and every synthesis path are unchanged; only reported variances scale."""
        self.var_scale_.pop(view, None)
        Y = self.check_new_observations(view, Y)
        mu, var = self.predict_view(view, X)
        if mu.shape != Y.shape:
            raise ValueError(f"calibrate_variance: {len(X)} latent points but {len(Y)} observations")
        c = np.mean((Y - mu) ** 2 / var, axis=0)
        self.var_scale_[view] = c
        log.info("%s predictive variance calibrated on %d frames: factors %.3g .. %.3g (median %.3g)",
                 view, len(Y), c.min(), c.max(), float(np.median(c)))
        return c

    def check_new_observations(self, view: str, Y: np.ndarray) -> np.ndarray:
        """``Y`` as a float64 (T, D) array of new observations of ``view``; ValueError naming
        the view when its shape is wrong or it holds NaN/inf (the model must be fitted)."""
        self._require_fitted()
        if view not in self.predictors_:
            raise ValueError(f"unknown view {view!r}; this model has {self.view_names}")
        Y = np.asarray(Y, dtype=np.float64)
        D = self.predictors_[view].out_dim
        if Y.ndim != 2 or Y.shape[1] != D:
            raise ValueError(f"view {view!r}: expected shape (T, {D}), got {Y.shape}")
        if not np.all(np.isfinite(Y)):
            raise ValueError(f"view {view!r}: new observations contain NaN or inf")
        return Y

    # ------------------------------------------------------------------ persistence
    def state(self) -> tuple[dict, dict[str, np.ndarray]]:
        """(JSON-able metadata, arrays) that fully describe the fitted model."""
        self._require_fitted()
        meta = {
            "format": self.format_name,
            "version": self.format_version,
            "config": asdict(self.config),
            "views": self.view_names,
            "seq_lengths": self.seq_lengths_,
            "history": self.history.log_joint,
            "history_monitor": self.history.monitor,
            "history_best_step": self.history.best_step,
        }
        arrays: dict[str, np.ndarray] = {"X": self.X_}
        for v in self.view_names:
            arrays[f"Y/{v}"] = self._Y[v].numpy()
            arrays[f"mean/{v}"] = self.means_[v]
        for k, val in self.hyper_.items():
            arrays[f"hyper/{k}"] = np.asarray(val, dtype=np.float64)
        if self.backconstraint is not None:
            for k, val in self.backconstraint.state().items():
                arrays[f"bc/{k}"] = val
        for v, c in self.var_scale_.items():
            arrays[f"varscale/{v}"] = c
        return meta, arrays

    @classmethod
    def from_state(cls, meta: dict, arrays: Mapping[str, np.ndarray]) -> SGPDM:
        """A fitted model from :meth:`state`'s metadata and arrays (ValueError if incomplete)."""
        check_format(meta, cls.format_name, cls.format_version, f"{cls.__name__} model")
        try:
            obj = cls(**meta["config"])
            obj.view_names = list(meta["views"])
            obj.seq_lengths_ = [int(t) for t in meta["seq_lengths"]]
            obj.history = FitHistory(list(meta.get("history", [])), list(meta.get("history_monitor", [])),
                                     meta.get("history_best_step"))
            obj.X_ = np.asarray(arrays["X"], dtype=np.float64)
            obj._Y = {v: torch.as_tensor(np.asarray(arrays[f"Y/{v}"], dtype=np.float64)) for v in obj.view_names}
            obj.means_ = {v: np.asarray(arrays[f"mean/{v}"], dtype=np.float64) for v in obj.view_names}
            hyper = {k[len("hyper/"):]: torch.as_tensor(np.asarray(a, dtype=np.float64))
                     for k, a in arrays.items() if k.startswith("hyper/")}
            bc_keys = {k[3:]: arrays[k] for k in arrays if k.startswith("bc/")}
        except (KeyError, TypeError) as exc:
            raise ValueError(f"SGPDM model is incomplete or corrupt: missing {exc}") from None
        obj.backconstraint = MLPBackConstraint.from_state(bc_keys) if bc_keys else None
        if obj.backconstraint is not None:
            obj._bc_params = obj.backconstraint.parameters()
        obj._X = torch.as_tensor(obj.X_)
        obj._log = {}
        obj._fixed = hyper
        obj._restore_extra(arrays)
        obj._finalise()
        obj.var_scale_ = {k[len("varscale/"):]: np.asarray(a, dtype=np.float64)
                          for k, a in arrays.items() if k.startswith("varscale/")}
        return obj

    def _restore_extra(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Hook for subclasses: restore their own arrays before the predictors are built."""

    def save(self, path: str | os.PathLike) -> Path:
        """Write ``<path>.json`` (metadata) and ``<path>.npz`` (arrays), atomically."""
        path = Path(path)
        meta, arrays = self.state()
        return write_model_files(path.with_suffix(".json"), path.with_suffix(".npz"), meta, arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> SGPDM:
        """Read a model written by :meth:`save`; errors name the damaged file."""
        path = Path(path)
        jpath, npath = path.with_suffix(".json"), path.with_suffix(".npz")
        meta, arrays = read_model_files(jpath, npath)
        return cls.from_state(meta, arrays)
