"""A fitted GP predictor's arrays in NumPy, and its predictive from them: :class:`NumpyGP`.

The synthesis density (:mod:`bayes_talk.synthesis.joint`) and the segment objective of
Algorithms 1-2 (:mod:`bayes_talk.synthesis.segment_objective`) read every state's GPs through
it: the predictive mean and variance, the gradient of the mean, and the predictive
log-likelihood of rows with its gradients (deena2009 eq. 9; docs/model.md), by the compiled
loops of :mod:`bayes_talk.gp.predictive_fused` unless ``BAYES_TALK_FUSED=0``, then by NumPy
and LAPACK (:meth:`NumpyGP.loglik_numpy`, the reference a test compares them with).
"""
from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dtrtrs

from bayes_talk.base import settings
from bayes_talk.gp.predictive import GPPredictor
from bayes_talk.gp.predictive_fused import (
    LOG_2PI,
    pad_inputs,
    predictive_loglik,
    predictive_mean_var,
    predictive_mean_vjp,
    take_inputs,
)


class NumpyGP:
    """Arrays of a fitted :class:`GPPredictor`, cached on it once.

    Every predictive goes through the Cholesky factor L of K (docs/model.md): with
    V = L⁻¹k(X, x), σ² = α − Σ V² + β⁻¹ and K⁻¹k = L⁻ᵀV. An explicit K⁻¹ cancels
    catastrophically when β is large (β_x = 10⁶ for the dynamics: σ² came out 0.18 instead
    of 7.4e-8 in the silence state). σ² is floored at β⁻¹, its exact lower bound.
    """

    def __init__(self, p: GPPredictor):
        # copies, never views: a view dangles when torch swaps a tensor's storage (it
        # does when a process pool pickles the model: Tensor.share_memory_)
        self.X = p.X.numpy().copy()
        self.A = p.A.numpy().copy()
        # one copy of the N×N factor, row-major for the compiled path (row by row); the
        # column-major one LAPACK wants is made only if the NumPy path runs (:attr:`L`)
        self.Lc = np.array(p.L.numpy(), order="C", copy=True)
        self._L: np.ndarray | None = None
        self.alpha, self.gamma, self.beta = float(p.alpha), float(p.gamma), float(p.beta)
        self.w2 = (p.w * p.w).numpy().copy()
        self.mean = p.mean.numpy().copy()
        self._no_extra = np.zeros(self.A.shape[1])
        #: the first ``in_dims`` latent dimensions are the GP's inputs (None: all; GPPredictor)
        self.in_dims = getattr(p, "in_dims", None)
        if p.alpha_lin is not None:
            raise NotImplementedError("closed-form objective supports the RBF kernel only")

    @property
    def L(self) -> np.ndarray:
        """The Cholesky factor in column-major order (dtrtrs), made on first use."""
        if self._L is None:
            self._L = np.asfortranarray(self.Lc)
        return self._L

    def _solve(self, B: np.ndarray, trans: int = 0) -> np.ndarray:
        """L⁻¹B (trans=0) or L⁻ᵀB (trans=1) by LAPACK's triangular solve (dtrtrs)."""
        x, info = dtrtrs(self.L, B, lower=1, trans=trans)
        if info != 0:
            raise np.linalg.LinAlgError(f"triangular solve failed (LAPACK info {info})")
        return x

    def kernel(self, Xs: np.ndarray) -> np.ndarray:
        """k(Xs, X) (T×N), from the differences x − X_i (exact; the expansion
        ‖x‖² + ‖X_i‖² − 2xᵀX_i is faster but its rounding changed Algorithm 2's paths enough
        to fail the resampling robustness test)."""
        diff = Xs[:, None, :] - self.X[None, :, :]
        return self.alpha * np.exp(-0.5 * self.gamma * (diff * diff).sum(-1))

    def mean_var(self, Xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """μ (T×D, training mean added) and σ² (T,), as :meth:`GPPredictor.mean_var`."""
        Xs = take_inputs(Xs, self.in_dims)
        if settings.get("fused"):
            Xs = np.ascontiguousarray(Xs, dtype=np.float64)
            mu, s = np.empty((Xs.shape[0], self.A.shape[1])), np.empty(Xs.shape[0])
            predictive_mean_var(self.X, self.A, self.Lc, self.mean, self.alpha, self.gamma, self.beta, Xs, mu, s)
            return mu, s
        k = self.kernel(Xs)
        V = self._solve(k.T)
        s = np.maximum(self.alpha - (V * V).sum(0) + 1.0 / self.beta, 1.0 / self.beta)
        return k @ self.A + self.mean, s

    def mean_vjp(self, Xs: np.ndarray, G: np.ndarray) -> np.ndarray:
        """Σ_m G_tm ∂μ_m(x_t)/∂x_t for each row (T×d): −γ Σ_i k_i (A G_t)_i (x_t − X_i)."""
        d, Xs = Xs.shape[1], take_inputs(Xs, self.in_dims)
        if settings.get("fused"):
            Xs = np.ascontiguousarray(Xs, dtype=np.float64)
            out = np.empty(Xs.shape)
            predictive_mean_vjp(self.X, self.A, self.alpha, self.gamma, Xs, np.ascontiguousarray(G, dtype=np.float64), out)
            return pad_inputs(out, d)
        c = self.kernel(Xs) * (G @ self.A.T)
        return pad_inputs(-self.gamma * (c.sum(-1)[:, None] * Xs - c @ self.X), d)

    def loglik(self, Y: np.ndarray, Xs: np.ndarray, extra_var: np.ndarray | None = None,
               rowwise: bool = False):
        """ℓ summed over rows (``rowwise``: per row, (T,)), ∂ℓ/∂Xs (T×d), ∂ℓ/∂Y (T×D).

        Rows are independent, so many inputs can share one call (and one pair of
        triangular solves): :meth:`UtteranceDensity.batch` stacks them. Computed by the
        compiled loop of :mod:`bayes_talk.gp.predictive_fused` unless ``BAYES_TALK_FUSED=0``
        (then by :meth:`loglik_numpy`, the reference)."""
        if not settings.get("fused"):
            return self.loglik_numpy(Y, Xs, extra_var, rowwise)
        d = Xs.shape[1]
        Y = np.ascontiguousarray(Y, dtype=np.float64)
        Xs = np.ascontiguousarray(take_inputs(Xs, self.in_dims), dtype=np.float64)
        T = Xs.shape[0]
        ll = np.empty(T)
        gx = np.empty((T, Xs.shape[1]))
        gy = np.empty(Y.shape)
        extra = self._no_extra if extra_var is None else np.ascontiguousarray(extra_var, dtype=np.float64)
        predictive_loglik(self.X, self.A, self.Lc, self.mean, self.alpha, self.gamma, self.beta,
                          self.w2, Y, Xs, extra, ll, gx, gy)
        return (ll if rowwise else float(ll.sum())), pad_inputs(gx, d), gy

    def loglik_numpy(self, Y: np.ndarray, Xs: np.ndarray, extra_var: np.ndarray | None = None,
                     rowwise: bool = False):
        """:meth:`loglik` by NumPy and LAPACK (dtrtrs): the reference of the compiled path."""
        d, Xs = Xs.shape[1], take_inputs(Xs, self.in_dims)
        k = self.kernel(Xs)                                           # T×N
        mu = k @ self.A + self.mean                                  # T×D
        V = self._solve(k.T)                                          # N×T: L⁻¹k
        Kk = self._solve(V, trans=1).T                                # T×N: K⁻¹k = L⁻ᵀL⁻¹k
        s_raw = self.alpha - (V * V).sum(0) + 1.0 / self.beta
        floor = 1.0 / self.beta
        s = np.maximum(s_raw, floor)                                  # T
        v = s[:, None] / self.w2[None, :]
        if extra_var is not None:
            v = v + extra_var[None, :]
        r = Y - mu
        if rowwise:
            ll = -0.5 * (LOG_2PI * r.shape[1] + np.log(v).sum(1) + (r * r / v).sum(1))
        else:
            ll = -0.5 * (LOG_2PI * r.size + np.log(v).sum() + (r * r / v).sum())
        g_mu = r / v                                                 # T×D
        g_s = ((r * r / v - 1.0) / (2.0 * v) / self.w2[None, :]).sum(-1)  # T
        g_s = np.where(s_raw > floor, g_s, 0.0)
        c = k * (g_mu @ self.A.T - 2.0 * g_s[:, None] * Kk)          # T×N
        g_x = -self.gamma * (c.sum(-1)[:, None] * Xs - c @ self.X)   # T×d
        return ll, pad_inputs(g_x, d), -g_mu


def numpy_gp(p: GPPredictor) -> NumpyGP:
    """The GP predictor's arrays as NumPy (float64), made once and cached on it."""
    cached = getattr(p, "_numpy_gp", None)
    if cached is None:
        cached = NumpyGP(p)
        p._numpy_gp = cached
    return cached


__all__ = ["NumpyGP", "numpy_gp"]
