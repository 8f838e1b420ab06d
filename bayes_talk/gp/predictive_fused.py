"""The GP predictive log-likelihood of a few rows and its gradient in one compiled pass (for speed).

The synthesis density (:mod:`bayes_talk.synthesis.joint`) and the segment objective of
Algorithms 1-2 (:mod:`bayes_talk.synthesis.segment_objective`) evaluate, thousands of times
per utterance, the predictive log-likelihood of 1-5 rows under a state's GP with N ≈ 30-300
training points. For a GP with training inputs X (N×d), A = K⁻¹Y (N×D), the Cholesky
factor L of K, and each input row x with target y (deena2009 eq. 9; docs/model.md):

    k_i = α exp(−γ/2 ‖x − X_i‖²),  μ = kᵀA + ȳ,  v = L⁻¹k,  u = L⁻ᵀv = K⁻¹k
    s = max(α − vᵀv + β⁻¹, β⁻¹),   var_m = s / w_m² + e_m
    ℓ = Σ_m ln N(y_m; μ_m, var_m)
    ∂ℓ/∂μ_m = r_m / var_m,   ∂ℓ/∂s = Σ_m (r_m²/var_m − 1) / (2 var_m w_m²)   (0 where s is floored)
    ∂ℓ/∂x = −γ Σ_i c_i (x − X_i),   c = k ∘ (A ∂ℓ/∂μ − 2 (∂ℓ/∂s) u),   ∂ℓ/∂y = −∂ℓ/∂μ

At these sizes the NumPy version spends most of its time in call overhead (a kernel matrix,
two LAPACK triangular solves and a dozen reductions per call, ~230 µs); this loop does the
same arithmetic row by row (forward and back substitution through L, O(N²) per row) with no
temporaries. Single-threaded and in a fixed order: the result does not depend on the thread
count. :class:`~bayes_talk.gp.numpy_gp.NumpyGP` uses it unless
``BAYES_TALK_FUSED=0`` (then the NumPy/LAPACK path, the reference a test compares with).
The same loops give the predictive mean and variance alone (:func:`predictive_mean_var`) and
the reverse pass of μ and s through their input (:func:`predictive_mean_var_vjp`, the
gradient of the dynamics in the non-centred coordinates of :mod:`bayes_talk.posterior.noncentred`);
:class:`PackedGPs` runs any of them over rows of several GPs in one call.

Floating-point flags: the loops here and in :mod:`bayes_talk.gp.fused` are compiled with ``fastmath={"reassoc"}`` (so the
reductions vectorise), not with ``"contract"`` too: with both, the machine code numba
compiled in a process and the code it loaded from its on-disk cache (``cache=True``) gave
different last bits (seen in the segment objective and the packed predictives), so a
synthesis or a chain run in a fresh worker process differed from the same run in the
process that compiled first. Reassociation alone, or no flag, gives the same bits either
way (tests/gp/test_compiled_determinism.py) at the same speed (measured within ±20 % at
N = 40-300 on a loaded machine; no flags at all was 1.3-2× slower there).
"""
from __future__ import annotations

import math

import numba
import numpy as np

LOG_2PI = math.log(2.0 * math.pi)


@numba.njit(cache=True, fastmath={"reassoc"})
def kernel_rows(X: np.ndarray, alpha: float, gamma: float, Xs: np.ndarray) -> np.ndarray:
    """k(Xs, X) (T×N) from the differences x − X_i."""
    T, d = Xs.shape
    N = X.shape[0]
    k = np.empty((T, N))
    for t in range(T):
        for i in range(N):
            s2 = 0.0
            for j in range(d):
                diff = Xs[t, j] - X[i, j]
                s2 += diff * diff
            k[t, i] = alpha * math.exp(-0.5 * gamma * s2)
    return k


