"""Sampler diagnostics through ArviZ (docs/uncertainty.md, "Diagnostics and thresholds") - the only
posterior module that imports arviz.

Every ArviZ call goes through :mod:`bayes_talk.base.arviz_compat` (ArviZ 0.2x on Python 3.11,
1.x on >= 3.12).

* :func:`chain_diagnostics` - draws (chains, draws, n): rank-normalised split R-hat
  (``arviz.rhat(method="rank")``, Vehtari et al. 2021), bulk and tail ESS
  (``arviz.ess(method="bulk"|"tail")``) and the Monte-Carlo standard errors of the mean and
  of the standard deviation (``arviz.mcse(method="mean"|"sd")``), per coordinate and worst case.
* :func:`energy_bfmi` - the energy Bayesian fraction of missing information per chain
  (``arviz.bfmi``, Betancourt 2016): Σ(E_n − E_{n−1})² / Σ(E_n − Ē)² of the Hamiltonian at
  each NUTS iteration; below 0.3 the momentum resampling does not explore the energy levels.
* :func:`psis` / :func:`psis_khat` - the Pareto shape k̂ (and the effective sample size
  1/Σ w̃² of the smoothed weights) of importance weights (``arviz.psislw``,
  Vehtari et al. 2024): for draws x_s of an approximation q (Laplace, VI) of p, the log
  weights ln p(x_s) − ln q(x_s); k̂ ≤ 0.7 means importance sampling from q, and so q
  itself for expectations of moderate functions, is reliable; above 0.7 it is not.
* :func:`frame_update_rate` / :func:`frame_update_diagnostics` - how often a particle Gibbs
  sweep changed each frame's latent: per chain c and frame t, the fraction
  r_ct = Σ_s m_cst / Σ_s w_cs of the sweeps counted (w_cs = 1 where a sweep ran at
  iteration s, m_cst = 1 where it changed x_t), and its minimum, mean and the frames no
  chain updated. A frame with r_ct = 0 was never moved by the sweeps of chain c (only the
  other kernels moved it); no threshold, reported only.
* :func:`convergence_problems` - the failed checks against :data:`THRESHOLDS`, in words;
  :func:`sampler_warning` - those checks as the one warning a synthesis result carries.
* :func:`inference_data` - ``arviz.from_dict`` for the synthesis result type.
* :func:`psis_diagnostics` - k̂ of an iid approximation's draws against the synthesis density
  (Laplace, VI); :func:`sampler_diagnostics` - the summary of a NUTS or emcee run on the
  latents the user receives (the posterior methods' diagnostics, ``diagnostics.json``).

With a single chain (Laplace draws) the chain is split in two halves before ArviZ sees it
(ArviZ returns nan R-hat for one chain); ``n_chains`` reports the chains given.
"""
from __future__ import annotations

import warnings

import numpy as np

from bayes_talk.base import arviz_compat as azc

DIAGNOSTIC_KEYS = ("rhat_max", "ess_bulk_min", "ess_tail_min", "mcse_mean_max", "mcse_sd_max", "n_chains",
                   "n_draws", "rhat", "ess_bulk", "ess_tail", "mcse_mean", "mcse_sd")

#: rank R-hat at most this (Vehtari et al. 2021)
RHAT_MAX = 1.01
#: bulk and tail ESS at least this (Vehtari et al. 2021: 100 per chain for 4 chains)
ESS_MIN = 400.0
#: PSIS Pareto k̂ at most this (Vehtari et al. 2024)
KHAT_MAX = 0.7
#: energy BFMI at least this in every chain (Betancourt 2016)
EBFMI_MIN = 0.3
THRESHOLDS = {"rhat_max": RHAT_MAX, "ess_min": ESS_MIN, "divergences": 0, "khat_max": KHAT_MAX,
              "ebfmi_min": EBFMI_MIN}


