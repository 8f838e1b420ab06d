"""DPDS: the label-switched LDS trained by direct likelihood maximisation
(englebienne2008 §3, App. A); the model shared with SLDS is described in
:mod:`bayes_talk.estimators.baselines.lds`."""
from __future__ import annotations

from typing import ClassVar, Self

import numpy as np
import scipy.linalg
import scipy.optimize

from bayes_talk.data.utterance import Utterance, check_test
from bayes_talk.estimators.baselines.lds import (
    LOG2PI,
    Batch,
    LabelSwitchedLDS,
    init_ar,
    label_means,
    prepare_fit,
)

__all__ = ["DPDS", "dpds_forward", "dpds_grad_A", "dpds_loglik", "dpds_profile", "dpds_solve_mu_nu"]


# --------------------------------------------------------------------------- DPDS
def dpds_forward(A: np.ndarray, nu: np.ndarray, mu: np.ndarray, batch: Batch) -> np.ndarray:
    """Deterministic states x (T_max, S, D): x_1 = μ_{π_1}, x_t = A_{π_t} x_{t−1} + ν_{π_t}."""
    L = batch.L
    T, S = L.shape
    x = np.empty((T, S, A.shape[1]))
    x[0] = mu[L[0]]
    for t in range(1, T):
        x[t] = A[L[t]] * x[t - 1] + nu[L[t]]
    return x


def dpds_loglik(A: np.ndarray, nu: np.ndarray, mu: np.ndarray, R: np.ndarray, batch: Batch) -> float:
    """englebienne2008 eq. (1) with Σ_π = R (shared diagonal observation noise):

        log p(Y | π) = −½ Σ_s Σ_t [ log|2π R| + (y_t − x_t)ᵀ R⁻¹ (y_t − x_t) ].
    """
    r = (batch.Y - dpds_forward(A, nu, mu, batch))[batch.M]
    return float(-0.5 * np.sum(LOG2PI + np.log(R) + r * r / R))


def dpds_grad_A(A: np.ndarray, nu: np.ndarray, mu: np.ndarray, R: np.ndarray, batch: Batch) -> np.ndarray:
    """∂ log p / ∂a_{n,d} (Π, D) by forward accumulation, englebienne2008 eq. (2):

        ∂x_1/∂a_n = 0,   ∂x_t/∂a_n = δ_{n,π_t} x_{t−1} + a_{π_t} ∂x_{t−1}/∂a_n,
        ∂L/∂a_n = Σ_s Σ_{t≥2} R⁻¹ (y_t − x_t) ∂x_t/∂a_n

    (the extracted paper text prints x_t in the first term; differentiating
    x_t = A_{π_t} x_{t−1} + ν_{π_t} gives x_{t−1}).
    """
    Y, L, M = batch.Y, batch.L, batch.M
    T, S, D = Y.shape
    P = A.shape[0]
    x_prev = mu[L[0]]
    G = np.zeros((S, D, P))
    grad = np.zeros((P, D))
    srange = np.arange(S)
    for t in range(1, T):
        a = A[L[t]]
        G *= a[:, :, None]
        G[srange, :, L[t]] += x_prev
        x = a * x_prev + nu[L[t]]
        w = M[t][:, None] * (Y[t] - x) / R
        grad += np.einsum("sd,sdn->nd", w, G)
        x_prev = x
    return grad


