"""The segment objective of sequence optimisation in closed form (numpy), for speed.

The same log density as :func:`bayes_talk.synthesis.optimise.sequence_log_density`
(deena2009 eq. 9 with the entry term of deena2010 eq. 12 and the smoothness term), with
its gradient written out, so that MAP synthesis runs scipy's L-BFGS on plain arrays
instead of building an autograd graph for every evaluation of a 2-5 frame segment (the
torch version stays the reference: the samplers differentiate it, and a test checks the
two agree to round-off).

For a GP predictor with training inputs X (N×d), A = K⁻¹Y, K⁻¹, and an input x (computed by
:mod:`bayes_talk.gp.predictive_fused` on the arrays of :func:`bayes_talk.gp.numpy_gp.numpy_gp`):

    k_i = α exp(−γ/2 ‖x − X_i‖²),  μ = kᵀA + ȳ,  s = α − kᵀK⁻¹k + β⁻¹ = α − ‖L⁻¹k‖² + β⁻¹
    ℓ(y | x) = Σ_m ln N(y_m; μ_m, v_m),  v_m = s / w_m² (+ e_m, an optional extra variance)

    ∂ℓ/∂μ_m = r_m / v_m,   ∂ℓ/∂s = Σ_m (r_m²/v_m − 1) / (2 v_m w_m²),   r = y − μ
    ∂ℓ/∂x = −γ Σ_i c_i (x − X_i),   c = k ∘ (A ∂ℓ/∂μ − 2 (∂ℓ/∂s) K⁻¹k)
    ∂ℓ/∂y = −∂ℓ/∂μ

The dynamics term ℓ(x_t | x_{t−1}) is the same expression with the dynamics GP (w = 1,
ȳ = 0), differentiated in both its input x_{t−1} and its target x_t.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numba
import numpy as np

from bayes_talk.base import settings
from bayes_talk.gp.numpy_gp import numpy_gp
from bayes_talk.gp.predictive import GPPredictor
from bayes_talk.gp.predictive_fused import predictive_loglik

LOG_2PI = math.log(2.0 * math.pi)
#: L-BFGS iterations per segment (Algorithms 1 and 2): the one default of the library, the
#: command line and the evaluation protocols (SystemConfig.synth_max_iter)
SEGMENT_MAX_ITER = 50


def _gp_args(p: GPPredictor | None, D: int) -> tuple:
    """The arrays :func:`_segment_compiled` takes for one GP (an empty stand-in for None)."""
    if p is None:
        z = np.zeros((0, 1))
        return (z, z, z, np.zeros(D), 1.0, 1.0, 1.0, np.ones(D))
    g = numpy_gp(p)
    return (g.X, g.A, g.Lc, g.mean, g.alpha, g.gamma, g.beta, g.w2)


@numba.njit(cache=True)
def _block_sum(a: np.ndarray, lo: int, n: int) -> float:
    """NumPy's pairwise-summation leaf (n ≤ 128): eight running sums, then the rest."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r = a[lo:lo + 8].copy()
    i = 8
    while i < n - (n % 8):
        for j in range(8):
            r[j] += a[lo + i + j]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@numba.njit(cache=True)
def _numpy_sum(a: np.ndarray) -> float:
    """Σ a in the order of NumPy's pairwise summation (``ndarray.sum`` of a contiguous
    float64 vector: halves split at multiples of 8 down to blocks of ≤ 128), so the compiled
    objective equals the per-term one bit for bit (L-BFGS paths that stop at the iteration
    cap amplify a last-bit difference). The recursion is unrolled onto a stack: numba's
    cache cannot hold recursive functions (a cached caller segfaulted on reload)."""
    los = np.empty(64, np.int64)
    ns = np.empty(64, np.int64)
    st = np.zeros(64, np.int64)
    left = np.empty(64)
    los[0], ns[0], st[0] = 0, a.shape[0], 0
    sp, ret = 1, 0.0
    while sp > 0:
        i = sp - 1
        if ns[i] <= 128:
            ret = _block_sum(a, los[i], ns[i])
            sp -= 1
            continue
        n2 = ns[i] // 2
        n2 -= n2 % 8
        if st[i] == 0:
            st[i] = 1
            los[sp], ns[sp], st[sp] = los[i], n2, 0
            sp += 1
        elif st[i] == 1:
            left[i] = ret
            st[i] = 2
            los[sp], ns[sp], st[sp] = los[i] + n2, ns[i] - n2, 0
            sp += 1
        else:
            ret = left[i] + ret
            sp -= 1
    return ret