def chain_diagnostics(samples: np.ndarray) -> dict:
    """Rank R-hat, bulk/tail ESS and MCSE of (chains, draws, n) samples via ArviZ."""
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 3:
        raise ValueError(f"samples: expected (chains, draws, n), got shape {s.shape}")
    C, S, n = s.shape
    if S < 4:
        raise ValueError(f"need at least 4 draws per chain for split R-hat, got {S}")
    if C == 1:  # ArviZ gives nan R-hat for one chain: split it explicitly (what split R-hat does)
        h = S // 2
        s = np.stack([s[0, :h], s[0, h:2 * h]])
    rhat = np.asarray(azc.rhat(s), float).reshape(n)
    bulk = np.asarray(azc.ess(s, "bulk"), float).reshape(n)
    tail = np.asarray(azc.ess(s, "tail"), float).reshape(n)
    mcse_mean = np.asarray(azc.mcse(s, "mean"), float).reshape(n)
    mcse_sd = np.asarray(azc.mcse(s, "sd"), float).reshape(n)
    return {
        "rhat_max": float(np.nanmax(rhat)),
        "ess_bulk_min": float(np.nanmin(bulk)),
        "ess_tail_min": float(np.nanmin(tail)),
        "mcse_mean_max": float(np.nanmax(mcse_mean)),
        "mcse_sd_max": float(np.nanmax(mcse_sd)),
        "n_chains": int(C),
        "n_draws": int(S),
        "rhat": rhat,
        "ess_bulk": bulk,
        "ess_tail": tail,
        "mcse_mean": mcse_mean,
        "mcse_sd": mcse_sd,
    }


def frame_diagnostics(samples: np.ndarray, prefix: str = "") -> dict:
    """:func:`chain_diagnostics` of draws (chains, draws, T, D) — latents or AAM parameters per
    frame — summarised over everything (``{prefix}rhat_max``, ``…ess_bulk_min``,
    ``…ess_tail_min``, ``…mcse_mean_max``, ``…mcse_sd_max``) and per frame, worst over the
    frame's D coordinates (``{prefix}rhat_per_frame``, ``…ess_bulk_per_frame``,
    ``…ess_tail_per_frame``, ``…mcse_mean_per_frame``, ``…mcse_sd_per_frame``: lists of T
    floats, JSON-ready)."""
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 4:
        raise ValueError(f"samples: expected (chains, draws, T, D), got shape {s.shape}")
    C, S, T, D = s.shape
    cd = chain_diagnostics(s.reshape(C, S, T * D))
    out = {prefix + k: cd[k] for k in ("rhat_max", "ess_bulk_min", "ess_tail_min", "mcse_mean_max", "mcse_sd_max")}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # all-nan frames (constant draws)
        for k, fn in (("rhat", np.nanmax), ("ess_bulk", np.nanmin), ("ess_tail", np.nanmin),
                      ("mcse_mean", np.nanmax), ("mcse_sd", np.nanmax)):
            out[f"{prefix}{k}_per_frame"] = [float(v) for v in fn(cd[k].reshape(T, D), axis=1)]
    return out


def frame_update_rate(moved: np.ndarray, swept: np.ndarray | None = None) -> np.ndarray:
    """Per chain and frame, the fraction of particle Gibbs sweeps that changed the frame's
    latent (the module docstring's r_ct), (C, T): ``moved`` (C, S, T) whether the move after
    iteration s changed frame t; ``swept`` (C, S) whether a sweep ran then (None: at every
    iteration). A chain without a sweep has rate nan."""
    m = np.asarray(moved, dtype=bool)
    if m.ndim != 3:
        raise ValueError(f"moved: expected (chains, sweeps, T), got shape {m.shape}")
    n = np.full(m.shape[:2], True) if swept is None else np.asarray(swept, dtype=bool)
    if n.shape != m.shape[:2]:
        raise ValueError(f"swept: expected shape {m.shape[:2]}, got {n.shape}")
    if np.any(m & ~n[..., None]):
        raise ValueError("moved: a frame changed at an iteration without a sweep")
    with np.errstate(invalid="ignore", divide="ignore"):
        return m.sum(1) / n.sum(1)[:, None]


