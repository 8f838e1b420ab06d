"""The joint MAP of the whole-utterance synthesis density (the first step of every
posterior method of :mod:`bayes_talk.posterior.sampling`).

:func:`maximise_utterance` starts at deena2010's Algorithm 1 path (carried along the dynamics
means when it is off them: :func:`along_dynamics`, :data:`CARRY_RMS_Z`) and maximises
ln p(X | audio, states) of :class:`~bayes_talk.synthesis.joint.UtteranceDensity`: L-BFGS in
coordinates whitened by the Laplace precision at the start (posterior scales span orders
of magnitude), then scipy's ``trust-exact`` with the exact Hessian, which handles the
negative curvature the density has away from its modes. Converged when max |∂ ln p/∂x| ≤
``MAP_GTOL`` or when −∇² ln p is positive definite and the Newton decrement
½ gᵀ(−∇² ln p)⁻¹ g is ≤ ``MAP_DTOL`` nats. :func:`restart_map` restarts it from draws of
its own Laplace approximation and keeps the best mode (the density is multimodal).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_talk.gp.predictive_fused import Runs
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
    hessian: np.ndarray | None = None  # ∇² ln p at the result
    decrement: float = float("nan")  # ½ gᵀ(−∇² ln p)⁻¹ g at the result (nats)
    hessian_modified: int = 0  # eigenvalues of −∇² ln p floored (not a strict maximum if > 0)
    carried: bool = False  # started from X0 carried along the dynamics means (CARRY_RMS_Z)
    start_rms_z: float = float("nan")  # dynamics_rms_z at X0 (NaN without dynamics steps)


def floored_precision(H: np.ndarray, floor: float = 1e-8) -> tuple[np.ndarray, np.ndarray, int]:
    """Eigen-decomposition of P = −H with eigenvalues floored at floor·max|λ| (and |λ| used
    for negative ones): (eigenvalues, eigenvectors, number modified)."""
    P = -0.5 * (H + H.T)
    lam, U = np.linalg.eigh(P)
    lo = floor * max(1.0, float(np.max(np.abs(lam))))
    n_mod = int(np.sum(lam < lo))
    return np.maximum(np.abs(lam), lo), U, n_mod


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
                       lbfgs_iter: int = MAP_LBFGS_ITER) -> MapResult:
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
       Laplace precision at the start x₀, x = x₀ + L z with L Lᵀ = P⁻¹, P = −∇² ln p (eigenvalues
       floored, negative ones by their modulus): cheap steps that bring the badly scaled
       latent directions (posterior sds spanning orders of magnitude) to the mode's basin.
    2. A trust-region Newton method with the exact Hessian (scipy's ``trust-exact``: the
       trust-region subproblem solved nearly exactly, Moré & Sorensen 1983; Nocedal & Wright
       2006 §4.3), again in coordinates whitened at the stage-1 point, so the trust region is
       an ellipsoid of the local posterior's shape. Unlike a line search along the Newton
       direction of a floored Hessian, it follows negative curvature out of saddle regions
       (on held-out utterances the joint density has them, e.g. in 5-frame silence blocks),
       and it takes full Newton steps, with quadratic convergence, near the mode. At most
       ``max_iter`` iterations.

    Converged when max |∂ ln p/∂x| ≤ ``gtol``, or when P is positive definite and the Newton
    decrement ½ gᵀP⁻¹g (the log density a Newton step would still gain) is at most ``dtol``
    nats: with dynamics noise variance 10⁻⁶ the curvature reaches 10⁸ and a gradient of 10² is
    then 10⁻⁶ away from the mode, so the gradient alone is not scale-free. The Hessian, the
    gradient norm and the decrement are those at the returned point (the Hessian is for
    Laplace)."""
    from scipy.optimize import minimize

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
    if lbfgs_iter > 0:
        x, f, g, n_iter = _lbfgs_stage(dens, x, f, g, lbfgs_iter, gtol)
    H = dens.hessian(x)
    state = _newton_state(H, g, gtol, dtol)
    if not state["converged"] and max_iter > 0:
        lam, U, _ = floored_precision(H)
        L = U / np.sqrt(lam)
        xs = x.copy()
        cache: dict = {}

        def point(z: np.ndarray) -> dict:
            key = z.tobytes()
            if key not in cache:
                cache.clear()
                xz = xs + L @ z
                fz, gz = dens(xz)
                cache[key] = {"x": xz, "f": fz, "g": gz.reshape(-1)}
            return cache[key]

        def neg(z: np.ndarray) -> tuple[float, np.ndarray]:
            p = point(z)
            if not np.isfinite(p["f"]):
                return np.inf, np.zeros_like(z)
            return -p["f"], -(L.T @ p["g"])

        def neg_hess(z: np.ndarray) -> np.ndarray:
            p = point(z)
            if "H" not in p:
                p["H"] = dens.hessian(p["x"])
            return -(L.T @ p["H"] @ L)

        def done(intermediate_result) -> None:
            p = point(np.asarray(intermediate_result.x))
            if "H" not in p:
                p["H"] = dens.hessian(p["x"])
            if _newton_state(p["H"], p["g"], gtol, dtol)["converged"]:
                raise StopIteration

        res = minimize(neg, np.zeros_like(x), jac=True, hess=neg_hess, method="trust-exact", callback=done,
                       options={"maxiter": max_iter, "gtol": 1e-300})
        p = point(np.asarray(res.x))
        if np.isfinite(p["f"]) and p["f"] >= f:
            x, f, g = p["x"], float(p["f"]), p["g"]
            H = p["H"] if "H" in p else dens.hessian(x)
            state = _newton_state(H, g, gtol, dtol)
        n_iter += int(res.nit)
    return MapResult(x.reshape(dens.T, dens.d), float(f), state["grad_norm"], n_iter, state["converged"],
                     float(f0), H, state["decrement"], state["n_mod"], carried, rms_z)


