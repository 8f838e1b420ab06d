"""NUTS in whitened vs non-centred coordinates on the toy utterance of tests/ (issue 24).

Model: ``SwitchingSGPDM(states="vlmm")`` with the test configuration on
``tests/toydata.py make_utterances(24, seed=0)``; utterance: the first ``--frames`` (78)
frames of ``make_utterances(1, seed=1, mean_len=80)[0]``; smoothness on ("frame").
For each coordinate system (``--coords``), ``sample_synthesis(method="nuts")`` with the
library defaults unless overridden (``--chains``, ``--warmup``, ``--draws`` pooled), and
the diagnostics of the latents and of the AAM-parameter means μ_Z(x) at every draw
(rank R-hat, bulk/tail ESS: ``chain_diagnostics``). JSON, written after each run:

    PYTHONPATH=. python benchmarks/noncentred_toy.py [--coords whitened,noncentred] \
        [--out benchmarks/results/noncentred_toy78.json]

``--coords pg-nuts``: ``sample_synthesis(method="pg-nuts")`` (particle Gibbs ∘ NUTS ∘ mode
jumps, its defaults; ``--pg-particles``, ``--pg-coords``, ``--pg-every``, ``--pg-backward``,
``--pg-frame-tries``, ``--pg-frame-modes on|off``, ``--pg-block-len`` override them). ``--coords pg``: particle Gibbs alone from Laplace draws (``--pg-particles``, ``--pg-h`` the
proposal's kernel bandwidths), with the per-frame update rate and the frames never updated.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parent / "tests"))

from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.posterior.diagnostics import chain_diagnostics, frame_update_diagnostics
from bayes_talk.posterior.sampling import sample_synthesis

SMALL = {"latent_dim": 3, "max_iter": 40, "min_count": 4, "max_frames_per_state": 120, "fallback_frames": 150}
KEYS = ("rhat_max", "ess_bulk_min", "ess_tail_min")


def main() -> None:
    from toydata import make_utterances

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--coords", default="whitened,noncentred")
    ap.add_argument("--frames", type=int, default=78)
    ap.add_argument("--chains", type=int, default=None)
    ap.add_argument("--warmup", type=int, default=None)
    ap.add_argument("--draws", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=None, help="chains in this many processes (default: in-process)")
    ap.add_argument("--pg-particles", type=int, default=64, help="particles of the particle Gibbs sweeps (coords pg)")
    ap.add_argument("--pg-h", default="0.05",
                    help="comma-separated bandwidths of the proposal's training-latent kernels (coords pg)")
    ap.add_argument("--pg-lookahead", action="store_true",
                    help="weigh the proposal's centres at a dynamics run's first frame by the run's audio (coords pg)")
    ap.add_argument("--pg-map-centre", action="store_true",
                    help="add the joint MAP's latent of each frame to the proposal's centres (coords pg)")
    ap.add_argument("--pg-backward", action="store_true", help="backward simulation instead of ancestor sampling (pg-nuts)")
    ap.add_argument("--pg-frame-tries", type=int, default=None,
                    help="K-try Metropolis updates of isolated frames after each sweep (pg-nuts)")
    ap.add_argument("--pg-coords", default=None,
                    help="the NUTS coordinates of pg-nuts (noncentred or noncentred-whitened; default: its own)")
    ap.add_argument("--pg-frame-modes", choices=("on", "off"), default=None,
                    help="the isolated frames' tries from their own modes or from the sweep's proposal (pg-nuts)")
    ap.add_argument("--pg-block-len", type=int, default=None,
                    help="also update dynamics runs of up to this many frames by multiple tries (pg-nuts)")
    ap.add_argument("--pg-every", type=int, default=None, help="a particle Gibbs sweep after every k-th iteration (pg-nuts)")
    ap.add_argument("--save-draws", type=Path, default=None,
                    help="write the latent draws (chains, draws, T, d) and the lp per draw to this .npz (for analysis)")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "noncentred_toy78.json")
    args = ap.parse_args()
    model = SwitchingSGPDM(states="vlmm", **SMALL).fit(make_utterances(24, seed=0))
    u = make_utterances(1, seed=1, mean_len=80)[0]
    T = min(args.frames, u.n_frames)
    mfcc, labels = u.mfcc[:T], u.labels[:T]
    res = {"command": "benchmarks/noncentred_toy.py " + " ".join(sys.argv[1:]), "frames": T,
           "utterance": "tests/toydata.py make_utterances(1, seed=1, mean_len=80)[0], first frames",
           "cpus": os.cpu_count(), "runs": {}}
    kw = {k: v for k, v in (("chains", args.chains), ("warmup", args.warmup), ("n_draws", args.draws)) if v is not None}
    for coords in args.coords.split(","):
        if coords == "pg":
            res["runs"]["pg"] = particle_gibbs(model, mfcc, labels, args)
            print("pg", json.dumps(res["runs"]["pg"]), flush=True)
            _write(res, args.out)
            continue
        t0 = time.perf_counter()
        method = "pg-nuts" if coords == "pg-nuts" else "nuts"   # pg-nuts: its own defaults (non-centred)
        if method == "pg-nuts":
            skw = {"pg_particles": args.pg_particles}
            if args.pg_coords:
                skw["coords"] = args.pg_coords
        else:
            skw = {"coords": coords}
        if args.pg_every is not None and method == "pg-nuts":
            skw["pg_every"] = args.pg_every
        if args.pg_frame_tries is not None and method == "pg-nuts":
            skw["pg_frame_tries"] = args.pg_frame_tries
        if args.pg_frame_modes is not None and method == "pg-nuts":
            skw["pg_frame_modes"] = args.pg_frame_modes == "on"
        if args.pg_block_len is not None and method == "pg-nuts":
            skw["pg_block_len"] = args.pg_block_len
        if args.pg_backward and method == "pg-nuts":
            skw["pg_backward"] = True
        if args.workers:
            skw["workers"] = args.workers
        r = sample_synthesis(model, mfcc, labels, method=method, seed=args.seed, sampler_kw=skw, log_warnings=False,
                             **kw)
        wall = time.perf_counter() - t0
        lat = chain_diagnostics(r.latent_draws.reshape(r.latent_draws.shape[0], r.latent_draws.shape[1], -1))
        aam = chain_diagnostics(r.draw_mean.reshape(r.draw_mean.shape[0], r.draw_mean.shape[1], -1))
        d = r.diagnostics
        res["runs"][coords] = {
            "wall_seconds": wall, "latents": {k: float(lat[k]) for k in KEYS},
            "aam_mean": {k: float(aam[k]) for k in KEYS},
            **{k: d.get(k) for k in ("divergences", "ebfmi_min", "step_size", "n_steps_mean", "tree_depth_mean",
                                     "accept_stat_mean", "n_gradients", "sampler_seconds", "warmup_seconds",
                                     "map_log_density", "mode_jumps", "mode_jump_acceptance", "n_chains", "n_draws",
                                     "pg_h", "pg_mode_centres", "pg_particles", "coords", "pg_every", "pg_backward", "pg_frame_tries",
                                     "pg_frame_modes", "pg_block_len", "pg_neighbours", "pg_pairs", "pg_adapt_weights",
                                     "pg_block_sweeps", "pg_adapt_moments", "pg_adapt_clusters",
                                     "pg_adaptation")},
            # where the chains disagree: worst R-hat over each frame's coordinates, and ln p per chain
            "rhat_per_frame": d.get("rhat_per_frame"), "aam_rhat_per_frame": d.get("aam_rhat_per_frame"),
            # pg-nuts: how often the sweeps after the warm-up changed each frame (per chain)
            **{k: d.get(k) for k in ("pg_frame_update_rate_min", "pg_frame_update_rate_mean",
                                     "pg_frames_never_updated") if k in d},
            "lp_mean_per_chain": np.asarray(r.sample_stats["lp"]).mean(1).tolist() if "lp" in r.sample_stats else None}
        if args.save_draws:
            np.savez(args.save_draws, latents=r.latent_draws, lp=np.asarray(r.sample_stats.get("lp", np.nan)))
        print(coords, json.dumps(res["runs"][coords]), flush=True)
        _write(res, args.out)


def _write(res: dict, out: Path) -> None:
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(res, indent=1, default=float))
    tmp.replace(out)


def particle_gibbs(model, mfcc, labels, args) -> dict:
    """Particle Gibbs (CSMC with ancestor sampling) chains from Laplace draws at the MAP
    (``--pg-particles``, ``--chains``, ``--warmup`` and ``--draws`` per chain as sweeps)."""
    from bayes_talk.synthesis.joint import UtteranceDensity, make_plan
    from bayes_talk.posterior.particle_gibbs import run_particle_gibbs
    from bayes_talk.posterior.sampling import visual_predictive

    chains = args.chains or 4
    t0 = time.perf_counter()
    lap = sample_synthesis(model, mfcc, labels, method="laplace", n_draws=max(8, chains), seed=args.seed,
                           log_warnings=False)
    plan = make_plan(model, mfcc, labels)
    h = tuple(float(v) for v in args.pg_h.split(","))
    out = run_particle_gibbs(UtteranceDensity(plan), plan, lap.latent_draws[0, :chains], n_draws=args.draws or 200,
                             warmup=args.warmup or 100, seed=args.seed, n_particles=args.pg_particles, h=h,
                             lookahead=args.pg_lookahead,
                             extra_centres=lap.map_latents[None] if args.pg_map_centre else None)
    S = out["samples"]
    zm, _ = visual_predictive(plan, S)
    lat = chain_diagnostics(S.reshape(S.shape[0], S.shape[1], -1))
    aam = chain_diagnostics(zm.reshape(zm.shape[0], zm.shape[1], -1))
    ud = frame_update_diagnostics(out["frame_update_rate"], prefix="")
    return {"wall_seconds": time.perf_counter() - t0, "sampler_seconds": out["seconds"],
            "latents": {k: float(lat[k]) for k in KEYS}, "aam_mean": {k: float(aam[k]) for k in KEYS},
            "n_particles": args.pg_particles, "bandwidths": list(h), "lookahead": args.pg_lookahead,
            "map_centre": args.pg_map_centre, "sweeps_per_chain": int(S.shape[1]),
            "n_chains": int(S.shape[0]), "frames_never_updated": len(ud["frames_never_updated"]),
            "frame_update_rate_min": ud["frame_update_rate_min"], "frame_update_rate_mean": ud["frame_update_rate_mean"],
            "frame_update_rate_per_frame": np.mean(ud["frame_update_rate"], axis=0).tolist(),
            "lp_mean_per_chain": out["lp"].mean(1).tolist(),
            "map_log_density": float(lap.diagnostics["map_log_density"])}


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    interruptible(main)
