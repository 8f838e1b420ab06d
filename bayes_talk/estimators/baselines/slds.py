"""Switching LDS with known labels, trained by EM (englebienne2008 §3); the model shared
with DPDS is described in :mod:`bayes_talk.estimators.baselines.lds`."""
from __future__ import annotations

from typing import ClassVar, Self

import numpy as np

from bayes_talk.data.utterance import Utterance, check_test
from bayes_talk.estimators.baselines.lds import (
    LOG2PI,
    Batch,
    LabelSwitchedLDS,
    first_frame_means,
    init_ar,
    label_means,
    prepare_fit,
)

__all__ = ["SLDS", "kalman_smoother"]


# --------------------------------------------------------------------------- SLDS
def kalman_smoother(batch: Batch, A: np.ndarray, nu: np.ndarray, Q: np.ndarray, R: np.ndarray,
                    mu0: np.ndarray, P0: np.ndarray, smooth: bool = True) -> dict[str, np.ndarray]:
    """Kalman filter and Rauch-Tung-Striebel smoother of the label-switched LDS (B = I).

    Per dimension (all matrices diagonal), with predicted moments m⁻_t, P⁻_t:

        m⁻_1 = μ_{π_1}, P⁻_1 = P_0;   m⁻_t = a_t m_{t−1} + ν_t,   P⁻_t = a_t² P_{t−1} + q_t
        S_t = P⁻_t + r,  K_t = P⁻_t / S_t,  m_t = m⁻_t + K_t (y_t − m⁻_t),  P_t = (1 − K_t) P⁻_t
        log p(y_{1:T} | π) = Σ_t log N(y_t; m⁻_t, S_t)
        J_t = P_t a_{t+1} / P⁻_{t+1},  m̃_t = m_t + J_t (m̃_{t+1} − m⁻_{t+1}),
        P̃_t = P_t + J_t² (P̃_{t+1} − P⁻_{t+1}),  Cov(x_{t+1}, x_t | y) = J_t P̃_{t+1}.

    Returns a dict with ``loglik`` (S,) per sequence and, if ``smooth``, ``m`` and ``P``
    (T_max, S, D) smoothed moments and ``C`` (T_max, S, D) with C[t] = Cov(x_t, x_{t−1})
    (C[0] = 0 and 0 at padded steps).
    """
    Y, L, M = batch.Y, batch.L, batch.M
    T, S, D = Y.shape
    m_pred = np.empty((T, S, D))
    P_pred = np.empty((T, S, D))
    m_f = np.empty((T, S, D))
    P_f = np.empty((T, S, D))
    ll = np.zeros(S)
    for t in range(T):
        if t == 0:
            m_pred[0] = mu0[L[0]]
            P_pred[0] = np.broadcast_to(P0, (S, D))
        else:
            a = A[L[t]]
            m_pred[t] = a * m_f[t - 1] + nu[L[t]]
            P_pred[t] = a * a * P_f[t - 1] + Q[L[t]]
        Sv = P_pred[t] + R
        e = Y[t] - m_pred[t]
        ll += M[t] * np.sum(-0.5 * (LOG2PI + np.log(Sv) + e * e / Sv), axis=1)
        K = P_pred[t] / Sv
        m_f[t] = m_pred[t] + K * e
        P_f[t] = P_pred[t] * R / Sv
    out = {"loglik": ll}
    if not smooth:
        return out
    m_s = m_f.copy()
    P_s = P_f.copy()
    C = np.zeros((T, S, D))
    for t in range(T - 2, -1, -1):
        v = M[t + 1][:, None]
        J = P_f[t] * A[L[t + 1]] / P_pred[t + 1]
        m_s[t] = np.where(v, m_f[t] + J * (m_s[t + 1] - m_pred[t + 1]), m_f[t])
        P_s[t] = np.where(v, P_f[t] + J * J * (P_s[t + 1] - P_pred[t + 1]), P_f[t])
        C[t + 1] = np.where(v, J * P_s[t + 1], 0.0)
    out.update(m=m_s, P=P_s, C=C)
    return out