def _lbfgs_stage(dens: UtteranceDensity, x0: np.ndarray, f0: float, g0: np.ndarray, max_iter: int,
                 gtol: float) -> tuple[np.ndarray, float, np.ndarray, int]:
    """L-BFGS (scipy) on ln p in coordinates whitened at x0; the best point seen and its
    gradient, and the iteration count."""
    from scipy.optimize import minimize

    lam, U, _ = floored_precision(dens.hessian(x0))
    L = U / np.sqrt(lam)
    best = {"f": f0, "x": x0, "g": g0}

    def neg(z: np.ndarray) -> tuple[float, np.ndarray]:
        x = x0 + L @ z
        f, g = dens(x)
        g = g.reshape(-1)
        if np.isfinite(f) and f > best["f"]:
            best.update(f=f, x=x, g=g)
        return -f, -(L.T @ g)

    def done(z) -> None:
        if np.max(np.abs(best["g"])) <= gtol:
            raise StopIteration

    res = minimize(neg, np.zeros_like(x0), jac=True, method="L-BFGS-B", callback=done,
                   options={"maxiter": max_iter, "gtol": 1e-12, "ftol": 1e-15, "maxcor": 30})
    return best["x"], float(best["f"]), best["g"], int(res.nit)


def _newton_state(H: np.ndarray, g: np.ndarray, gtol: float, dtol: float) -> dict:
    """The convergence test at a point with Hessian H and gradient g of ln p: max |g|, the
    Newton decrement ½ gᵀP⁻¹g (P = −H, eigenvalues floored), eigenvalues floored, converged."""
    lam, U, n_mod = floored_precision(H)
    decrement = 0.5 * float(np.sum((U.T @ g) ** 2 / lam))
    gnorm = float(np.max(np.abs(g)))
    return {"grad_norm": gnorm, "decrement": decrement, "n_mod": n_mod,
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
        lam, U, _ = floored_precision(mp.hessian)
        L = U / np.sqrt(lam)
        x = mp.latents.reshape(-1)
        best = mp
        for _ in range(n_restarts):
            x0 = (x + L @ rng.standard_normal(x.size)).reshape(dens.T, dens.d)
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