def frame_update_diagnostics(rate: np.ndarray, prefix: str = "pg_") -> dict:
    """JSON-ready summary of :func:`frame_update_rate` (C, T): ``{prefix}frame_update_rate``
    (C lists of T), ``…_min`` and ``…_mean`` over chains and frames, and
    ``{prefix}frames_never_updated``: the frames whose rate is 0 in every chain."""
    r = np.asarray(rate, dtype=np.float64)
    if r.ndim != 2:
        raise ValueError(f"rate: expected (chains, T), got shape {r.shape}")
    return {f"{prefix}frame_update_rate": r.tolist(), f"{prefix}frame_update_rate_min": float(np.min(r)),
            f"{prefix}frame_update_rate_mean": float(np.mean(r)),
            f"{prefix}frames_never_updated": [int(t) for t in np.flatnonzero(np.all(r == 0, axis=0))]}


def energy_bfmi(energy: np.ndarray) -> np.ndarray:
    """E-BFMI of each chain from the Hamiltonian energy (chains, draws) of NUTS iterations."""
    e = np.asarray(energy, dtype=np.float64)
    if e.ndim != 2 or e.shape[1] < 2:
        raise ValueError(f"energy: expected (chains, draws >= 2), got shape {e.shape}")
    return azc.bfmi(e)


def psis(log_weights: np.ndarray) -> tuple[float, float]:
    """(Pareto k̂, effective sample size) of the importance log weights (n,) =
    ln p(x_s) − ln q(x_s) (constants free), by PSIS (``az.psislw``; Vehtari et al. 2024):
    ESS = 1 / Σ w̃², w̃ the smoothed, normalised weights. With k̂ > 0.7 neither the
    estimates nor this ESS are reliable."""
    lw = np.asarray(log_weights, dtype=np.float64).reshape(-1)
    if lw.size < 10:
        raise ValueError(f"need at least 10 importance weights for PSIS, got {lw.size}")
    if not np.all(np.isfinite(lw)):
        return float("inf"), 0.0
    lw_s, k = azc.psislw(lw)  # ArviZ's warning for k̂ > 0.7 is silenced: the caller reports it
    w = np.exp(lw_s - np.max(lw_s))
    w /= w.sum()
    return k, float(1.0 / np.sum(w * w))


def psis_khat(log_weights: np.ndarray) -> float:
    """Pareto k̂ of the importance log weights (n,) = ln p(x_s) − ln q(x_s) (:func:`psis`)."""
    return psis(log_weights)[0]


def sampler_warning(method: str, fails: list[str], advice: str = "") -> list[str]:
    """The one warning of a synthesis whose ``method`` failed the checks ``fails`` ([] when
    none failed); :func:`is_sampler_warning` recognises it."""
    if not fails:
        return []
    return [f"{method} did not converge: " + "; ".join(fails) + " — do not trust its bands"
            + (f"; {advice}" if advice else "")]


def is_sampler_warning(method: str, warning: str) -> bool:
    """Whether ``warning`` is the :func:`sampler_warning` of ``method``."""
    return warning.startswith(f"{method} did not converge: ")