class SLDS(LabelSwitchedLDS):
    """Switching LDS with known labels, trained by EM (englebienne2008 §3).

    Model (per visual dimension, all matrices diagonal, B = I):

        x_1 ~ N(μ_{π_1}, P_0),  x_t = a_{π_t} x_{t−1} + ν_{π_t} + w_t,  w_t ~ N(0, q_{π_t}),
        z_t = x_t + v_t,  v_t ~ N(0, r).

    Per-label transition a_π, bias ν_π and process noise q_π; the observation noise r and
    the initial variance P_0 are shared by all labels (the paper allows R_π per label; a
    shared r keeps the model identifiable on small corpora and matches the DPDS). EM: the
    E-step is :func:`kalman_smoother`; the M-step is exact:

        [a_n, ν_n] solves [[Σ E x²_{t−1}, Σ E x_{t−1}], [Σ E x_{t−1}, N_n]] [a, ν]ᵀ
                          = [Σ E x_t x_{t−1}, Σ E x_t]ᵀ        (sums over t ≥ 2 with π_t = n)
        q_n = Σ E (x_t − a_n x_{t−1} − ν_n)² / N_n,  r = Σ_t E (z_t − x_t)² / N,
        μ_n = mean of E x_1 over sequences starting with n,  P_0 = Σ_s E (x_1 − μ_{π_1})² / S.

    Variances are floored at ``var_floor`` times the data variance of each dimension
    (a constrained M-step, EM stays monotone). ``loglik_history_`` records
    log p(Z | π; θ_k) at every E-step; it never decreases. Deterministic (no random
    initialisation): θ_0 is the per-label least-squares AR(1) fit of the observations
    with the residual variance split equally between q and r.

    Test log-likelihood: log p(z_{1:T} | π_{1:T}) by the Kalman filter -- conditioned on the
    frame labels only (not on the audio).
    """

    name: ClassVar[str] = "slds"
    has_log_likelihood: ClassVar[bool] = True

    def __init__(self, n_iter: int = 100, tol: float = 1e-6, var_floor: float = 1e-5,
                 a_init_max: float = 0.99) -> None:
        if n_iter < 0:
            raise ValueError(f"n_iter must be >= 0, got {n_iter}")
        if not var_floor > 0:
            raise ValueError(f"var_floor must be > 0, got {var_floor}")
        self.n_iter = n_iter
        self.tol = tol
        self.var_floor = var_floor
        self.a_init_max = a_init_max

    def fit(self, train: list[Utterance]) -> Self:
        """EM from the deterministic AR(1) start (class docstring); returns ``self``."""
        d_y, d_z, P, b, data_var = prepare_fit(self, train)
        floor = self.var_floor * data_var
        lmean = label_means(b, P)
        a, nu, res = init_ar(b, P, self.a_init_max)
        fin = np.isfinite(res)
        res_glob = np.where(fin.any(axis=0),
                            np.where(fin, res, 0.0).sum(axis=0) / np.maximum(fin.sum(axis=0), 1),
                            data_var)
        Q = np.maximum(np.where(np.isfinite(res), res, res_glob) / 2, floor)
        R = np.maximum(res_glob / 2, floor)
        mu0, _ = first_frame_means(b, P, b.Y[0], lmean)
        P0 = np.maximum(data_var, floor)
        hist: list[float] = []
        valid1 = b.M[1:]
        lab1 = b.L[1:][valid1]
        n_lab = np.bincount(lab1, minlength=P).astype(np.float64)[:, None]
        for it in range(self.n_iter + 1):
            es = kalman_smoother(b, a, nu, Q, R, mu0, P0)
            hist.append(float(es["loglik"].sum()))
            if it == self.n_iter:
                break
            if it > 0 and abs(hist[-1] - hist[-2]) <= self.tol * abs(hist[-2]):
                break
            m, Pv, C = es["m"], es["P"], es["C"]
            xp, xc = m[:-1][valid1], m[1:][valid1]
            Pp, Pc, Cc = Pv[:-1][valid1], Pv[1:][valid1], C[1:][valid1]
            st = {k: np.zeros((P, d_z)) for k in ("pp", "p", "c", "x", "xx")}
            for k, val in (("pp", xp * xp + Pp), ("p", xp), ("c", xc * xp + Cc), ("x", xc),
                           ("xx", xc * xc + Pc)):
                np.add.at(st[k], lab1, val)
            det = st["pp"] * n_lab - st["p"] ** 2
            ok = (n_lab > 0) & (det > 1e-12 * np.maximum(st["pp"] * n_lab, 1e-300))
            dsafe = np.where(ok, det, 1.0)
            a = np.where(ok, (st["c"] * n_lab - st["p"] * st["x"]) / dsafe, a)
            nu = np.where(ok, (st["pp"] * st["x"] - st["p"] * st["c"]) / dsafe, nu)
            sse = (st["xx"] - 2 * a * st["c"] - 2 * nu * st["x"] + a * a * st["pp"]
                   + 2 * a * nu * st["p"] + nu * nu * n_lab)
            Q = np.where(ok, np.maximum(sse / np.maximum(n_lab, 1), floor), Q)
            e = b.Y[b.M] - m[b.M]
            R = np.maximum(np.mean(e * e + Pv[b.M], axis=0), floor)
            mu0, _ = first_frame_means(b, P, m[0], mu0)
            P0 = np.maximum(np.mean((m[0] - mu0[b.L[0]]) ** 2 + Pv[0], axis=0), floor)
        self.A_, self.nu_, self.Q_, self.R_, self.mu0_, self.P0_ = a, nu, Q, R, mu0, P0
        self.loglik_history_ = np.array(hist)
        self.n_iter_ = len(hist) - 1
        self.n_audio_, self.n_visual_ = d_y, d_z
        return self

    def _start_means(self) -> np.ndarray:
        return self.mu0_

    def log_likelihood(self, seq: Utterance) -> float:
        """log p(z_{1:T} | π_{1:T}) by the Kalman filter (labels only, no audio)."""
        self._check_fitted()
        check_test(seq, n_visual=self.n_visual_, need_aam=True)
        b = self._batch([seq])
        es = kalman_smoother(b, self.A_, self.nu_, self.Q_, self.R_, self.mu0_, self.P0_, smooth=False)
        return float(es["loglik"][0])