def dpds_solve_mu_nu(A: np.ndarray, batch: Batch, mu_default: np.ndarray,
                     nu_default: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact maximiser of eq. (1) over μ, ν for fixed A (englebienne2008 eq. (3), Alg. 1).

    For fixed A every x_t is linear in θ = [μ_1..μ_Π, ν_1..ν_Π] (per dimension d):
    x_t = h_tᵀ θ with h_1 = e_{μ,π_1} and h_t = a_{π_t} h_{t−1} + e_{ν,π_t}. With a shared
    diagonal R the weights cancel, and θ solves the normal equations (eq. 3)

        (Σ_s Σ_t h_t h_tᵀ) θ = Σ_s Σ_t h_t y_{t,d},

    whose blocks are Algorithm 1's D^{μμ}, D^{μν}, D^{νμ}, D^{νν}, b^μ, b^ν. Parameters
    whose column is identically zero (a phone that never starts a sequence for μ, never
    occurs at t ≥ 2 for ν) are not identifiable and keep their ``*_default`` value.
    """
    Y, L, M = batch.Y, batch.L, batch.M
    T, S, D = Y.shape
    P = A.shape[0]
    H = np.zeros((D, S, 2 * P))
    srange = np.arange(S)
    H[:, srange, L[0]] = 1.0
    G = np.zeros((D, 2 * P, 2 * P))
    c = np.zeros((D, 2 * P))
    # rows h_t of the valid frames are buffered and reduced in chunks of ~chunk_rows rows,
    # so that Σ h hᵀ is one BLAS matrix product per dimension and chunk
    chunk_rows = 4096
    rows_H: list[np.ndarray] = []
    rows_Y: list[np.ndarray] = []
    n_rows = 0
    for t in range(T):
        if t > 0:
            H *= A[L[t]].T[:, :, None]
            H[:, srange, P + L[t]] += 1.0
        v = M[t]
        rows_H.append(H[:, v, :])
        rows_Y.append(Y[t][v].T)
        n_rows += int(v.sum())
        if n_rows >= chunk_rows or t == T - 1:
            X = np.concatenate(rows_H, axis=1)       # (D, rows, 2Π)
            yv = np.concatenate(rows_Y, axis=1)      # (D, rows)
            for d in range(D):  # 2-D products go to BLAS (a batched matmul of views does not)
                G[d] += X[d].T @ X[d]
                c[d] += X[d].T @ yv[d]
            rows_H, rows_Y, n_rows = [], [], 0
    mu, nu = mu_default.copy(), nu_default.copy()
    for d in range(D):
        act = np.diag(G[d]) > 0
        Ga, ca = G[d][np.ix_(act, act)], c[d][act]
        try:
            th = scipy.linalg.solve(Ga, ca, assume_a="pos")
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
            th = np.linalg.lstsq(Ga, ca, rcond=None)[0]
        full = np.concatenate([mu[:, d], nu[:, d]])
        full[act] = th
        mu[:, d], nu[:, d] = full[:P], full[P:]
    return mu, nu


def dpds_profile(A: np.ndarray, batch: Batch, mu_default: np.ndarray, nu_default: np.ndarray,
                 var_floor: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Profile log-likelihood L*(A) = max_{μ,ν,R} eq. (1) and its gradient.

    μ, ν by :func:`dpds_solve_mu_nu`, then R = Σ (y − x)² / N per dimension (floored at
    ``var_floor``); by the envelope theorem ∂L*/∂A = ∂L/∂A at (μ*, ν*, R*) (eq. 2).
    Returns (L*, ∂L*/∂A, μ*, ν*, R*).
    """
    mu, nu = dpds_solve_mu_nu(A, batch, mu_default, nu_default)
    r = (batch.Y - dpds_forward(A, nu, mu, batch))[batch.M]
    R = np.maximum(np.mean(r * r, axis=0), var_floor)
    ll = float(-0.5 * np.sum(LOG2PI + np.log(R) + r * r / R))
    return ll, dpds_grad_A(A, nu, mu, R, batch), mu, nu, R


class DPDS(LabelSwitchedLDS):
    """Deterministic Process Dynamical System (englebienne2008 §3, App. A).

    The SLDS with zero process noise: the state is a deterministic function of the labels,
    x_1 = μ_{π_1}, x_t = A_{π_t} x_{t−1} + ν_{π_t}, and z_t = x_t + v_t, v_t ~ N(0, R) with
    one diagonal R shared by all labels and frames (the paper shares R over states; we
    also use it for the first frame, Σ_π = R, which is what makes the unweighted normal
    equations of Algorithm 1 exact).

    Fit: maximise the profile log-likelihood L*(A) (:func:`dpds_profile`: exact μ, ν, R
    for each A, App. A) over the diagonal A_π with L-BFGS-B using the eq. (2) gradient.
    A is bounded to [−a_max, a_max] (stable generation). Initial A: per-label
    least-squares AR(1) fit of the observations clipped to [0, a_max]; deterministic.
    ``loglik_history_`` holds L*(A) after each L-BFGS iteration.

    Test log-likelihood: Σ_t log N(z_t; x̂_t, R) with x̂ from (GEN) -- conditioned on the
    frame labels only (not on the audio).
    """

    name: ClassVar[str] = "dpds"
    has_log_likelihood: ClassVar[bool] = True

    def __init__(self, max_iter: int = 200, a_max: float = 0.999, var_floor: float = 1e-5,
                 gtol: float = 1e-6) -> None:
        if not 0 < a_max < 1:
            raise ValueError(f"a_max must be in (0, 1), got {a_max}")
        if not var_floor > 0:
            raise ValueError(f"var_floor must be > 0, got {var_floor}")
        self.max_iter = max_iter
        self.a_max = a_max
        self.var_floor = var_floor
        self.gtol = gtol

    def fit(self, train: list[Utterance]) -> Self:
        """Maximise the likelihood over A by L-BFGS-B, μ and ν profiled out (class docstring); returns ``self``."""
        d_y, d_z, P, b, data_var = prepare_fit(self, train)
        floor = self.var_floor * data_var
        N = b.n_frames
        lmean = label_means(b, P)
        a0, _, _ = init_ar(b, P, self.a_max)
        shape = a0.shape
        cache: dict[str, object] = {}

        def f(theta: np.ndarray) -> tuple[float, np.ndarray]:
            A = theta.reshape(shape)
            ll, g, *_ = dpds_profile(A, b, lmean, (1 - A) * lmean, floor)
            cache.update(theta=theta.copy(), ll=ll)
            return -ll / N, -g.ravel() / N

        hist = [-N * f(a0.ravel())[0]]

        def cb(theta: np.ndarray) -> None:
            same = np.array_equal(theta, cache["theta"])
            hist.append(float(cache["ll"]) if same else -N * f(theta)[0])

        res = scipy.optimize.minimize(f, a0.ravel(), jac=True, method="L-BFGS-B",
                                      bounds=[(-self.a_max, self.a_max)] * a0.size, callback=cb,
                                      options={"maxiter": self.max_iter, "gtol": self.gtol})
        A = res.x.reshape(shape)
        ll, _, mu, nu, R = dpds_profile(A, b, lmean, (1 - A) * lmean, floor)
        self.A_, self.mu_, self.nu_, self.R_ = A, mu, nu, R
        self.loglik_history_ = np.array(hist)
        self.train_loglik_ = ll
        self.optim_result_ = {"success": bool(res.success), "nit": int(res.nit), "message": str(res.message)}
        self.n_audio_, self.n_visual_ = d_y, d_z
        return self

    def _start_means(self) -> np.ndarray:
        return self.mu_

    def log_likelihood(self, seq: Utterance) -> float:
        """Σ_t log N(z_t; x̂_t, R) with x̂ from (GEN) (labels only, no audio)."""
        self._check_fitted()
        check_test(seq, n_visual=self.n_visual_, need_aam=True)
        r = seq.aam - self.predict(seq)
        return float(-0.5 * np.sum(LOG2PI + np.log(self.R_) + r * r / self.R_))
