"""Label-switched linear dynamical systems: SLDS and DPDS (englebienne2008 §3, App. A).

Both models are driven by the known frame labels π_{1:T} (no audio) and use the
observation = state convention B = I of englebienne2008 §3:

    x_1 = μ_{π_1} (+ noise),   x_t = A_{π_t} x_{t−1} + ν_{π_t} (+ w_t),   y_t = x_t + v_t,

where y_t is the visual feature vector z_t (``Sequence.aam``), A_π is diagonal and all
covariances are diagonal. With diagonal A and covariances every visual dimension is an
independent scalar system, which is how both models are computed (vectorised over the
dimensions and over sequences, which are padded to a common length and masked).

Labels: ``μ_π`` is the mean of the *first* frame of the sequences that start with phone π;
a new phone segment does NOT restart the state: the paper's recursion
x_t = A_{π_t} x_{t−1} + ν_{π_t} runs for every t ≥ 2 across phone boundaries (eq. 1; in
App. A, Algorithm 1 accumulates the μ_n coefficients only over sequences whose first
label is n, and the ν coefficients through all t ≥ 2). For a phone that never starts a
training sequence μ_π is not identifiable; it is set to the mean of that phone's training
frames (used only if a test sequence starts with it). Unseen phones: see
:class:`bayes_talk.baselines.base.LabelEncoder`.

Generation (englebienne2008 §3, "Sequence generation"), both models:

    ŷ_1 = μ_{π_1},   ŷ_t = A_{π_t} ŷ_{t−1} + ν_{π_t}                       (GEN)

i.e. the mean (= most likely) observation sequence for the labels.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Self

import numpy as np
import scipy.linalg
import scipy.optimize

from bayes_talk.baselines.base import Baseline, LabelEncoder, check_test, check_train
from bayes_talk.data.sequence import Sequence

__all__ = [
    "DPDS",
    "SLDS",
    "Batch",
    "dpds_forward",
    "dpds_grad_A",
    "dpds_loglik",
    "dpds_profile",
    "dpds_solve_mu_nu",
    "kalman_smoother",
    "make_batch",
    "mean_trajectory",
]

_LOG2PI = float(np.log(2.0 * np.pi))


# --------------------------------------------------------------------------- batching
@dataclass(frozen=True)
class Batch:
    """Sequences padded to a common length (time-major).

    Y : (T_max, S, D) observations (0 where padded); L : (T_max, S) label indices
    (0 where padded); M : (T_max, S) bool validity mask.
    """

    Y: np.ndarray
    L: np.ndarray
    M: np.ndarray

    @property
    def n_frames(self) -> int:
        return int(self.M.sum())


def make_batch(labels: list[np.ndarray], Y: list[np.ndarray] | None = None,
               n_dims: int | None = None) -> Batch:
    """Pad per-sequence label indices (T_s,) and observations (T_s, D) into a :class:`Batch`."""
    S = len(labels)
    if S == 0:
        raise ValueError("no sequences")
    T = max(len(l) for l in labels)
    D = Y[0].shape[1] if Y is not None else int(n_dims or 0)
    Yb = np.zeros((T, S, D))
    Lb = np.zeros((T, S), dtype=np.int64)
    Mb = np.zeros((T, S), dtype=bool)
    for s, l in enumerate(labels):
        n = len(l)
        Lb[:n, s] = l
        Mb[:n, s] = True
        if Y is not None:
            if Y[s].shape != (n, D):
                raise ValueError(f"sequence {s}: observations have shape {Y[s].shape}, expected {(n, D)}")
            Yb[:n, s] = Y[s]
    return Batch(Yb, Lb, Mb)


def mean_trajectory(A: np.ndarray, nu: np.ndarray, mu: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(GEN): ŷ_1 = μ_{π_1}, ŷ_t = A_{π_t} ŷ_{t−1} + ν_{π_t}; A, ν, μ are (Π, D) diagonals."""
    out = np.empty((len(idx), A.shape[1]))
    out[0] = mu[idx[0]]
    for t in range(1, len(idx)):
        out[t] = A[idx[t]] * out[t - 1] + nu[idx[t]]
    return out