@numba.njit(cache=True, fastmath={"reassoc"})
def forward_solve_rows(L: np.ndarray, k: np.ndarray) -> np.ndarray:
    """V = k L⁻ᵀ (T×N): each row solves L v = k_t. Row i of L is applied to every input
    while it is in cache, so L is read once per call, not once per input; four inputs at a
    time share each load of L[i, j] (each input's sum runs in the same order as one at a
    time, so the bits are the same: tests/gp/test_predictive_fused_blocking.py)."""
    T, N = k.shape
    v = np.empty((T, N))
    for i in range(N):
        piv = L[i, i]
        t = 0
        while t + 4 <= T:
            a0, a1, a2, a3 = k[t, i], k[t + 1, i], k[t + 2, i], k[t + 3, i]
            for j in range(i):
                lij = L[i, j]
                a0 -= lij * v[t, j]
                a1 -= lij * v[t + 1, j]
                a2 -= lij * v[t + 2, j]
                a3 -= lij * v[t + 3, j]
            v[t, i], v[t + 1, i], v[t + 2, i], v[t + 3, i] = a0 / piv, a1 / piv, a2 / piv, a3 / piv
            t += 4
        for r in range(t, T):
            acc = k[r, i]
            for j in range(i):
                acc -= L[i, j] * v[r, j]
            v[r, i] = acc / piv
    return v


@numba.njit(cache=True, fastmath={"reassoc"})
def back_solve_rows(L: np.ndarray, v: np.ndarray) -> np.ndarray:
    """U = V L⁻¹ (T×N): each row solves Lᵀ u = v_t (u = K⁻¹k_t when v_t = L⁻¹k_t), in column
    form, so row i of L is read once for all inputs."""
    T, N = v.shape
    w = v.copy()
    for i in range(N - 1, -1, -1):
        piv = L[i, i]
        for t in range(T):
            ui = w[t, i] / piv
            w[t, i] = ui
            for j in range(i):
                w[t, j] -= L[i, j] * ui
    return w


@numba.njit(cache=True, fastmath={"reassoc"})
def input_gradient_row(X: np.ndarray, A: np.ndarray, gamma: float, k: np.ndarray, u: np.ndarray, x: np.ndarray,
                       g_mu: np.ndarray, g_s: float, out: np.ndarray) -> None:
    """Σ_m (g_mu)_m ∂μ_m/∂x + g_s ∂s/∂x at one input x (into out, (d,)):
    −γ Σ_i c_i (x − X_i), c = k ∘ (A g_mu − 2 g_s u), with k = k(x, X) and u = K⁻¹k (the
    module docstring's ∂ℓ/∂x with ∂ℓ/∂μ = g_mu and ∂ℓ/∂s = g_s)."""
    N, D = A.shape
    d = x.shape[0]
    for j in range(d):
        out[j] = 0.0
    for i in range(N):
        ag = 0.0
        for m in range(D):
            ag += A[i, m] * g_mu[m]
        c = k[i] * (ag - 2.0 * g_s * u[i])
        for j in range(d):
            out[j] += c * (x[j] - X[i, j])
    for j in range(d):
        out[j] *= -gamma


