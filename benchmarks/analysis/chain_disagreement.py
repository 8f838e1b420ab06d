"""Where and why the chains of a toy-utterance run disagree (issue 24).

Reads the draws written by ``benchmarks/noncentred_toy.py --save-draws DRAWS.npz`` (latents
(chains, draws, T, d) and ln p per draw) and reports: rank R-hat and bulk ESS per latent
coordinate (ArviZ), their quantiles as ESS per draw, the worst frames with the block they
belong to in the toy utterance's plan (block start, smoothness factor, whether the state
model has dynamics), and for each worst frame's worst coordinate the chains' means and sds,
the between-chain over within-chain spread, each chain's own ESS, the fraction of each
chain's draws inside the other chains' central 90 % (≈ 0.9 when they sample one region;
≈ 0 for chains in separate modes) and each chain's first- and second-half means (drift);
and ln p's R-hat and ESS (chains at different heights of the density would show there).

    PYTHONPATH=. python benchmarks/analysis/chain_disagreement.py DRAWS.npz OUT.json [--frames 78]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent.parent))
sys.path.insert(0, str(HERE.parent.parent / "tests"))

from bayes_talk.base import arviz_compat as azc
from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.synthesis.joint import make_plan

SMALL = {"latent_dim": 3, "max_iter": 40, "min_count": 4, "max_frames_per_state": 120, "fallback_frames": 150}


def frame_kinds(T: int) -> tuple[dict[int, str], list[int]]:
    """Per frame of the toy utterance: its block, whether it starts it, linked/smoothness,
    dynamics; and the isolated frames (no dynamics on either side: ``dynamics_blocks(ff, 1)``)."""
    from toydata import make_utterances

    from bayes_talk.posterior.frame_updates import dynamics_blocks
    from bayes_talk.synthesis.joint import UtteranceDensity
    from bayes_talk.posterior.particle_gibbs import FrameFactors

    model = SwitchingSGPDM(states="vlmm", **SMALL).fit(make_utterances(24, seed=0))
    u = make_utterances(1, seed=1, mean_len=80)[0]
    plan = make_plan(model, u.mfcc[:T], u.labels[:T])
    out = {}
    for b in plan.blocks:
        for t in range(b.start, b.stop):
            tags = ["block start" if t == b.start else "inside"]
            if t == b.start and b.linked:
                tags.append("linked")
            if t == b.start and b.smooth:
                tags.append("smoothness factor")
            tags.append("no dynamics" if b.model.dynamics_predictor_ is None else "dynamics")
            out[t] = f"[{b.start}, {b.stop}) {'/'.join(b.key)}: " + ", ".join(tags)
    return out, [s for s, _ in dynamics_blocks(FrameFactors(UtteranceDensity(plan)), 1)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("draws", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", type=int, default=78)
    ap.add_argument("--worst", type=int, default=8)
    args = ap.parse_args()
    f = np.load(args.draws)
    X, lp = f["latents"], f["lp"]
    C, D, T, d = X.shape
    flat = X.reshape(C, D, T * d)
    rh = np.asarray(azc.rhat(flat), dtype=float).reshape(T, d)
    ess = np.asarray(azc.ess(flat, "bulk"), dtype=float).reshape(T, d)
    kinds, iso = frame_kinds(T)
    res = {"command": "benchmarks/analysis/chain_disagreement.py " + " ".join(sys.argv[1:]),
           "chains": C, "draws_per_chain": D, "rhat_max": float(rh.max()),
           "frames_rhat_above_1.01": int((rh.max(1) > 1.01).sum()),
           "frames_rhat_above_1.05": int((rh.max(1) > 1.05).sum()),
           "ess_per_draw_quantiles_0_5_25_50": np.quantile(ess / (C * D), [0, 0.05, 0.25, 0.5]).round(3).tolist(),
           "lp_mean_per_chain": lp.mean(1).tolist(), "lp_sd_per_chain": lp.std(1).tolist(),
           "lp_rhat": float(np.asarray(azc.rhat(lp[:, :, None])).ravel()[0]),
           "lp_ess_bulk": float(np.asarray(azc.ess(lp[:, :, None], "bulk")).ravel()[0]),
           "isolated_frames": iso, "worst_frames_isolated": None,
           "rhat_per_frame": rh.max(1).round(4).tolist(), "ess_bulk_min_per_frame": ess.min(1).round(1).tolist(),
           "worst_frames": []}
    for t in np.argsort(ess.min(1))[:args.worst]:
        k = int(np.argmin(ess[t]))
        v = X[:, :, t, k]
        m, s = v.mean(1), v.std(1)
        inside = []
        for c in range(C):
            o = np.delete(v, c, 0).ravel()
            lo, hi = np.quantile(o, [0.05, 0.95])
            inside.append(float(np.mean((v[c] >= lo) & (v[c] <= hi))))
        h = D // 2
        res["worst_frames"].append({
            "frame": int(t), "block": kinds[int(t)], "coordinate": k, "rhat": float(rh[t, k]),
            "ess_bulk": float(ess[t, k]), "chain_means": m.tolist(), "chain_sds": s.tolist(),
            "between_over_within": float(m.std() / s.mean()),
            "ess_bulk_per_chain": [float(np.asarray(azc.ess(np.stack([v[c, :h], v[c, h:2 * h]])[:, :, None],
                                                                "bulk")).ravel()[0]) for c in range(C)],
            "fraction_inside_other_chains_90": inside,
            "half_means_per_chain": [[float(v[c, :h].mean()), float(v[c, h:].mean())] for c in range(C)]})
    res["worst_frames_isolated"] = sum(w["frame"] in iso for w in res["worst_frames"])
    args.out.write_text(json.dumps(res, indent=1))
    print(json.dumps({k: v for k, v in res.items() if k not in ("rhat_per_frame", "ess_bulk_min_per_frame")},
                     indent=1))


if __name__ == "__main__":
    main()
