"""Inducing-point (sparse) versions of the SGPDM's two likelihood terms.

With M inducing inputs Z (M×d) in the latent space, a kernel k and inputs X (N×d), write
K_mm = k(Z, Z), K_nm = k(X, Z) and the Nyström matrix Q_nn = K_nm K_mm⁻¹ K_mn. Both
terms below are the log-density of the N×D matrix V under independent columns with
covariance Q_nn + Λ, Λ = diag(λ_1..λ_N), minus a trace correction:

* Observation mappings (audio and visual views): the collapsed variational bound of
  Titsias (2009, eq. 9), Λ = σ² I with σ² = β⁻¹,

      F(X, Z) = ln N(V; 0, Q_nn + σ² I) − (D / 2σ²) · tr(K_nn − Q_nn)          (Titsias eq. 9)

  F ≤ ln p(V | X) (the exact eq. 5 of deena2010) for every Z, with equality when Z = X.
* Dynamics (deena2010 eq. 7 on the latent transitions X_in → X_out): FITC (Snelson &
  Ghahramani 2006; Lawrence 2007 §3, "FITC"), Λ = diag(K_nn − Q_nn) + σ_x² I and no
  trace term,

      ln p_FITC(X_out | X_in, Z) = ln N(X_out; 0, Q_nn + diag(K_nn − Q_nn) + σ_x² I),

  also exact when Z contains X_in. Why not the Titsias bound here: the dynamics noise is
  fixed at σ_x² = β_x⁻¹ = 10⁻⁶ (the 100:1 signal-to-noise ratio of deena2010 §4.1), so the
  trace penalty tr(K − Q)/(2σ_x²) is multiplied by 10⁶ and would pin every latent point
  onto an inducing point; DTC (no trace term, Λ = σ_x² I) has the same defect through its
  rank-M covariance. FITC's diagonal correction is the local predictive variance of each
  transition, so points away from Z are merely less constrained.

Evaluation (one M×M Cholesky per kernel, O(N M²)): with L_m = chol(K_mm),
A = L_m⁻¹ K_mn (M×N), Ã = A Λ^{−½}, B = I + Ã Ãᵀ = L_B L_Bᵀ and c = L_B⁻¹ Ã Λ^{−½} V,

    ln|Q_nn + Λ| = Σ_n ln λ_n + 2 Σ ln diag L_B,
    tr((Q_nn + Λ)⁻¹ V Vᵀ) = Σ_n ‖v_n‖²/λ_n − ‖c‖²,       diag Q_nn = Σ_m A_mn².

The predictive at a new latent point x (Titsias §3 / FITC, the same formula with the
model's Λ) is μ(x) = k(x, Z) Σ K_mn Λ⁻¹ V and σ²(x) = k(x,x) − k(x,Z)(K_mm⁻¹ − Σ)k(Z,x) + σ²,
Σ = (K_mm + K_mn Λ⁻¹ K_nm)⁻¹. :func:`sparse_predictor` writes it in the form of an exact GP
predictive on the inducing inputs (:class:`~bayes_talk.gp.predictive.GPPredictor`), so
every synthesis routine of the package (closed-form sequence optimisation, initialisers,
samplers) uses it unchanged: μ(x) = k(x,Z) A_Z and σ²(x) = α − ‖L_Z⁻¹ k(Z,x)‖² + σ² with

    A_Z = L_m⁻ᵀ L_B⁻ᵀ c,      L_Z L_Zᵀ = (K_mm⁻¹ − Σ)⁻¹ = K_mm + L_m (Ã Ãᵀ)⁻¹ L_mᵀ.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from bayes_talk.gp.kernels import rbf
from bayes_talk.gp.linalg import cholesky, solve_lower
from bayes_talk.gp.predictive import GPPredictor
from bayes_talk.gp.threads import one_thread

LOG_2PI = math.log(2.0 * math.pi)


def _kmm(Z: torch.Tensor, alpha, gamma, jitter: float) -> torch.Tensor:
    """K_mm + jitter·α·I (the relative jitter keeps the M×M factorisation stable while Z moves)."""
    K = rbf(Z, Z, alpha, gamma)
    if jitter > 0.0:
        K = K + (jitter * alpha) * torch.eye(Z.shape[0], dtype=Z.dtype)
    return K


def _projected(V: torch.Tensor, A: torch.Tensor, lam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """ln N(V; 0, AᵀA + diag λ) summed over columns, with (L_B, c) for the predictive."""
    N, D = V.shape
    s = torch.rsqrt(lam)
    At = A * s[None, :]
    B = At @ At.mT + torch.eye(A.shape[0], dtype=A.dtype)
    LB = cholesky(B, "sparse GP matrix I + ÃÃᵀ")
    Vs = V * s[:, None]
    c = solve_lower(LB, At @ Vs)
    logdet = torch.log(lam).sum() + 2.0 * torch.log(LB.diagonal()).sum()
    quad = (Vs * Vs).sum() - (c * c).sum()
    return -0.5 * (N * D * LOG_2PI + D * logdet + quad), LB, c


def titsias_bound(
    V: torch.Tensor, X: torch.Tensor, Z: torch.Tensor, alpha, gamma, beta, jitter: float = 1e-6,
) -> torch.Tensor:
    """Titsias (2009) eq. 9 for the N×D matrix V (already scaled by W) at inputs X:
    ln N(V; 0, Q_nn + β⁻¹I) − (D β / 2)·tr(K_nn − Q_nn)."""
    Lm = cholesky(_kmm(Z, alpha, gamma, jitter), "inducing kernel matrix K_mm")
    A = solve_lower(Lm, rbf(Z, X, alpha, gamma))
    N, D = V.shape
    lam = (1.0 / beta) * torch.ones(N, dtype=V.dtype)
    ll, _, _ = _projected(V, A, lam)
    trace = N * alpha - (A * A).sum()
    return ll - 0.5 * D * beta * trace


def fitc_loglik(
    V: torch.Tensor, X: torch.Tensor, Z: torch.Tensor, alpha, gamma, beta, jitter: float = 1e-6,
) -> torch.Tensor:
    """FITC: ln N(V; 0, Q_nn + diag(K_nn − Q_nn) + β⁻¹ I), columns independent."""
    Lm = cholesky(_kmm(Z, alpha, gamma, jitter), "inducing kernel matrix K_mm")
    A = solve_lower(Lm, rbf(Z, X, alpha, gamma))
    lam = (alpha - (A * A).sum(0)).clamp_min(0.0) + 1.0 / beta
    ll, _, _ = _projected(V, A, lam)
    return ll


def sparse_predictor(
    X: torch.Tensor,
    Y: torch.Tensor,
    Z: torch.Tensor,
    alpha: float,
    gamma: float,
    beta: float,
    w: torch.Tensor | None = None,
    mean: torch.Tensor | None = None,
    fitc: bool = False,
    jitter: float = 1e-6,
    what: str = "sparse GP",
) -> GPPredictor:
    """The sparse predictive (Titsias, or FITC with ``fitc=True``) as a :class:`GPPredictor`
    on the inducing inputs Z; ``Y`` (N×D, centred, unscaled) is kept for the nearest-neighbour
    initialiser, which looks up training frames. The W scaling cancels in the mean and is
    applied by the predictor's density, as for the exact model."""
    with torch.no_grad(), one_thread():   # the same bits whatever the caller's thread count
        X, Y, Z = X.detach(), Y.detach(), Z.detach()
        Lm = cholesky(_kmm(Z, alpha, gamma, jitter), f"{what}: inducing kernel matrix")
        A = solve_lower(Lm, rbf(Z, X, alpha, gamma))
        if fitc:
            lam = (alpha - (A * A).sum(0)).clamp_min(0.0) + 1.0 / beta
        else:
            lam = torch.full((X.shape[0],), 1.0 / beta, dtype=X.dtype)
        _, LB, c = _projected(Y, A, lam)
        A_Z = torch.linalg.solve_triangular(Lm.mT, torch.linalg.solve_triangular(LB.mT, c, upper=True), upper=True)
        At = A * torch.rsqrt(lam)[None, :]
        e, U = torch.linalg.eigh(At @ At.mT)
        e = e.clamp_min(float(e.max()) * 1e-12)
        LU = Lm @ U
        P = Lm @ Lm.mT + (LU / e[None, :]) @ LU.mT
        P = 0.5 * (P + P.mT)
        L_Z = cholesky(P, f"{what}: predictive matrix")
    return GPPredictor.from_factors(Z, Y, L_Z, A_Z, alpha, gamma, beta, w, mean)


def kmeans_inducing(X: np.ndarray, M: int, seed: int) -> np.ndarray:
    """M inducing inputs: k-means centres of the rows of X (scikit-learn, seeded); all of X
    when it has at most M rows."""
    X = np.asarray(X, dtype=np.float64)
    if len(X) <= M:
        return X.copy()
    from sklearn.cluster import KMeans

    km = KMeans(n_clusters=M, n_init=1, random_state=seed).fit(X)
    return np.asarray(km.cluster_centers_, dtype=np.float64)