@numba.njit(cache=True, fastmath={"reassoc"})
def predictive_loglik(X: np.ndarray, A: np.ndarray, L: np.ndarray, mean: np.ndarray,
                      alpha: float, gamma: float, beta: float, w2: np.ndarray, Y: np.ndarray, Xs: np.ndarray,
                      extra: np.ndarray, ll: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> None:
    """Per-row ℓ (into ll, (T,)), ∂ℓ/∂Xs (into gx, (T, d)) and ∂ℓ/∂Y (into gy, (T, D)).

    L: the lower Cholesky factor of K (C order). Both substitutions walk L row by row and
    apply each row to all T inputs while it is in cache (L is read twice per call, not
    twice per row); extra: (D,) added variances (zeros for none)."""
    T = Xs.shape[0]
    N, D = A.shape
    floor = 1.0 / beta
    k = kernel_rows(X, alpha, gamma, Xs)
    v = forward_solve_rows(L, k)                    # L v = k
    w = back_solve_rows(L, v)                       # Lᵀ u = v
    mu = np.empty(D)
    gmu = np.empty(D)
    for t in range(T):
        vv = 0.0
        for i in range(N):
            vv += v[t, i] * v[t, i]
        for m in range(D):
            mu[m] = mean[m]
        for i in range(N):
            ki = k[t, i]
            for m in range(D):
                mu[m] += ki * A[i, m]
        s_raw = alpha - vv + floor
        s = max(floor, s_raw)
        lsum = 0.0
        gs = 0.0
        for m in range(D):
            var = s / w2[m] + extra[m]
            r = Y[t, m] - mu[m]
            q = r * r / var
            lsum += LOG_2PI + math.log(var) + q
            gmu[m] = r / var
            gs += (q - 1.0) / (2.0 * var) / w2[m]
            gy[t, m] = -gmu[m]
        ll[t] = -0.5 * lsum
        if not s_raw > floor:
            gs = 0.0
        input_gradient_row(X, A, gamma, k[t], w[t], Xs[t], gmu, gs, gx[t])


@numba.njit(cache=True, fastmath={"reassoc"})
def predictive_mean_var(X: np.ndarray, A: np.ndarray, L: np.ndarray, mean: np.ndarray, alpha: float,
                        gamma: float, beta: float, Xs: np.ndarray, mu: np.ndarray, s: np.ndarray) -> None:
    """μ = kᵀA + ȳ (into mu, (T, D)) and s = max(α − ‖L⁻¹k‖² + β⁻¹, β⁻¹) (into s, (T,))."""
    T = Xs.shape[0]
    N, D = A.shape
    floor = 1.0 / beta
    k = kernel_rows(X, alpha, gamma, Xs)
    v = forward_solve_rows(L, k)
    for t in range(T):
        vv = 0.0
        for i in range(N):
            vv += v[t, i] * v[t, i]
        sr = alpha - vv + floor
        s[t] = max(floor, sr)
        for m in range(D):
            mu[t, m] = mean[m]
        for i in range(N):
            ki = k[t, i]
            for m in range(D):
                mu[t, m] += ki * A[i, m]


@numba.njit(cache=True, fastmath={"reassoc"})
def predictive_mean_vjp(X: np.ndarray, A: np.ndarray, alpha: float, gamma: float, Xs: np.ndarray,
                        G: np.ndarray, out: np.ndarray) -> None:
    """Σ_m G_tm ∂μ_m(x_t)/∂x_t (into out, (T, d)): −γ Σ_i k_i (A G_t)_i (x_t − X_i)."""
    T, d = Xs.shape
    N, D = A.shape
    k = kernel_rows(X, alpha, gamma, Xs)
    for t in range(T):
        for j in range(d):
            out[t, j] = 0.0
        for i in range(N):
            ag = 0.0
            for m in range(D):
                ag += A[i, m] * G[t, m]
            c = k[t, i] * ag
            for j in range(d):
                out[t, j] += c * (Xs[t, j] - X[i, j])
        for j in range(d):
            out[t, j] *= -gamma


@numba.njit(cache=True, fastmath={"reassoc"})
def predictive_mean_var_vjp(X: np.ndarray, A: np.ndarray, L: np.ndarray, alpha: float, gamma: float, beta: float,
                            Xs: np.ndarray, G: np.ndarray, gs: np.ndarray, out: np.ndarray) -> None:
    """Σ_m G_tm ∂μ_m/∂x_t + gs_t ∂s/∂x_t (into out, (T, d)): −γ Σ_i k_i ((A G_t)_i − 2 gs_t u_i)(x_t − X_i),
    u = K⁻¹k (gs taken as 0 where s is floored at β⁻¹); the reverse pass of the dynamics
    mean and variance of :mod:`bayes_talk.posterior.noncentred`."""
    T = Xs.shape[0]
    N = A.shape[0]
    floor = 1.0 / beta
    k = kernel_rows(X, alpha, gamma, Xs)
    v = forward_solve_rows(L, k)
    w = back_solve_rows(L, v)
    for t in range(T):
        vv = 0.0
        for i in range(N):
            vv += v[t, i] * v[t, i]
        g = gs[t] if alpha - vv + floor > floor else 0.0
        input_gradient_row(X, A, gamma, k[t], w[t], Xs[t], G[t], g, out[t])


# ------------------------------------------------------------------ many GPs in one call
@numba.njit(cache=True, nogil=True)   # other threads (the progress heartbeat) run meanwhile
def _packed_loglik(run_gp, run_lo, run_hi, X, A, Lflat, offs, loffs, alpha, gamma, beta, w2, mean,
                   Y, Xs, extra, ll, gx, gy):
    """:func:`predictive_loglik` over runs of rows [lo, hi) that share GP ``run_gp``."""
    for r in range(run_gp.shape[0]):
        g, lo, hi = run_gp[r], run_lo[r], run_hi[r]
        o, n = offs[g], offs[g + 1] - offs[g]
        L = Lflat[loffs[g]:loffs[g] + n * n].reshape((n, n))
        predictive_loglik(X[o:o + n], A[o:o + n], L, mean[g], alpha[g], gamma[g], beta[g], w2[g],
                          Y[lo:hi], Xs[lo:hi], extra, ll[lo:hi], gx[lo:hi], gy[lo:hi])


@numba.njit(cache=True, nogil=True)   # other threads (the progress heartbeat) run meanwhile
def _packed_mean_var(run_gp, run_lo, run_hi, X, A, Lflat, offs, loffs, alpha, gamma, beta, mean, Xs, mu, s):
    """:func:`predictive_mean_var` over runs of rows that share a GP."""
    for r in range(run_gp.shape[0]):
        g, lo, hi = run_gp[r], run_lo[r], run_hi[r]
        o, n = offs[g], offs[g + 1] - offs[g]
        L = Lflat[loffs[g]:loffs[g] + n * n].reshape((n, n))
        predictive_mean_var(X[o:o + n], A[o:o + n], L, mean[g], alpha[g], gamma[g], beta[g], Xs[lo:hi],
                            mu[lo:hi], s[lo:hi])


@numba.njit(cache=True, nogil=True)   # other threads (the progress heartbeat) run meanwhile
def _packed_mean_var_vjp(run_gp, run_lo, run_hi, X, A, Lflat, offs, loffs, alpha, gamma, beta, Xs, G, gs, out):
    """:func:`predictive_mean_var_vjp` over runs of rows that share a GP."""
    for r in range(run_gp.shape[0]):
        g, lo, hi = run_gp[r], run_lo[r], run_hi[r]
        o, n = offs[g], offs[g + 1] - offs[g]
        L = Lflat[loffs[g]:loffs[g] + n * n].reshape((n, n))
        predictive_mean_var_vjp(X[o:o + n], A[o:o + n], L, alpha[g], gamma[g], beta[g], Xs[lo:hi], G[lo:hi],
                                gs[lo:hi], out[lo:hi])


@numba.njit(cache=True, nogil=True)   # other threads (the progress heartbeat) run meanwhile
def _packed_mean_vjp(run_gp, run_lo, run_hi, X, A, offs, alpha, gamma, Xs, G, out):
    """:func:`predictive_mean_vjp` over runs of rows that share a GP."""
    for r in range(run_gp.shape[0]):
        g, lo, hi = run_gp[r], run_lo[r], run_hi[r]
        o, n = offs[g], offs[g + 1] - offs[g]
        predictive_mean_vjp(X[o:o + n], A[o:o + n], alpha[g], gamma[g], Xs[lo:hi], G[lo:hi], out[lo:hi])


def take_inputs(Xs: np.ndarray, in_dims: int | None) -> np.ndarray:
    """The columns of latent rows ``Xs`` (R, d) that a GP reads: the first ``in_dims``, or
    all of them for None (GPPredictor.in_dims)."""
    return Xs if in_dims is None else Xs[:, :in_dims]


def pad_inputs(g: np.ndarray, d: int) -> np.ndarray:
    """A gradient (R, k) in a GP's k input dimensions as one in all d latent dimensions
    (zeros in the d − k it does not read: GPPredictor.in_dims); ``g`` itself when k = d."""
    if g.shape[1] == d:
        return g
    out = np.zeros((g.shape[0], d))
    out[:, :g.shape[1]] = g
    return out


class PackedGPs:
    """Several GP predictors of one output dimension D (e.g. every audio GP an utterance
    uses) packed into flat arrays, so one compiled call evaluates rows of all of them.

    Built from objects with the attributes of
    :class:`~bayes_talk.gp.numpy_gp.NumpyGP` (X, A, L, alpha, gamma, beta,
    w2, mean). Rows are described by :class:`Runs`: consecutive rows sharing a GP (each GP's
    Cholesky factor is read once per run)."""

    def __init__(self, gps: list):
        #: the GPs' inputs are the first ``in_dims`` latent dimensions (None: all); one value
        #: for the pack (GPPredictor.in_dims)
        dims = {getattr(g, "in_dims", None) for g in gps}
        if len(dims) > 1:
            raise ValueError(f"packed GPs must read the same latent dimensions, found in_dims {sorted(dims, key=str)}")
        self.in_dims = dims.pop() if dims else None
        self.n = len(gps)
        Ns = np.array([len(g.X) for g in gps], dtype=np.int64)
        self.offs = np.concatenate([[0], np.cumsum(Ns)]).astype(np.int64)
        self.loffs = np.concatenate([[0], np.cumsum(Ns * Ns)]).astype(np.int64)
        self.X = np.ascontiguousarray(np.concatenate([g.X for g in gps]))
        self.A = np.ascontiguousarray(np.concatenate([g.A for g in gps]))
        # row-major factors: NumpyGP keeps one (Lc); its column-major L is made only on demand
        self.L = np.concatenate([np.ascontiguousarray(g.Lc if hasattr(g, "Lc") else g.L).reshape(-1) for g in gps])
        self.alpha = np.array([g.alpha for g in gps])
        self.gamma = np.array([g.gamma for g in gps])
        self.beta = np.array([g.beta for g in gps])
        self.w2 = np.ascontiguousarray(np.stack([g.w2 for g in gps]))
        self.mean = np.ascontiguousarray(np.stack([g.mean for g in gps]))
        self.D = self.A.shape[1]

    def loglik(self, runs: Runs, Y: np.ndarray, Xs: np.ndarray, extra: np.ndarray | None = None):
        """Per-row ℓ (R,), ∂ℓ/∂Xs (R, d), ∂ℓ/∂Y (R, D) for rows laid out as ``runs``."""
        d, Xs = Xs.shape[1], take_inputs(Xs, self.in_dims)
        R = Xs.shape[0]
        ll, gx, gy = np.empty(R), np.empty((R, Xs.shape[1])), np.empty((R, self.D))
        ex = np.zeros(self.D) if extra is None else np.ascontiguousarray(extra, dtype=np.float64)
        _packed_loglik(runs.gp, runs.lo, runs.hi, self.X, self.A, self.L, self.offs, self.loffs, self.alpha,
                       self.gamma, self.beta, self.w2, self.mean, np.ascontiguousarray(Y, dtype=np.float64),
                       np.ascontiguousarray(Xs, dtype=np.float64), ex, ll, gx, gy)
        return ll, pad_inputs(gx, d), gy

    def loglik_value(self, runs: Runs, Y: np.ndarray, Xs: np.ndarray, extra: np.ndarray | None = None) -> np.ndarray:
        """Per-row ℓ (R,) alone, from :meth:`mean_var`: no back substitution and no gradient
        loop, about a third of :meth:`loglik`'s time for 64 rows of a 300-point GP (the
        particle sweeps need no gradient). Equal to :meth:`loglik`'s ℓ to round-off."""
        mu, s = self.mean_var(runs, Xs)
        var = s[:, None] / self.w2[runs.row_gp(1)] + (0.0 if extra is None else np.asarray(extra, dtype=np.float64))
        r = np.asarray(Y, dtype=np.float64) - mu
        return -0.5 * (LOG_2PI * self.D + np.log(var).sum(1) + (r * r / var).sum(1))

    def mean_var(self, runs: Runs, Xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """μ (R, D) and σ² (R,) for rows laid out as ``runs``."""
        Xs = take_inputs(Xs, self.in_dims)
        R = Xs.shape[0]
        mu, s = np.empty((R, self.D)), np.empty(R)
        _packed_mean_var(runs.gp, runs.lo, runs.hi, self.X, self.A, self.L, self.offs, self.loffs, self.alpha,
                         self.gamma, self.beta, self.mean, np.ascontiguousarray(Xs, dtype=np.float64), mu, s)
        return mu, s

    def mean_vjp(self, runs: Runs, Xs: np.ndarray, G: np.ndarray) -> np.ndarray:
        """Σ_m G_rm ∂μ_m(x_r)/∂x_r (R, d) for rows laid out as ``runs``."""
        d, Xs = Xs.shape[1], take_inputs(Xs, self.in_dims)
        out = np.empty(Xs.shape)
        _packed_mean_vjp(runs.gp, runs.lo, runs.hi, self.X, self.A, self.offs, self.alpha, self.gamma,
                         np.ascontiguousarray(Xs, dtype=np.float64), np.ascontiguousarray(G, dtype=np.float64), out)
        return pad_inputs(out, d)

    def mean_var_vjp(self, runs: Runs, Xs: np.ndarray, G: np.ndarray, gs: np.ndarray) -> np.ndarray:
        """Σ_m G_rm ∂μ_m(x_r)/∂x_r + gs_r ∂s(x_r)/∂x_r (R, d) for rows laid out as ``runs``
        (gs_r taken as 0 where s is floored at β⁻¹)."""
        d, Xs = Xs.shape[1], take_inputs(Xs, self.in_dims)
        out = np.empty(Xs.shape)
        _packed_mean_var_vjp(runs.gp, runs.lo, runs.hi, self.X, self.A, self.L, self.offs, self.loffs, self.alpha,
                             self.gamma, self.beta, np.ascontiguousarray(Xs, dtype=np.float64),
                             np.ascontiguousarray(G, dtype=np.float64), np.ascontiguousarray(gs, dtype=np.float64),
                             out)
        return pad_inputs(out, d)


class Runs:
    """Rows in runs of one GP: run r covers rows [lo_r, hi_r) of GP gp_r. ``repeat(k)``: the
    same runs with every row repeated k times in place (row i → rows k·i … k·i + k − 1), the
    layout of k perturbed or batched copies of each row."""

    def __init__(self, gp: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        self.gp = np.ascontiguousarray(gp, dtype=np.int64)
        self.lo = np.ascontiguousarray(lo, dtype=np.int64)
        self.hi = np.ascontiguousarray(hi, dtype=np.int64)

    @classmethod
    def one(cls, g: int, n: int) -> Runs:
        """n rows, all of GP g."""
        return cls(np.array([g]), np.array([0]), np.array([n]))

    @classmethod
    def of(cls, row_gp: np.ndarray) -> Runs:
        """Runs of a per-row GP index (rows of one GP should be consecutive)."""
        row_gp = np.asarray(row_gp, dtype=np.int64)
        if row_gp.size == 0:
            return cls(row_gp, row_gp, row_gp)
        cut = np.flatnonzero(np.diff(row_gp)) + 1
        lo = np.concatenate([[0], cut])
        hi = np.concatenate([cut, [row_gp.size]])
        return cls(row_gp[lo], lo, hi)

    def row_gp(self, k: int = 1) -> np.ndarray:
        """The GP of every row, each row repeated k times in place."""
        return np.repeat(np.repeat(self.gp, self.hi - self.lo), k)

    def repeat(self, k: int) -> Runs:
        """The runs of every row repeated k times in place."""
        return Runs(self.gp, self.lo * k, self.hi * k)