def _label_means(batch: Batch, n_labels: int) -> np.ndarray:
    sums = np.zeros((n_labels, batch.Y.shape[2]))
    np.add.at(sums, batch.L[batch.M], batch.Y[batch.M])
    cnt = np.bincount(batch.L[batch.M], minlength=n_labels)
    return sums / np.maximum(cnt, 1)[:, None]


def _init_ar(batch: Batch, n_labels: int, a_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-label least-squares fit of y_t ≈ a y_{t−1} + ν on the observations (initialisation).

    Returns a (clipped to [0, a_max]), ν and the residual variance, each (Π, D).
    """
    D = batch.Y.shape[2]
    v = batch.M[1:]
    lab = batch.L[1:][v]
    yp, yc = batch.Y[:-1][v], batch.Y[1:][v]
    st = {k: np.zeros((n_labels, D)) for k in ("pp", "p", "c", "x", "xx")}
    for k, val in (("pp", yp * yp), ("p", yp), ("c", yc * yp), ("x", yc), ("xx", yc * yc)):
        np.add.at(st[k], lab, val)
    n = np.bincount(lab, minlength=n_labels).astype(np.float64)[:, None]
    det = st["pp"] * n - st["p"] ** 2
    ok = (n > 1) & (det > 1e-12 * np.maximum(st["pp"] * n, 1e-300))
    a = np.where(ok, (st["c"] * n - st["p"] * st["x"]) / np.where(ok, det, 1.0), 0.5)
    a = np.clip(a, 0.0, a_max)
    mean_x = st["x"] / np.maximum(n, 1)
    mean_p = st["p"] / np.maximum(n, 1)
    nu = np.where(n > 0, mean_x - a * mean_p, 0.0)
    res = st["xx"] - 2 * a * st["c"] - 2 * nu * st["x"] + a * a * st["pp"] + 2 * a * nu * st["p"] + nu * nu * n
    var = np.where(n > 0, res / np.maximum(n, 1), np.nan)
    return a, nu, var


def _first_frame_means(batch: Batch, n_labels: int, values: np.ndarray,
                       fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` (S, D) over sequences grouped by first label; fallback elsewhere."""
    sums = np.zeros((n_labels, values.shape[1]))
    np.add.at(sums, batch.L[0], values)
    cnt = np.bincount(batch.L[0], minlength=n_labels)
    out = np.where(cnt[:, None] > 0, sums / np.maximum(cnt, 1)[:, None], fallback)
    return out, cnt > 0


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
        ll += M[t] * np.sum(-0.5 * (_LOG2PI + np.log(Sv) + e * e / Sv), axis=1)
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


def label_batch(encoder: LabelEncoder, seqs: list[Sequence]) -> Batch:
    """:func:`make_batch` of the sequences' encoded frame labels and visual features."""
    return make_batch([encoder.encode(s.labels, where=f"sequence {s.name!r}") for s in seqs],
                      [s.aam for s in seqs])


def _prepare_fit(model, train: list[Sequence]) -> tuple[int, int, int, Batch, np.ndarray]:
    """Shared start of SLDS/DPDS ``fit``: check the data, fit the label encoder on
    ``model``, batch the sequences, and the per-dimension data variance (1 where zero).
    Returns (D_y, D_z, number of labels, batch, data variance)."""
    d_y, d_z = check_train(train)
    model.encoder_ = LabelEncoder().fit(train)
    b = label_batch(model.encoder_, train)
    data_var = b.Y[b.M].var(axis=0)
    data_var[data_var <= 0] = 1.0
    return d_y, d_z, model.encoder_.n_classes, b, data_var


class SLDS(Baseline):
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
        self.n_iter = int(n_iter)
        self.tol = float(tol)
        self.var_floor = float(var_floor)
        self.a_init_max = float(a_init_max)

    def _batch(self, seqs: list[Sequence]) -> Batch:
        return label_batch(self.encoder_, seqs)

    def fit(self, train: list[Sequence]) -> Self:
        d_y, d_z, P, b, data_var = _prepare_fit(self, train)
        floor = self.var_floor * data_var
        lmean = _label_means(b, P)
        a, nu, res = _init_ar(b, P, self.a_init_max)
        fin = np.isfinite(res)
        res_glob = np.where(fin.any(axis=0),
                            np.where(fin, res, 0.0).sum(axis=0) / np.maximum(fin.sum(axis=0), 1),
                            data_var)
        Q = np.maximum(np.where(np.isfinite(res), res, res_glob) / 2, floor)
        R = np.maximum(res_glob / 2, floor)
        mu0, _ = _first_frame_means(b, P, b.Y[0], lmean)
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
            mu0, _ = _first_frame_means(b, P, m[0], mu0)
            P0 = np.maximum(np.mean((m[0] - mu0[b.L[0]]) ** 2 + Pv[0], axis=0), floor)
        self.A_, self.nu_, self.Q_, self.R_, self.mu0_, self.P0_ = a, nu, Q, R, mu0, P0
        self.loglik_history_ = np.array(hist)
        self.n_iter_ = len(hist) - 1
        self.n_audio_, self.n_visual_ = d_y, d_z
        return self

    def predict(self, seq: Sequence) -> np.ndarray:
        """(GEN) mean trajectory for ``seq.labels``."""
        self._check_fitted()
        check_test(seq)
        idx = self.encoder_.encode(seq.labels, where=f"sequence {seq.name!r}")
        return mean_trajectory(self.A_, self.nu_, self.mu0_, idx)

    def log_likelihood(self, seq: Sequence) -> float:
        """log p(z_{1:T} | π_{1:T}) by the Kalman filter (labels only, no audio)."""
        self._check_fitted()
        check_test(seq, n_visual=self.n_visual_, need_aam=True)
        b = self._batch([seq])
        es = kalman_smoother(b, self.A_, self.nu_, self.Q_, self.R_, self.mu0_, self.P0_, smooth=False)
        return float(es["loglik"][0])


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
    return float(-0.5 * np.sum(_LOG2PI + np.log(R) + r * r / R))


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
    ll = float(-0.5 * np.sum(_LOG2PI + np.log(R) + r * r / R))
    return ll, dpds_grad_A(A, nu, mu, R, batch), mu, nu, R


class DPDS(Baseline):
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
        self.max_iter = int(max_iter)
        self.a_max = float(a_max)
        self.var_floor = float(var_floor)
        self.gtol = float(gtol)

    def _batch(self, seqs: list[Sequence]) -> Batch:
        return label_batch(self.encoder_, seqs)

    def fit(self, train: list[Sequence]) -> Self:
        d_y, d_z, P, b, data_var = _prepare_fit(self, train)
        floor = self.var_floor * data_var
        N = b.n_frames
        lmean = _label_means(b, P)
        a0, _, _ = _init_ar(b, P, self.a_max)
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
        self.optim_result_ = res
        self.n_audio_, self.n_visual_ = d_y, d_z
        return self

    def predict(self, seq: Sequence) -> np.ndarray:
        """(GEN) deterministic trajectory for ``seq.labels``."""
        self._check_fitted()
        check_test(seq)
        idx = self.encoder_.encode(seq.labels, where=f"sequence {seq.name!r}")
        return mean_trajectory(self.A_, self.nu_, self.mu_, idx)

    def log_likelihood(self, seq: Sequence) -> float:
        """Σ_t log N(z_t; x̂_t, R) with x̂ from (GEN) (labels only, no audio)."""
        self._check_fitted()
        check_test(seq, n_visual=self.n_visual_, need_aam=True)
        r = seq.aam - self.predict(seq)
        return float(-0.5 * np.sum(_LOG2PI + np.log(self.R_) + r * r / self.R_))