@numba.njit(cache=True)
def _segment_compiled(X, Y, obs, dyn, has_dyn, f_mu, f_prec, f_logdet, has_first, vis, z, e, has_smooth, g):
    """:func:`segment_objective` in one compiled call (the same terms in the same order as
    the per-term path below); the gradient goes into ``g`` (T×d), the value is returned."""
    T, d = X.shape
    ll = np.empty(T)
    gy = np.empty(Y.shape)
    predictive_loglik(obs[0], obs[1], obs[2], obs[3], obs[4], obs[5], obs[6], obs[7], Y, X,
                      np.zeros(Y.shape[1]), ll, g, gy)
    lp = _numpy_sum(ll)
    if has_dyn and T > 1:
        ld = np.empty(T - 1)
        g_in = np.empty((T - 1, d))
        g_out = np.empty((T - 1, d))
        predictive_loglik(dyn[0], dyn[1], dyn[2], dyn[3], dyn[4], dyn[5], dyn[6], dyn[7],
                          np.ascontiguousarray(X[1:]), np.ascontiguousarray(X[:-1]), np.zeros(d), ld, g_in, g_out)
        lp += _numpy_sum(ld)
        for t in range(T - 1):
            for j in range(d):
                g[t, j] += g_in[t, j]
        for t in range(T - 1):
            for j in range(d):
                g[t + 1, j] += g_out[t, j]
    if has_first:
        r = X[0] - f_mu
        pr = f_prec @ r
        lp += -0.5 * ((r @ f_prec) @ r) - 0.5 * f_logdet - 0.5 * d * LOG_2PI
        for j in range(d):
            g[0, j] -= pr[j]
    if has_smooth:
        ls = np.empty(1)
        gs = np.empty((1, d))
        gz = np.empty(z.shape)
        predictive_loglik(vis[0], vis[1], vis[2], vis[3], vis[4], vis[5], vis[6], vis[7], z,
                          np.ascontiguousarray(X[:1]), e, ls, gs, gz)
        lp += ls[0]
        for j in range(d):
            g[0, j] += gs[0, j]
    return lp


def segment_objective(
    X: np.ndarray,
    Y: np.ndarray,
    obs: GPPredictor,
    dynamics: GPPredictor | None = None,
    first: tuple[np.ndarray, np.ndarray] | None = None,
    smooth: tuple[GPPredictor, np.ndarray, np.ndarray] | None = None,
) -> tuple[float, np.ndarray]:
    """(log density, gradient in X) of one segment.

    first: (μ_π, Σ_π⁻¹, log|Σ_π|) of the entry distribution on x_1.
    smooth: (visual predictor, ẑ_prev (1×D), extra variance (D,)) — the smoothness term
    ln N(ẑ_prev; μ_Z(x_1), σ²_Z/w²(x_1) + e) on the first point.

    Evaluated term by term (the reference). :func:`maximise_segment` evaluates the same sum
    in one compiled call (:func:`_segment_compiled`) unless ``BAYES_TALK_FUSED=0``.
    """
    lp, g = numpy_gp(obs).loglik(Y, X)[:2]
    g = g.copy()
    if dynamics is not None and X.shape[0] > 1:
        l_d, g_in, g_out = numpy_gp(dynamics).loglik(X[1:], X[:-1])
        lp += l_d
        g[:-1] += g_in
        g[1:] += g_out
    if first is not None:
        mu, prec, logdet = first
        r = X[0] - mu
        lp += -0.5 * (r @ prec @ r) - 0.5 * logdet - 0.5 * len(mu) * LOG_2PI
        g[0] -= prec @ r
    if smooth is not None:
        vis, z, e = smooth
        l_s, g_s, _ = numpy_gp(vis).loglik(z, X[:1], e)
        lp += l_s
        g[0] += g_s[0]
    return float(lp), g


