"""Fitting the face's observation term on held-out training utterances (docs/uncertainty.md).

The term (N1) of :mod:`bayes_talk.synthesis.face_noise` — per AAM parameter d a mean
shrinkage a_d, a GP-variance scale β_d, a Student-t scale τ_d with degrees of freedom ν_d
and a log-offset δ_{g,d} per phone class — is fitted by maximising the **held-out log
score** of the predictive (N2) on utterances the state models did not see:

    max  Σ_{held-out utterances} Σ_t Σ_d ln p(y_td)  −  Σ_{g,d} δ²_{g,d} / (2 s²)          (F1)

with p of (N2) evaluated on every ``frame_step``-th frame, each synthesis's mixture of draws
moment-matched to one Gaussian per entry (mean m̄, the spread of the component means
s²_μ beside the mean GP variance v̄: the component of (N2) becomes
N(c + a(m̄ − c), β v̄ + a² s²_μ + τ² λ); ``n_draws`` > 1 keeps that many of the draws
instead, evenly spaced over the chains), the Student-t's scale mixture by ``n_scales``
stratified quantiles of its mixing distribution. The Gaussian penalty (a prior
N(0, s²) on the class offsets, s = ``CLASS_PRIOR_SD``) shrinks the scale of a phone class
towards the parameter's own scale where few frames support it. ν_d is profiled over
:data:`NU_GRID` (the objective is a sum over d, so each parameter takes its best ν); for
each ν the other parameters are fitted jointly by L-BFGS (PyTorch autograd, float64).

**Where the held-out utterances come from.** A seeded fraction (20 % by default) of the
training utterances is held out; a model of the same configuration is trained on the rest
and synthesises them (:func:`bayes_talk.calibration.bands.calibrated_fit`'s schemes:
"refit" ships a second model trained on all utterances with the fitted term; "holdout" ships
the model that synthesised them; "cv" fits the term on out-of-fold syntheses of every
training utterance). The utterance is the exchangeable unit: whole utterances are held
out, never frames, because frames of one utterance share its latent path.

The plain constant band's variance v_d (the control ``evaluate`` scores beside the model's
bands) is the held-out mean squared error of the fitted mean, on the same utterances.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import stats

from bayes_talk.synthesis.face_noise import GAUSSIAN_NU, N_CLASSES, FaceNoise, frame_classes
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["ABLATIONS", "CLASS_PRIOR_SD", "NU_GRID", "fit_face_noise", "held_out_fitter"]

log = logging.getLogger(__name__)

#: the degrees of freedom ν_d is profiled over (the last: Gaussian)
NU_GRID = (2.5, 4.0, 7.0, 15.0, GAUSSIAN_NU)
#: prior s.d. of the class log-offsets δ_{g,d} of (F1)
CLASS_PRIOR_SD = 0.5
#: the ablations ``evaluate`` scores beside the model (fitted the same way, one term fixed):
#: the mean function c_t alone (a = β = 0), and the latent path's mean unshrunk (a = 1)
ABLATIONS = {"context-only": {"shrink": 0.0, "gp_scale": 0.0}, "unshrunk": {"shrink": 1.0}}


def _stack(results: Sequence[SynthesisResult], truths: Sequence[np.ndarray], labels: Sequence[Sequence[str]],
           n_draws: int, frame_step: int) -> dict[str, np.ndarray]:
    """The held-out entries of (F1): c (N, D), μ and v (N, K', D), the spread s²_μ (N, D)
    (zero unless the draws are moment-matched, ``n_draws`` = 1), y (N, D), g (N,)."""
    cs, mus, vs, ys, gs, sp = [], [], [], [], [], []
    for r, y, lab in zip(results, truths, labels, strict=True):
        y = np.asarray(y, dtype=np.float64)
        if y.shape != (r.n_frames, r.n_dims):
            raise ValueError(f"face noise fit: truth of shape {y.shape} for a synthesis of shape "
                             f"{(r.n_frames, r.n_dims)}")
        if len(lab) != r.n_frames:
            raise ValueError(f"face noise fit: {len(lab)} labels for a synthesis of {r.n_frames} frames")
        K = r.n_draws
        ts = np.arange(0, r.n_frames, frame_step)
        mu_all = r.draw_mean.reshape(K, r.n_frames, r.n_dims)[:, ts]
        v_all = r.draw_var.reshape(K, r.n_frames, r.n_dims)[:, ts]
        if n_draws == 1:   # moment-matched: the spread of the draws kept apart (it scales with a²)
            mu, v = mu_all.mean(0, keepdims=True), v_all.mean(0, keepdims=True)
            sp.append(mu_all.var(0))
        else:
            ks = np.unique(np.linspace(0, K - 1, min(n_draws, K)).round().astype(int))
            mu, v = mu_all[ks], v_all[ks]
            sp.append(np.zeros((len(ts), r.n_dims)))
        c = np.zeros((len(ts), r.n_dims)) if r.mean_function is None else r.mean_function[ts]
        if len(mu) < n_draws:   # the same number of components for every utterance
            rep = -(-n_draws // len(mu))
            mu, v = np.repeat(mu, rep, 0)[:n_draws], np.repeat(v, rep, 0)[:n_draws]
        cs.append(c)
        mus.append(mu.transpose(1, 0, 2))
        vs.append(v.transpose(1, 0, 2))
        ys.append(y[ts])
        gs.append(frame_classes(lab)[ts])
    return {"c": np.concatenate(cs), "mu": np.concatenate(mus), "v": np.concatenate(vs),
            "spread": np.concatenate(sp), "y": np.concatenate(ys), "g": np.concatenate(gs)}


def _fit_at(data: dict[str, np.ndarray], nu: float, n_scales: int, init: dict[str, np.ndarray],
            fixed: dict[str, float], prior_sd: float, max_iter: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(parameters, per-d penalised log score) of (F1) at one ν for every d."""
    import torch

    t = {k: torch.as_tensor(v) for k, v in data.items() if k != "g"}
    g = torch.as_tensor(data["g"])
    N, K, D = data["mu"].shape
    lam = (np.ones(1) if nu >= GAUSSIAN_NU else
           stats.invgamma.ppf((np.arange(n_scales) + 0.5) / n_scales, nu / 2.0, scale=nu / 2.0))
    lam_t = torch.as_tensor(lam)[None, None, :, None]                       # (1, 1, J, 1)
    log_mix = math.log(K * len(lam))
    dev = (t["mu"] - t["c"][:, None, :])[:, :, None, :]                     # (N, K, 1, D)
    resid0 = (t["y"] - t["c"])[:, None, None, :]                            # (N, 1, 1, D)
    v = t["v"][:, :, None, :]
    spread = t["spread"][:, None, None, :]
    p = {"shrink": torch.tensor(init["shrink"], requires_grad="shrink" not in fixed),
         "log_gp_scale": torch.tensor(np.log(np.maximum(init["gp_scale"], 1e-8)),
                                      requires_grad="gp_scale" not in fixed),
         "log_scale": torch.tensor(np.log(init["scale"]), requires_grad=True),
         "class_offset": torch.zeros((N_CLASSES, D), dtype=torch.float64, requires_grad=True)}
    if "shrink" in fixed:
        p["shrink"] = torch.as_tensor(np.broadcast_to(np.asarray(fixed["shrink"], np.float64), (D,)).copy())
    gp_fixed = fixed.get("gp_scale")
    free = [q for q in p.values() if q.requires_grad]

    def per_dim() -> torch.Tensor:
        gp = torch.zeros(D, dtype=torch.float64) if gp_fixed == 0.0 else torch.exp(p["log_gp_scale"])
        tau2 = torch.exp(2 * (p["log_scale"][None, :] + p["class_offset"][g]))[:, None, None, :]   # (N,1,1,D)
        var = gp * v + p["shrink"] ** 2 * spread + tau2 * lam_t                             # (N,K,J,D)
        r = resid0 - p["shrink"] * dev
        lp = -0.5 * (math.log(2 * math.pi) + torch.log(var) + r * r / var)
        ll = torch.logsumexp(lp.reshape(N, -1, D), dim=1) - log_mix                          # (N, D)
        return ll.sum(0) - 0.5 * (p["class_offset"] ** 2).sum(0) / prior_sd ** 2

    opt = torch.optim.LBFGS(free, lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-7, tolerance_change=1e-10)

    def closure():
        opt.zero_grad()
        loss = -per_dim().sum() / N
        loss.backward()
        return loss
    opt.step(closure)
    with torch.no_grad():
        score = per_dim().numpy()
        gp = np.zeros(D) if gp_fixed == 0.0 else np.exp(p["log_gp_scale"].numpy())
        out = {"shrink": p["shrink"].detach().numpy().copy(), "gp_scale": gp,
               "scale": np.exp(p["log_scale"].detach().numpy()), "class_offset": p["class_offset"].detach().numpy().copy()}
    return out, score


def fit_face_noise(results: Sequence[SynthesisResult], truths: Sequence[np.ndarray],
                   labels: Sequence[Sequence[str]], *, names: Sequence[str] | None = None, n_draws: int = 1,
                   frame_step: int = 2, n_scales: int = 16, nu_grid: Sequence[float] = NU_GRID,
                   prior_sd: float = CLASS_PRIOR_SD, fixed: dict[str, Any] | None = None,
                   mean: str = "least-squares", ablations: bool = False, max_iter: int = 100) -> FaceNoise:
    """The observation term (N1) fitted by (F1) to the syntheses ``results`` (without the
    term: any inference method's) of held-out utterances with AAM parameters ``truths`` and
    frame labels ``labels``. ``mean``: how the shrinkage a_d is fitted: "least-squares" (the
    default: a_d = clip(Σ (m̄ − c)(y − c) / Σ (m̄ − c)², 0, 1) over the held-out frames, the
    factor that minimises the held-out squared error of the trajectory, the score the mean is
    judged by; then the rest by (F1)) or "log-score" (a_d in (F1) with the rest). ``fixed``:
    parameters held at a value ("shrink", "gp_scale"). ``ablations``: also fit
    :data:`ABLATIONS` (recorded in ``info["ablations"]``)."""
    from bayes_talk.gp.threads import torch_threads

    if not results:
        raise ValueError("face noise fit: no held-out syntheses")
    fixed = dict(fixed or {})
    data = _stack(results, truths, labels, n_draws, frame_step)
    N, K, D = data["mu"].shape
    # a start: the least-squares shrinkage (on every held-out frame), the GP's own variance,
    # the rest to the scale
    num, den = np.zeros(D), np.zeros(D)
    for r, y in zip(results, truths, strict=True):
        c = 0.0 if r.mean_function is None else r.mean_function
        num += ((r.mean - c) * (np.asarray(y) - c)).sum(0)
        den += ((r.mean - c) ** 2).sum(0)
    ls = np.clip(num / np.maximum(den, 1e-12), 0.0, 1.0)
    dev = data["mu"].mean(1) - data["c"]
    resid = data["y"] - data["c"]
    if mean not in ("least-squares", "log-score"):
        raise ValueError(f"face noise fit: mean must be 'least-squares' or 'log-score', found {mean!r}")
    if mean == "least-squares" and "shrink" not in fixed:
        fixed["shrink"] = ls
    shrink0 = np.broadcast_to(np.asarray(fixed["shrink"], np.float64), (D,)).copy() if "shrink" in fixed else ls
    mse = ((resid - shrink0 * dev) ** 2).mean(0)
    init = {"shrink": shrink0, "gp_scale": np.ones(D),
            "scale": np.sqrt(np.maximum(mse - data["v"].mean((0, 1)) - shrink0 ** 2 * data["spread"].mean(0),
                                        0.1 * mse) + 1e-12)}
    best, best_score, best_nu = None, np.full(D, -np.inf), np.zeros(D)
    with torch_threads(1):
        for nu in nu_grid:
            params, score = _fit_at(data, float(nu), n_scales, init, fixed, prior_sd, max_iter)
            better = score > best_score
            if best is None:
                best = {k: v.copy() for k, v in params.items()}
            for k, v in params.items():
                best[k][..., better] = v[..., better]
            best_nu[better], best_score[better] = nu, score[better]
    # the control's variance: held-out MSE of the fitted mean on every frame
    sq, n = np.zeros(D), 0
    for r, y in zip(results, truths, strict=True):
        c = 0.0 if r.mean_function is None else r.mean_function
        m = c + best["shrink"] * (r.mean - c)
        sq += ((np.asarray(y) - m) ** 2).sum(0)
        n += r.n_frames
    noise = FaceNoise(best["shrink"], best["gp_scale"], best["scale"], best_nu, best["class_offset"],
                      np.maximum(sq / n, 1e-12))
    noise.info = {"n_utterances": len(results), "n_frames": int(n), "fit_entries": int(N * D),
                  "draws_per_synthesis": int(K), "frame_step": int(frame_step), "nu_grid": [float(v) for v in nu_grid],
                  "log_score_per_entry": float(best_score.sum() / (N * D)),
                  "mean": mean, "fixed": {k: np.asarray(v).tolist() for k, v in fixed.items()},
                  "names": list(names) if names is not None else None, "coverage": _coverage(noise, results, truths, labels)}
    if ablations:
        noise.info["ablations"] = {
            name: fit_face_noise(results, truths, labels, n_draws=n_draws, frame_step=frame_step, n_scales=n_scales,
                                 nu_grid=nu_grid, prior_sd=prior_sd, fixed=fix, mean=mean, max_iter=max_iter).to_dict()
            for name, fix in ABLATIONS.items()}
    log.info("face noise: held-out log score %.4f per entry on %d utterances; 90 %% coverage %.3f; a %s; nu %s",
             noise.info["log_score_per_entry"], len(results), noise.info["coverage"].get("0.9", float("nan")),
             np.round(noise.shrink, 2).tolist(), best_nu.tolist())
    return noise


def _coverage(noise: FaceNoise, results: Sequence[SynthesisResult], truths: Sequence[np.ndarray],
              labels: Sequence[Sequence[str]]) -> dict[str, Any]:
    """Central-band coverage of the fitted predictive on the utterances it was fitted on
    (pooled, and 90 % per parameter): y is inside the central q-band exactly when its central
    level |2F(y) − 1| is at most q (one CDF evaluation, no quantile solve)."""
    levels = np.concatenate([np.abs(2.0 * noise.apply(r, lab).cdf(y) - 1.0)
                             for r, y, lab in zip(results, truths, labels, strict=True)])
    out: dict[str, Any] = {str(q): float(np.mean(levels <= q)) for q in (0.5, 0.9)}
    out["0.9_per_parameter"] = np.mean(levels <= 0.9, axis=0).round(4).tolist()
    return out


def held_out_fitter(ablations: bool = False):
    """The ``fitter`` of :func:`bayes_talk.calibration.bands.calibrated_fit` that fits the
    observation term: ``fitter(results, held)`` -> :func:`fit_face_noise` on the held-out
    utterances' AAM parameters and labels."""
    def fitter(results: Sequence[SynthesisResult], held: Sequence) -> FaceNoise:
        return fit_face_noise(results, [s.aam for s in held], [s.labels for s in held],
                              names=[s.name for s in held], ablations=ablations)
    return fitter
