"""Where NUTS chains sit on a whole-utterance synthesis posterior (issue 10).

Runs ``sample_synthesis(method="nuts")`` on one held-out utterance, then maximises the joint
density from every chain's last draw (``maximise_utterance``) and reports, per chain: its
mean ln p over the draws, the log density of the mode it sits in, the frames where that
mode differs from the run's whitening mode (> 0.01), and the log density split into its
terms (audio GP likelihood and its −½ Σ ln σ²_Y(x) part, dynamics, entry densities,
smoothness factors) for the whitening mode and each chain's mode.

    PYTHONPATH=. python benchmarks/analysis/nuts_modes.py MODEL_DIR HELDOUT_DIR UTT OUT.json \
        [--warmup 300] [--draws 400]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bayes_talk.corpus import load_corpus
from bayes_talk.base.files import write_json
from bayes_talk.pipeline import load_trained
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan
from bayes_talk.synthesis.joint_map import maximise_utterance
from bayes_talk.posterior.sampling import sample_synthesis, visual_predictive
from bayes_talk.synthesis.segment_objective import LOG_2PI


def terms(dens: UtteranceDensity, x: np.ndarray) -> dict:
    """ln p(x) split by term (the sums of UtteranceDensity.values, kept apart)."""
    tm, d = dens.terms, dens.d
    Xb = x[None]

    def rows(idx):
        return Xb[:, idx].transpose(1, 0, 2).reshape(-1, d)

    def gauss(y, mu, var):
        r = y - mu
        return -0.5 * (LOG_2PI + np.log(var) + r * r / var)

    out = {"total": float(dens(x)[0])}
    mu, s = tm.audio_gps.mean_var(tm.a_runs.repeat(1), rows(tm.a_idx))
    var = s[:, None] / tm.audio_gps.w2[tm.a_runs.row_gp(1)]
    out["audio"] = float(gauss(np.repeat(tm.a_Y, 1, axis=0), mu, var).sum())
    out["audio_minus_half_log_var"] = float((-0.5 * np.log(var)).sum())
    mu, s = tm.dyn_gps.mean_var(tm.d_runs.repeat(1), rows(tm.d_src))
    out["dynamics"] = float(gauss(rows(tm.d_dst), mu, s[:, None] / tm.dyn_gps.w2[tm.d_runs.row_gp(1)]).sum())
    out["entry"] = float(np.sum(tm.entry_grad(Xb[:, tm.e_idx])[0])) if len(tm.e_idx) else 0.0
    out["smoothness"] = float(tm.smooth_grad(np.concatenate([rows(tm.s_idx - 1), rows(tm.s_idx)], 1), 1)[0].sum()) \
        if len(tm.s_idx) else 0.0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("heldout", type=Path)
    ap.add_argument("utterance")
    ap.add_argument("out", type=Path)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--draws", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    tm = load_trained(a.model)
    model = tm.uncalibrated
    tc = load_corpus(tm.training_corpus())
    s = next(u for u in load_corpus(a.heldout, aam=tc.aam_path).sequences if u.name == a.utterance)
    t0 = time.perf_counter()
    r = sample_synthesis(model, s.mfcc, s.labels, method="nuts", n_draws=a.draws, warmup=a.warmup, seed=a.seed)
    seconds = time.perf_counter() - t0
    plan = make_plan(model, s.mfcc, s.labels, "frame")
    dens = UtteranceDensity(plan)
    X, best = r.latent_draws, r.map.latents
    chains = []
    for c in range(X.shape[0]):
        m = maximise_utterance(dens, X[c, -1])
        chains.append({"mean_lp": float(r.sample_stats["lp"][c].mean()), "mode_log_density": m.log_density,
                       "mode_converged": m.converged,
                       "frames_differing": np.flatnonzero(np.abs(m.latents - best).max(1) > 1e-2).tolist(),
                       "mode_terms": terms(dens, m.latents),
                       "mode_visual_sq_err": float(np.mean((visual_predictive(plan, m.latents[None, None])[0][0, 0]
                                                            - s.aam) ** 2)),
                       "jumps_accepted": int(r.sample_stats["jumps"][c].sum())})
    keys = ("rhat_max", "ess_bulk_min", "ess_tail_min", "map_log_density", "map_first_log_density",
            "map_restart_log_densities", "pilot_mode_log_densities", "mode_jumps", "mode_jump_acceptance",
            "mode_jumps_accepted_per_chain", "n_gradients", "step_size", "tree_depth_mean", "divergences", "pilot")
    out = {"command": " ".join(sys.argv), "utterance": a.utterance, "frames": int(X.shape[2]),
           "warmup": a.warmup, "draws": a.draws, "seconds": seconds,
           "diagnostics": {k: r.diagnostics.get(k) for k in keys},
           "whitening_mode_terms": terms(dens, best),
           "whitening_mode_visual_sq_err": float(np.mean((visual_predictive(plan, best[None, None])[0][0, 0] - s.aam) ** 2)),
           "chains": chains}
    write_json(a.out, out)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