def compiled_segment_objective(
    Y: np.ndarray,
    obs: GPPredictor,
    dynamics: GPPredictor | None = None,
    first: tuple[np.ndarray, np.ndarray, float] | None = None,
    smooth: tuple[GPPredictor, np.ndarray, np.ndarray] | None = None,
) -> Callable[[np.ndarray], tuple[float, np.ndarray]]:
    """X ↦ :func:`segment_objective` (X, Y, obs, dynamics, first, smooth) as one compiled call
    per evaluation: the GPs' arrays are gathered once, so an L-BFGS iteration pays one Python
    call instead of three wrapped GP calls and a dozen small NumPy operations."""
    Y = np.ascontiguousarray(Y, dtype=np.float64)
    d = numpy_gp(obs).X.shape[1]
    o = _gp_args(obs, Y.shape[1])
    dy = _gp_args(dynamics, d)
    if first is not None:
        f_mu, f_prec, f_logdet = (np.ascontiguousarray(first[0], dtype=np.float64),
                                  np.ascontiguousarray(first[1], dtype=np.float64), float(first[2]))
    else:
        f_mu, f_prec, f_logdet = np.zeros(d), np.zeros((d, d)), 0.0
    if smooth is not None:
        vis = _gp_args(smooth[0], smooth[1].shape[-1])
        z = np.ascontiguousarray(np.reshape(smooth[1], (1, -1)), dtype=np.float64)
        e = np.ascontiguousarray(smooth[2], dtype=np.float64)
    else:
        vis, z, e = o, Y[:1], np.zeros(Y.shape[1])

    def f(X: np.ndarray) -> tuple[float, np.ndarray]:
        X = np.ascontiguousarray(X, dtype=np.float64)
        g = np.empty(X.shape)
        lp = _segment_compiled(X, Y, o, dy, dynamics is not None, f_mu, f_prec, f_logdet, first is not None,
                               vis, z, e, smooth is not None, g)
        return lp, g
    return f


def maximise_segment(
    X0: np.ndarray,
    Y: np.ndarray,
    obs: GPPredictor,
    dynamics: GPPredictor | None = None,
    first: tuple[np.ndarray, np.ndarray] | None = None,
    smooth: tuple[GPPredictor, np.ndarray, np.ndarray] | None = None,
    max_iter: int = SEGMENT_MAX_ITER,
) -> np.ndarray:
    """argmax of :func:`segment_objective` from X0 by scipy's L-BFGS-B.

    first: (μ_π, Σ_π) of the entry distribution (inverted here once).
    Never returns a point worse than X0.
    """
    from scipy.optimize import minimize

    shape = X0.shape
    first_p = None
    if first is not None:
        mu, cov = first
        first_p = (np.asarray(mu), np.linalg.inv(cov), float(np.linalg.slogdet(cov)[1]))

    # the compiled objective reads every GP on all d latent dimensions: a model with private
    # latent dimensions (a GP with ``in_dims``) takes the term-by-term reference
    private = any(getattr(p, "in_dims", None) is not None
                  for p in (obs, dynamics, None if smooth is None else smooth[0]))
    if settings.get("fused") and not private:
        objective = compiled_segment_objective(Y, obs, dynamics, first_p, smooth)
    else:
        def objective(X):
            return segment_objective(X, Y, obs, dynamics, first_p, smooth)

    def neg(flat: np.ndarray):
        f, g = objective(flat.reshape(shape))
        return -f, -g.ravel()

    x0 = np.asarray(X0, dtype=np.float64).ravel()
    res = minimize(neg, x0, jac=True, method="L-BFGS-B", options={"maxiter": max_iter, "gtol": 1e-5})
    if not np.all(np.isfinite(res.x)) or res.fun > neg(x0)[0]:
        return x0.reshape(shape).copy()
    return res.x.reshape(shape)