def convergence_problems(diag: dict) -> list[str]:
    """The failed checks of a sampler run's diagnostics, in words: R-hat above
    :data:`RHAT_MAX`, bulk or tail ESS below :data:`ESS_MIN` (of the latents, and of the
    AAM parameters' draws ``aam_rhat_max`` … when present), any divergent transition,
    PSIS k̂ above :data:`KHAT_MAX`, an E-BFMI below :data:`EBFMI_MIN`, an emcee chain
    shorter than the autocorrelation-time rule. Only the keys present are checked
    ([] for the MAP)."""
    out = []
    for pre, name in (("", ""), ("aam_", "AAM-parameter ")):   # the latents, then what users consume
        r = diag.get(pre + "rhat_max")
        if r is not None and (not np.isfinite(r) or r > RHAT_MAX):
            out.append(f"{name}R-hat {r:.4f} > {RHAT_MAX}")   # 4 decimals: 1.0102, not 1.01, against 1.01
        for key, what in (("ess_bulk_min", "bulk"), ("ess_tail_min", "tail")):
            e = diag.get(pre + key)
            if e is not None and (not np.isfinite(e) or e < ESS_MIN):
                out.append(f"{name}{what} ESS {e:.3g} < {ESS_MIN:g}")
    dv = diag.get("divergences")
    if dv:
        out.append(f"{int(dv)} divergent transitions (want 0)")
    k = diag.get("khat")
    if k is not None and (not np.isfinite(k) or k > KHAT_MAX):
        out.append(f"PSIS k̂ {k:.3g} > {KHAT_MAX}")
    b = diag.get("ebfmi_min")
    if b is not None and np.isfinite(b) and b < EBFMI_MIN:
        out.append(f"E-BFMI {b:.3g} < {EBFMI_MIN}")
    if diag.get("autocorr_ok") is False:
        out.append(f"emcee chain of {diag['autocorr_steps']} steps < {diag['autocorr_tol']:g} × "
                   f"autocorrelation time {diag['autocorr_time_max']:.3g}")
    return out


def inference_data(posterior: dict, sample_stats: dict | None = None, observed_data: dict | None = None,
                   dims: dict | None = None, coords: dict | None = None,
                   posterior_predictive: dict | None = None):
    """``arviz.from_dict`` (:func:`bayes_talk.base.arviz_compat.from_dict`): arrays (chains,
    draws, ...) of ``posterior`` and ``sample_stats`` (ArviZ names: ``lp``,
    ``acceptance_rate``, ``step_size``, ``tree_depth``, ``n_steps``, ``diverging``,
    ``energy``), ``observed_data`` without chain/draw dimensions."""
    return azc.from_dict(posterior, posterior_predictive=posterior_predictive, sample_stats=sample_stats,
                         observed_data=observed_data, coords=coords, dims=dims)


#: draws per batched density call of the k̂ check
KHAT_CHUNK = 50


def psis_diagnostics(dens, X: np.ndarray, log_q: np.ndarray, n_keep: int | None = None,
                      sample_stats: dict | None = None) -> dict:
    """PSIS k̂ and ESS of an approximation q of p (Laplace, VI; ``dens`` the
    :class:`~bayes_talk.synthesis.joint.UtteranceDensity` of p) from its draws X (S, T·d) and
    their ln q (constants free): log weights ln p(x_s) − ln q(x_s) (Vehtari et al. 2024); ln p
    in chunks through :meth:`UtteranceDensity.values` (value only, all draws' rows of a GP in
    one run). With ``sample_stats`` (a dict), the first ``n_keep`` draws' ``lp`` and
    ``log_weight`` (1, n_keep) are put in it (``InferenceData.sample_stats``)."""
    lp = np.concatenate([dens.values(X[i:i + KHAT_CHUNK]) for i in range(0, len(X), KHAT_CHUNK)])
    khat, ess = psis(lp - log_q)
    if sample_stats is not None and n_keep:   # per kept draw (one chain): ln p and the log weight ln p − ln q
        sample_stats["lp"] = lp[None, :n_keep]
        sample_stats["log_weight"] = (lp - log_q)[None, :n_keep]
    return {"khat": khat, "psis_ess": ess, "khat_draws": len(lp)}


