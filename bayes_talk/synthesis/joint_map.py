"""The joint MAP of the whole-utterance synthesis density (the first step of every
posterior method of :mod:`bayes_talk.posterior.sampling`), in time and memory linear in the
utterance's length.

:func:`maximise_utterance` starts at deena2010's Algorithm 1 path (carried along the dynamics
means when it is off them: :func:`along_dynamics`, :data:`CARRY_RMS_Z`) and maximises
ln p(X | audio, states) of :class:`~bayes_talk.synthesis.joint.UtteranceDensity`: L-BFGS in
coordinates whitened by the Laplace precision at the start (posterior scales span orders
of magnitude), then a trust-region Newton method with the exact Hessian, which handles the
negative curvature the density has away from its modes. The Hessian is block-tridiagonal
(each term reads one frame or two neighbouring ones), and every solve, whitening and
trust-region subproblem goes through its banded Cholesky factor
(:mod:`bayes_talk.synthesis.banded`): O(T·d³) per iteration instead of the dense O((T·d)³).
Converged when max |∂ ln p/∂x| ≤ ``MAP_GTOL`` or when −∇² ln p is positive definite and the
Newton decrement ½ gᵀ(−∇² ln p)⁻¹ g is ≤ ``MAP_DTOL`` nats. :func:`restart_map` restarts it
from draws of its own Laplace approximation and keeps the best mode (the density is
multimodal).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from bayes_talk.gp.predictive_fused import Runs
from bayes_talk.synthesis.banded import BandedFactor, BlockTridiagonal, modified_cholesky
from bayes_talk.synthesis.joint import UtteranceDensity

#: trust-region Newton iterations of the joint MAP (one default for the library, the CLI and the protocols)
MAP_MAX_ITER = 100
#: L-BFGS iterations before them (cheap steps towards the mode's basin)
MAP_LBFGS_ITER = 100
#: the joint MAP has converged when max |∂ ln p / ∂x| is at most this
MAP_GTOL = 1e-3
#: ... or when the Newton decrement (nats still to gain) is at most this
MAP_DTOL = 1e-6
#: the MAP starts from Algorithm 1's path carried along the dynamics means when that path's
#: dynamics steps are further than this, in root mean square, from the dynamics GP's mean in
#: units of its predictive sd (:func:`dynamics_rms_z`): a path of the model's
#: dynamics has about 1; measured, Algorithm 1's paths have 0.07-0.6 on the default family
#: (40 development utterances) and 0.1-2.7 on a small phone-state model, 66-95 on a VLMM model
#: of 12 utterances
CARRY_RMS_Z = 10.0
#: the trust region's radius at the start and its largest, in the coordinates whitened at the
#: point the Newton stage starts from (scipy's ``trust-exact`` defaults)
TRUST_RADIUS = (1.0, 1000.0)
#: an utterance longer than ``MAP_WINDOW[0]`` frames is maximised window by window first:
#: windows of ``MAP_WINDOW[1]`` frames every ``MAP_WINDOW[2]`` frames (so neighbours overlap),
#: each the conditional density of its frames given the rest (:func:`_window_sweep`); one
#: trust region over a whole long path shrinks to its worst region's scale, and the Newton
#: iterations then grow with the length (measured: 30 at 9.5 s of speech, over 100 at 28 s)
MAP_WINDOW = (250, 100, 75)
#: window sweeps (each followed by the whole path's convergence test) before the Newton stage
#: over the whole path
MAP_SWEEPS = 2
#: at most this many rounds of restarts of the joint MAP from draws of its Laplace
#: approximation (the restarts per round are each method's ``map_restarts`` in
#: :data:`bayes_talk.posterior.methods.INFERENCE`): the joint density has several modes, and
#: the samplers run in coordinates whitened at the best mode found
MAP_RESTART_ROUNDS = 3


@dataclass
class MapResult:
    """The joint MAP path and how the optimiser got there."""

    latents: np.ndarray  # (T, d)
    log_density: float
    grad_norm: float  # max |∂ ln p/∂x| at the result
    n_iter: int
    converged: bool
    start_log_density: float  # at Algorithm 1's path (X0)
    hessian: BlockTridiagonal | None = None  # ∇² ln p at the result (block-tridiagonal)
    decrement: float = float("nan")  # ½ gᵀ(−∇² ln p)⁻¹ g at the result (nats)
    hessian_modified: int = 0  # eigenvalues of −∇² ln p that are ≤ 0 (not a strict maximum if > 0)
    carried: bool = False  # started from X0 carried along the dynamics means (CARRY_RMS_Z)
    start_rms_z: float = float("nan")  # dynamics_rms_z at X0 (NaN without dynamics steps)
    _factor: BandedFactor | None = field(default=None, repr=False, compare=False)

    def laplace_factor(self) -> BandedFactor:
        """The banded Cholesky factor of the Laplace precision −∇² ln p at the result
        (:func:`laplace_factor`; computed once)."""
        if self._factor is None:
            if self.hessian is None:
                raise ValueError("this MapResult has no Hessian")
            self._factor = laplace_factor(self.hessian)
        return self._factor


def as_block_hessian(H, d: int) -> BlockTridiagonal:
    """H as a :class:`~bayes_talk.synthesis.banded.BlockTridiagonal` of blocks d×d (a dense
    array's block-tridiagonal part; the class itself as it is)."""
    return H if isinstance(H, BlockTridiagonal) else BlockTridiagonal.from_dense(np.asarray(H), d)


def laplace_factor(H: BlockTridiagonal) -> BandedFactor:
    """The banded Cholesky factor of the precision P = −H of the Laplace approximation at a
    point whose log-density Hessian is H; where P is not positive definite (the MAP stopped
    short of a maximum), of P + τ·diag(|P_ii|) with the smallest τ that makes it so
    (:func:`~bayes_talk.synthesis.banded.modified_cholesky`, τ in ``shift``)."""
    return modified_cholesky(-H, "the Laplace precision -Hessian")


def dynamics_rms_z(dens: UtteranceDensity, X: np.ndarray) -> float:
    """Root mean square of the standardised dynamics residuals of a path,
    z_tm = (x_tm − μ_x,m(x_{t−1})) / σ_x,m(x_{t−1}) over every dynamics step of the density
    (inside blocks and across linked boundaries) and latent dimension, σ²_x,m = s(x_{t−1})/w_m²
    as in its dynamics terms: about 1 for a path of the model's own dynamics, below 1 near a
    mode; NaN without dynamics steps."""
    tm = dens.terms
    if not len(tm.d_dst):
        return float("nan")
    X = np.asarray(X, dtype=np.float64).reshape(dens.T, dens.d)
    mu, s = tm.dyn_gps.mean_var(tm.d_runs, X[tm.d_src])
    z2 = (X[tm.d_dst] - mu) ** 2 / (s[:, None] / tm.dyn_gps.w2[tm.d_runs.row_gp()])
    return float(np.sqrt(z2.mean()))


def along_dynamics(dens: UtteranceDensity, X: np.ndarray) -> np.ndarray:
    """X with every dynamics step of the density replaced by the dynamics GP's mean, in time
    order: x_t ← μ_x(x_{t−1}) for each step x_{t−1} → x_t (inside blocks and across linked
    boundaries), every other frame (block starts, frames of models without dynamics) kept.
    This maximises each dynamics factor N(x_t; μ_x(x_{t−1}), σ²_x(x_{t−1})) given the frame
    before it (its σ² does not depend on x_t)."""
    X = np.array(X, dtype=np.float64).reshape(dens.T, dens.d)
    tm = dens.terms
    if not len(tm.d_dst):
        return X
    row_gp = tm.d_runs.row_gp()
    for j in np.argsort(tm.d_dst, kind="stable"):
        t = tm.d_dst[j]
        mu, _ = tm.dyn_gps.mean_var(Runs(row_gp[j:j + 1], np.zeros(1), np.ones(1)), X[t - 1:t])
        X[t] = mu[0]
    return X


def maximise_utterance(dens: UtteranceDensity, X0: np.ndarray, max_iter: int = MAP_MAX_ITER,
                       gtol: float = MAP_GTOL, dtol: float = MAP_DTOL,
                       lbfgs_iter: int = MAP_LBFGS_ITER,
                       progress: Callable[[str, int], None] | None = None) -> MapResult:
    """The joint MAP from X0 (Algorithm 1's path), in two stages.

    0. The start. When X0 is off the model's dynamics — its standardised dynamics residuals
       have a root mean square above ``CARRY_RMS_Z`` (10 predictive sds; a path of the
       dynamics has about 1) — and X0 carried along the dynamics means
       (:func:`along_dynamics`: each dynamics step x_t ← μ_x(x_{t−1}),
       block starts kept) has the higher ln p, the MAP starts there. With the dynamics noise
       at 10⁻⁶ such a path is 10⁵–10⁶ nats below the modes (the VLMM family's Algorithm 1
       paths on a small corpus: 66–95 sds), and from it the MAP used to stop at its iteration
       cap; carried, it starts within a few hundred nats of a mode. A path on the dynamics
       (the default family's: 0.07–0.6 sds) is left as it is, so which of the
       nearby modes the MAP finds is unchanged there (docs/uncertainty.md).

    1. Up to ``lbfgs_iter`` L-BFGS iterations (scipy) in the coordinates whitened by the
       Laplace precision at the start x₀, x = x₀ + L z with L Lᵀ = P⁻¹, P = −∇² ln p (L = R⁻ᵀ
       from P's banded Cholesky factor R, or that of P + τ·diag(|P_ii|) where P is not positive
       definite: :func:`laplace_factor`): cheap steps that bring the badly scaled latent
       directions (posterior sds spanning orders of magnitude) to the mode's basin.
    2. A trust-region Newton method with the exact Hessian (:func:`_trust_region_stage`: the
       subproblem solved nearly exactly, Moré & Sorensen 1983; Nocedal & Wright 2006 §4.3, as
       scipy's ``trust-exact`` does), its region an ellipsoid of the local posterior's shape:
       ‖s‖_M ≤ Δ in the metric M of the Laplace precision at the stage-1 point (the same as
       a ball in the coordinates whitened there). Each subproblem (P + λM) s = g is a banded
       Cholesky solve. Unlike a line search along the Newton direction of a modified Hessian,
       it follows negative curvature out of saddle regions (on held-out utterances the joint
       density has them, e.g. in 5-frame silence blocks): where P is indefinite the step
       is the region's boundary solution with λ above P's most negative eigenvalue in M's
       metric, and the radius shrinks until the model agrees with the density. Near the mode
       it takes full Newton steps, with quadratic convergence. At most ``max_iter`` iterations.

    Converged when max |∂ ln p/∂x| ≤ ``gtol``, or when P is positive definite and the Newton
    decrement ½ gᵀP⁻¹g (the log density a Newton step would still gain) is at most ``dtol``
    nats: with dynamics noise variance 10⁻⁶ the curvature reaches 10⁸ and a gradient of 10² is
    then 10⁻⁶ away from the mode, so the gradient alone is not scale-free. The Hessian, the
    gradient norm and the decrement are those at the returned point (the Hessian is for
    Laplace). Time and memory are linear in the number of frames.

    ``progress(stage, iterations)``: called after every iteration of each stage (``"lbfgs"``,
    ``"newton"``) with the iterations done so far."""
    x0 = np.asarray(X0, dtype=np.float64).reshape(-1).copy()
    f0, g0 = dens(x0)
    n_iter = 0
    x, f, g = x0, f0, g0.reshape(-1)
    carried, rms_z = False, dynamics_rms_z(dens, x0)
    if rms_z > CARRY_RMS_Z:
        xr = along_dynamics(dens, x0).reshape(-1)
        fr, gr = dens(xr)
        if np.isfinite(fr) and fr > f0:
            x, f, g, carried = xr, fr, gr.reshape(-1), True
    if dens.T > MAP_WINDOW[0]:
        for sweep in range(MAP_SWEEPS):
            x, k = _window_sweep(dens, x, max_iter, gtol, dtol, lbfgs_iter, sweep, progress)
            n_iter += k
            f, g = dens(x)
            g = g.reshape(-1)
            H = dens.hessian(x)
            state = _newton_state(H, g, gtol, dtol)
            if state["converged"]:
                break
    else:
        if lbfgs_iter > 0:
            x, f, g, n_iter = _lbfgs_stage(dens, x, f, g, lbfgs_iter, gtol, progress)
        H = dens.hessian(x)
        state = _newton_state(H, g, gtol, dtol)
    if not state["converged"] and max_iter > 0:
        x, f, g, H, state, k = _trust_region_stage(dens, x, f, g, H, state, max_iter, gtol, dtol, progress)
        n_iter += k
    return MapResult(x.reshape(dens.T, dens.d), float(f), state["grad_norm"], n_iter, state["converged"],
                     float(f0), H, state["decrement"], state["n_mod"], carried, rms_z, _factor=state["factor"])


class _Conditional:
    """The conditional log density of frames ``inner`` of ``dens`` (a
    :meth:`~bayes_talk.synthesis.joint.UtteranceDensity.window`) given its other frames ``X``
    (held fixed): value, gradient and block-tridiagonal Hessian in the window's frames."""

    def __init__(self, dens: UtteranceDensity, X: np.ndarray, inner: slice):
        self.dens, self.X, self.inner = dens, np.array(X, dtype=np.float64), inner
        self.T, self.d = inner.stop - inner.start, dens.d

    def _full(self, x: np.ndarray) -> np.ndarray:
        X = self.X.copy()
        X[self.inner] = np.asarray(x, dtype=np.float64).reshape(self.T, self.d)
        return X

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        f, G = self.dens(self._full(x))
        return f, G[self.inner]

    def hessian(self, x: np.ndarray) -> BlockTridiagonal:
        H = self.dens.hessian(self._full(x))
        i = self.inner
        return BlockTridiagonal(H.diag[i], H.upper[i.start:i.stop - 1])


def _window_sweep(dens: UtteranceDensity, x: np.ndarray, max_iter: int, gtol: float, dtol: float,
                  lbfgs_iter: int, sweep: int, progress=None) -> tuple[np.ndarray, int]:
    """One left-to-right sweep of block coordinate ascent over windows of ``MAP_WINDOW[1]``
    frames every ``MAP_WINDOW[2]`` (odd sweeps start half a stride later, so the seams move):
    each window's frames maximised given the others (the two stages of
    :func:`maximise_utterance` on the conditional density of :class:`_Conditional`; its terms
    only, so a sweep costs time linear in the length). Each window's result is kept only when
    it raises ln p (a maximisation never lowers it). Returns the path and the iterations."""
    _, width, stride = MAP_WINDOW
    T, d = dens.T, dens.d
    X = x.reshape(T, d).copy()
    starts = list(range(0, max(T - width, 0) + 1, stride))
    if sweep % 2:
        starts = [0] + [s + stride // 2 for s in starts if s + stride // 2 < T - width // 2]
    if starts[-1] + width < T:
        starts.append(T - width)
    n_iter = 0
    for lo in starts:
        hi = min(lo + width, T)
        sub, inner = dens.window(lo, hi)
        a = lo - inner.start
        cond = _Conditional(sub, X[a:a + sub.T], inner)
        xw = X[lo:hi].reshape(-1)
        f0, g0 = cond(xw)
        xw, f, g, k = _lbfgs_stage(cond, xw, f0, g0.reshape(-1), lbfgs_iter, gtol) if lbfgs_iter > 0 else \
            (xw, f0, g0.reshape(-1), 0)
        H = cond.hessian(xw)
        state = _newton_state(H, g, gtol, dtol)
        if not state["converged"] and max_iter > 0:
            xw, f, g, H, state, kn = _trust_region_stage(cond, xw, f, g, H, state, max_iter, gtol, dtol)
            k += kn
        if f >= f0:
            X[lo:hi] = xw.reshape(hi - lo, d)
        n_iter += k
        if progress is not None:
            progress("window", hi)
    return X.reshape(-1), n_iter


def _lbfgs_stage(dens: UtteranceDensity, x0: np.ndarray, f0: float, g0: np.ndarray, max_iter: int,
                 gtol: float, progress=None) -> tuple[np.ndarray, float, np.ndarray, int]:
    """L-BFGS (scipy) on ln p in coordinates whitened at x0 (x = x0 + L z, L = R⁻ᵀ of the
    banded factor of the Laplace precision there); the best point seen and its gradient, and
    the iteration count."""
    from scipy.optimize import minimize

    fac = laplace_factor(dens.hessian(x0))
    best = {"f": f0, "x": x0, "g": g0, "iter": 0}

    def neg(z: np.ndarray) -> tuple[float, np.ndarray]:
        x = x0 + fac.scale_matvec(z)
        f, g = dens(x)
        g = g.reshape(-1)
        if np.isfinite(f) and f > best["f"]:
            best.update(f=f, x=x, g=g)
        return -f, -fac.scale_rmatvec(g)

    def done(z) -> None:
        best["iter"] += 1
        if progress is not None:
            progress("lbfgs", best["iter"])
        if np.max(np.abs(best["g"])) <= gtol:
            raise StopIteration

    res = minimize(neg, np.zeros_like(x0), jac=True, method="L-BFGS-B", callback=done,
                   options={"maxiter": max_iter, "gtol": 1e-12, "ftol": 1e-15, "maxcor": 30})
    return best["x"], float(best["f"]), best["g"], int(res.nit)


def _trust_region_stage(dens: UtteranceDensity, x: np.ndarray, f: float, g: np.ndarray, H: BlockTridiagonal,
                        state: dict, max_iter: int, gtol: float, dtol: float, progress=None):
    """Stage 2 of :func:`maximise_utterance`: at most ``max_iter`` trust-region Newton
    iterations from x in the metric M of the Laplace precision at x (scipy ``trust-exact``'s
    radius rules: shrink ×¼ when the step's gain is under ¼ of the model's, double it up to
    ``TRUST_RADIUS[1]`` when over ¾ on the boundary, accept when over 0.15). Returns the
    accepted point, its value, gradient, Hessian, convergence state and the iterations."""
    M = state["factor"]
    radius, max_radius = TRUST_RADIUS
    n = 0
    for n in range(1, max_iter + 1):
        P = -H
        s, on_boundary = _trust_region_step(P, M, g, radius)
        predicted = float(g @ s - 0.5 * s @ P.matvec(s))
        x_new = x + s
        f_new, g_new = dens(x_new)
        rho = (f_new - f) / predicted if np.isfinite(f_new) and predicted > 0 else -np.inf
        if rho < 0.25:
            radius *= 0.25
        elif rho > 0.75 and on_boundary:
            radius = min(2.0 * radius, max_radius)
        if rho > 0.15:
            x, f, g = x_new, float(f_new), g_new.reshape(-1)
            H = dens.hessian(x)
            state = _newton_state(H, g, gtol, dtol)
        if progress is not None:
            progress("newton", n)
        if state["converged"] or radius < 1e-12:
            break
    return x, f, g, H, state, n


def _trust_region_step(P: BlockTridiagonal, M: BandedFactor, g: np.ndarray, radius: float,
                       tol: float = 0.1, max_iter: int = 60) -> tuple[np.ndarray, bool]:
    """The step s maximising the model gᵀs − ½ sᵀPs over ‖s‖_M ≤ ``radius`` (‖s‖_M = ‖Rᵀs‖,
    M = R Rᵀ), nearly exactly (Moré & Sorensen 1983): s(λ) = (P + λM)⁻¹ g with the λ ≥ 0 that
    makes P + λM positive definite and ‖s(λ)‖_M within ``tol``·radius of the radius (or λ = 0
    and s inside). λ by Newton's method on 1/radius − 1/‖s(λ)‖_M, safeguarded by bisection
    between a λ known too small (P + λM indefinite, or ‖s‖_M too long) and one known too large;
    each trial one banded Cholesky factorisation of P + λM. Returns (s, on the boundary)."""
    Mmat = M.matrix

    def norm(s: np.ndarray) -> float:
        return float(np.linalg.norm(M.unscale_matvec(s)))

    lo, hi, best = 0.0, None, None
    lam, s, ns = 0.0, np.zeros_like(g), 0.0
    g_white = float(np.linalg.norm(M.scale_rmatvec(g)))
    for _ in range(max_iter):
        try:
            C = (P + Mmat.scaled(lam)).cholesky() if lam > 0 else P.cholesky()
        except np.linalg.LinAlgError:
            lo = max(lo, lam)
            lam = 0.5 * (lo + hi) if hi is not None else max(4.0 * lam, g_white / radius, 1e-12)
            continue
        s = C.solve(g)
        ns = norm(s)
        if lam == 0.0 and ns <= radius:
            return s, False
        if abs(ns - radius) <= tol * radius:
            return s, True
        if ns > radius:
            lo = lam
        else:
            hi, best = lam, s
        Ms = Mmat.matvec(s)
        q2 = float(Ms @ C.solve(Ms))
        new = lam + (ns * ns / q2) * (ns - radius) / radius if q2 > 0 else np.inf
        if hi is not None and not (lo < new < hi):
            new = 0.5 * (lo + hi)
        elif hi is None and not new > lo:
            new = max(2.0 * lo, 1e-12)
        if hi is not None and hi - lo <= 1e-12 * hi:
            break                       # the hard case: no λ reaches the boundary; the inner solution at hi
        lam = new
    if best is not None:
        return best, False
    return (s * (radius / ns), True) if ns > 0 else (s, False)     # no positive definite λ met: no step


def _newton_state(H: BlockTridiagonal, g: np.ndarray, gtol: float, dtol: float) -> dict:
    """The convergence test at a point with Hessian H and gradient g of ln p: max |g|, the
    Newton decrement ½ gᵀP⁻¹g (P = −H; where P is not positive definite, with P's modified
    Cholesky factor), the number of eigenvalues of P that are ≤ 0, converged, and the factor."""
    P = -H
    try:
        fac, n_mod = P.cholesky(), 0
    except np.linalg.LinAlgError:
        fac, n_mod = laplace_factor(H), max(P.inertia(), 1)
    decrement = 0.5 * float(g @ fac.solve(g))
    gnorm = float(np.max(np.abs(g)))
    return {"grad_norm": gnorm, "decrement": decrement, "n_mod": n_mod, "factor": fac,
            "converged": gnorm <= gtol or (n_mod == 0 and decrement <= dtol)}


def restart_map(dens: UtteranceDensity, mp: MapResult, n_restarts: int, seed: int = 0,
                rounds: int = MAP_RESTART_ROUNDS, max_iter: int = MAP_MAX_ITER) -> tuple[MapResult, list[MapResult]]:
    """The highest mode found by restarting :func:`maximise_utterance` from ``n_restarts``
    draws of the Laplace approximation N(x_MAP, (−∇² ln p)⁻¹) at the current mode, keeping
    the best converged result, and again from the new best, for at most ``rounds`` rounds
    or until a round finds nothing higher by more than ``MAP_DTOL`` nats. The draws lie in
    the Laplace approximation's typical set, where a unimodal posterior would bring every
    restart back to the same mode. Returns the best result and every restart's end (its
    ``log_density``, ``latents``, ``converged``; :func:`mode_jumps` turns the converged
    ones into the NUTS sampler's mode-jumping moves). Seeded: same seed, same result."""
    rng = np.random.default_rng([seed, 0x6D6170])
    found: list[MapResult] = []
    for _ in range(rounds):
        fac = mp.laplace_factor()
        x = mp.latents.reshape(-1)
        best = mp
        for _ in range(n_restarts):
            x0 = (x + fac.scale_matvec(rng.standard_normal(x.size))).reshape(dens.T, dens.d)
            if not np.isfinite(dens(x0)[0]):
                continue
            r = maximise_utterance(dens, x0, max_iter=max_iter)
            found.append(r)
            if r.converged and r.log_density > best.log_density:
                best = r
        if best.log_density <= mp.log_density + MAP_DTOL:
            break
        best.start_log_density = mp.start_log_density
        mp = best
    return mp, found