def sampler_diagnostics(draws, latents: np.ndarray) -> dict:
    """Summary diagnostics of a NUTS or emcee run, ``draws`` its
    :class:`~bayes_talk.posterior.samplers.Draws` (JSON-ready scalars and short lists).

    R-hat, ESS and MCSE are those of the latent draws the user receives (``latents``,
    (chains, draws, T, d): X = X_MAP + L z, or x(ε)), overall and per frame
    (:func:`~bayes_talk.posterior.diagnostics.frame_diagnostics`), not of the coordinates
    the sampler moved in (the maps are not the identity, and ESS and R-hat are per
    coordinate). NUTS: divergences, step sizes, the acceptance statistic, tree depths,
    gradients, E-BFMI per chain, mode jumps, per-chain seconds; with particle Gibbs sweeps
    (``pg_frame_moved`` in the per-draw statistics) the per-frame update rate of the sweeps
    after the warm-up (:func:`~bayes_talk.posterior.diagnostics.frame_update_diagnostics`).
    emcee: acceptance and the autocorrelation time."""
    out = frame_diagnostics(latents)
    out.update(n_chains=int(latents.shape[0]), n_draws=int(latents.shape[1]))
    st, ss = draws.stats, draws.sample_stats
    if draws.method == "nuts":
        out["divergences"] = int(sum(st["divergences"]))
        out["step_size"] = [float(s) for s in st["step_size"]]
        out["accept_stat_mean"] = float(np.mean(ss["acceptance_rate"]))
        out["target_accept"] = st["target_accept"]
        out["tree_depth_mean"] = float(np.mean(ss["tree_depth"]))
        out["tree_depth_max"] = int(np.max(ss["tree_depth"]))
        out["max_tree_depth"] = st["max_tree_depth"]
        out["max_tree_depth_hits"] = st["max_tree_depth_hits"]
        out["n_steps_mean"] = float(np.mean(ss["n_steps"]))
        out["n_gradients"] = st["n_gradients"]
        out["warmup"] = st["warmup"]
        out["warmup_seconds"] = st["warmup_seconds"]
        out["ebfmi"] = [float(b) for b in energy_bfmi(ss["energy"])]
        out["ebfmi_min"] = min(out["ebfmi"])
        out["mode_jumps"] = st["n_jumps"]
        att, acc = sum(st["jump_attempts"]), sum(st["jumps_accepted"])
        out["mode_jump_acceptance"] = acc / att if att else None
        out["mode_jumps_accepted_per_chain"] = st["jumps_accepted"]
        out["pilot"] = st.get("pilot", 0)
        out["chain_seconds"] = st["chain_seconds"]
        out["pilot_seconds"] = float(st.get("pilot_seconds", 0.0))
        if "checks" in st:   # a stopping rule (stop_at_targets): when it was asked, whether it ended the draws
            out.update(stopped_early=st["stopped_early"], max_draws_per_chain=st["max_draws_per_chain"])
        if "pg_frame_moved" in ss:
            out["pg_sweeps_per_chain"] = [int(n) for n in ss["pg_sweep"].sum(1)]
            if "pg_seconds" in ss:   # the move's seconds over the kept draws (warm-up not recorded)
                out["pg_seconds_per_chain"] = [float(v) for v in ss["pg_seconds"].sum(1)]
            out.update(frame_update_diagnostics(frame_update_rate(ss["pg_frame_moved"], ss["pg_sweep"])))
        if "pg_blocks_without_modes" in st:   # blocks whose tries fall back to the sweep's proposal
            out["pg_blocks_without_modes"] = st["pg_blocks_without_modes"]
        if "extra_move_adaptation" in st:     # pg_adapt_weights: the mode weights the chains' warm-ups taught
            out["pg_adaptation"] = st["extra_move_adaptation"]
    if "acceptance_fraction" in st:
        out["acceptance_fraction"] = float(st["acceptance_fraction"])
        out["acceptance_min"] = float(st["acceptance_min"])
        for k in ("autocorr_time_max", "autocorr_time_mean", "autocorr_steps", "autocorr_tol", "autocorr_ok",
                  "steps", "thin", "n_walkers", "warmup"):
            out[k] = st[k]
    out["sampler_seconds"] = float(draws.seconds)
    return out


__all__ = [
    "DIAGNOSTIC_KEYS",
    "EBFMI_MIN",
    "ESS_MIN",
    "KHAT_CHUNK",
    "KHAT_MAX",
    "RHAT_MAX",
    "THRESHOLDS",
    "chain_diagnostics",
    "convergence_problems",
    "energy_bfmi",
    "frame_diagnostics",
    "frame_update_diagnostics",
    "frame_update_rate",
    "inference_data",
    "is_sampler_warning",
    "psis",
    "psis_diagnostics",
    "psis_khat",
    "sampler_diagnostics",
    "sampler_warning",
]
