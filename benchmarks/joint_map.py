"""The joint MAP of the whole-utterance synthesis posterior on held-out utterances.

For each of the first ``--n-test`` utterances of ``--test-corpus`` (projected through the
training corpus's AAM ``--aam``), with a model written by ``bayes-talk train``:

* Algorithm 1's path, then :func:`~bayes_talk.synthesis.joint_map.maximise_utterance`:
  converged or not, max |∂ ln p/∂x|, Newton decrement, Hessian eigenvalues floored,
  iterations, density evaluations, seconds (wall, one torch thread), ln p;
* the PSIS k̂ of the Laplace approximation at that MAP (``--khat-draws`` draws; k̂ ≤ 0.7 is
  the threshold of a usable importance proposal);
* ``--reference``: beside it, the dense reference of the same two stages (L-BFGS whitened by
  the eigen-decomposition of the precision, eigenvalues floored; scipy's ``trust-exact`` on the
  dense Hessian: cubic in the length), started from the same path: the difference of the two
  MAPs' ln p, their largest |Δx|, the largest relative difference of the latents' Laplace
  marginal sds (banded selected inverse against the dense inverse), the AAM parameters' mean
  square error at each MAP (the visual predictive mean against the utterance's own), and both
  wall times;
* ``--restarts K``: the MAP restarted from K draws of that Laplace approximation, each
  restart's converged flag, ln p, and distance from the first MAP (Euclidean in the
  whitened coordinates, i.e. in Laplace standard deviations; largest |Δx|; frames moved
  by more than 10⁻³). A unimodal posterior brings every restart back to the same mode.

    PYTHONPATH=. python benchmarks/joint_map.py --model MODEL_DIR \\
        --test-corpus data/dev40 --aam data/train250/aam.npz \\
        [--n-test 8] [--utterances utt0001,utt0003] [--restarts 6] [--khat-draws 200] [--reference] \\
        [--out benchmarks/results/joint_map.json]
    PYTHONPATH=. python benchmarks/joint_map.py --quick   # -> benchmarks/results/quick/joint_map.json
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

from bayes_talk.gp.threads import torch_threads
from bayes_talk.posterior.diagnostics import psis_diagnostics
from bayes_talk.posterior.sampling import visual_predictive
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan
from bayes_talk.synthesis.joint_map import (
    MAP_DTOL,
    MAP_GTOL,
    MAP_LBFGS_ITER,
    MAP_MAX_ITER,
    maximise_utterance,
)
from bayes_talk.synthesis.sequential import synthesize
from benchmarks.common import bench_corpus, bench_model, result_path, write_result


def _map_row(dens: UtteranceDensity, X0: np.ndarray) -> tuple[dict, object]:
    e0, t0 = dens.n_evals, time.perf_counter()
    mp = maximise_utterance(dens, X0)
    row = {"converged": bool(mp.converged), "grad_max": mp.grad_norm, "decrement": mp.decrement,
           "hessian_modified": mp.hessian_modified, "n_iter": mp.n_iter, "log_density": mp.log_density,
           "start_log_density": mp.start_log_density, "density_evals": dens.n_evals - e0,
           "seconds": time.perf_counter() - t0}
    return row, mp


def _dense_reference(dens: UtteranceDensity, X0: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The same MAP by dense linear algebra (the reference the banded solver is measured
    against): L-BFGS whitened by the floored eigen-decomposition of −∇² ln p at the start, then
    scipy's ``trust-exact`` whitened at the L-BFGS point, stopped by the same convergence test.
    Returns (x, ln p, the dense Laplace covariance at x)."""
    from scipy.optimize import minimize

    def whiten(x):
        P = -dens.hessian(x).dense()
        lam, U = np.linalg.eigh(0.5 * (P + P.T))
        lam = np.maximum(np.abs(lam), 1e-8 * max(1.0, float(np.abs(lam).max())))
        return U / np.sqrt(lam), (U / lam) @ U.T, bool(np.linalg.eigvalsh(0.5 * (P + P.T))[0] > 0)

    def done_at(x, g):
        _, cov, pd = whiten(x)
        return np.abs(g).max() <= MAP_GTOL or (pd and 0.5 * g @ cov @ g <= MAP_DTOL)

    x = np.asarray(X0, dtype=np.float64).reshape(-1)
    L, _, _ = whiten(x)
    best = {"f": dens(x)[0], "x": x}

    def neg(z, xs, L):
        xz = xs + L @ z
        f, g = dens(xz)
        if np.isfinite(f) and f > best["f"]:
            best.update(f=f, x=xz, g=g.reshape(-1))
        return (-f, -(L.T @ g.reshape(-1))) if np.isfinite(f) else (np.inf, np.zeros_like(z))

    minimize(neg, np.zeros_like(x), args=(x, L), jac=True, method="L-BFGS-B",
             options={"maxiter": MAP_LBFGS_ITER, "gtol": 1e-12, "ftol": 1e-15, "maxcor": 30})
    xs = best["x"]
    if not done_at(xs, dens(xs)[1].reshape(-1)):
        L, _, _ = whiten(xs)

        def stop(intermediate_result):
            xz = xs + L @ intermediate_result.x
            if done_at(xz, dens(xz)[1].reshape(-1)):
                raise StopIteration

        minimize(neg, np.zeros_like(xs), args=(xs, L), jac=True, method="trust-exact", callback=stop,
                 hess=lambda z, xs, L: -(L.T @ dens.hessian(xs + L @ z).dense() @ L),
                 options={"maxiter": MAP_MAX_ITER, "gtol": 1e-300})
    x = best["x"]
    return x, float(dens(x)[0]), whiten(x)[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=None)
    ap.add_argument("--test-corpus", default=None)
    ap.add_argument("--aam", default=None, help="the training corpus's aam.npz")
    ap.add_argument("--n-test", type=int, default=8)
    ap.add_argument("--utterances", default=None, help="comma-separated names (instead of the first --n-test)")
    ap.add_argument("--restarts", type=int, default=0)
    ap.add_argument("--khat-draws", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reference", action="store_true", help="also the dense reference MAP and Laplace covariance")
    ap.add_argument("--quick", action="store_true", help="the quick model and held-out corpus: 1 utterance, "
                    "1 restart, 50 k-hat draws")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    args.out = result_path("joint_map", args.quick, args.out)
    if args.quick:
        args.n_test, args.restarts, args.khat_draws = 1, 1, 50
    args.model = args.model or bench_model(args.quick)
    args.test_corpus = args.test_corpus or bench_corpus("test", args.quick)
    args.aam = args.aam or bench_corpus("train", args.quick) / "aam.npz"

    from bayes_talk.corpus import load_corpus
    from bayes_talk.pipeline import corpus_front_end, load_trained

    tm = load_trained(args.model)
    model = tm.uncalibrated
    seqs = load_corpus(args.test_corpus, aam=args.aam, cache=False, **corpus_front_end(tm.audio)).sequences
    if args.utterances:
        want = args.utterances.split(",")
        seqs = [s for s in seqs if s.name in want]
    else:
        seqs = seqs[:args.n_test]
    res = {"model": os.path.relpath(Path(args.model).resolve(), HERE.parent),
           "test_corpus": os.path.relpath(Path(args.test_corpus).resolve(), HERE.parent),
           "loadavg_start": os.getloadavg()[0], "utterances": []}
    with torch_threads(1):
        for s in seqs:
            plan = make_plan(model, s.mfcc, s.labels, "frame")
            dens = UtteranceDensity(plan)
            t0 = time.perf_counter()
            X0 = synthesize(model, s.mfcc, s.labels, algorithm="optimise", smoothness="frame").latents
            row = {"name": s.name, "frames": plan.n_frames, "dim": plan.n_frames * plan.latent_dim,
                   "blocks": len(plan.blocks), "algorithm1_seconds": time.perf_counter() - t0}
            m, mp = _map_row(dens, X0)
            row.update(m)
            fac = mp.laplace_factor()
            x = mp.latents.reshape(-1)
            if args.reference:
                t0 = time.perf_counter()
                xr, fr, cov = _dense_reference(dens, X0)
                sd_new = np.sqrt(np.einsum("tii->ti", fac.marginal_covariances()).reshape(-1))
                z_new = visual_predictive(plan, mp.latents[None, None])[0][0, 0]
                z_ref = visual_predictive(plan, xr.reshape(1, 1, plan.n_frames, -1))[0][0, 0]
                row["reference"] = {"seconds": time.perf_counter() - t0, "log_density": fr,
                                    "log_density_difference": mp.log_density - fr,
                                    "latents_max_abs_difference": float(np.abs(xr - x).max()),
                                    "marginal_sd_max_rel_difference": float(np.max(np.abs(sd_new / np.sqrt(np.diag(cov)) - 1))),
                                    "aam_mse_at_map": float(np.mean((z_new - s.aam) ** 2)),
                                    "aam_mse_at_reference_map": float(np.mean((z_ref - s.aam) ** 2))}
            rng = np.random.default_rng(args.seed)
            Z = rng.standard_normal((max(args.khat_draws, args.restarts), x.size))
            if args.khat_draws:
                Zk = Z[:args.khat_draws]
                row["khat"] = psis_diagnostics(dens, x[None] + fac.scale_matvec(Zk.T).T,
                                               -0.5 * np.sum(Zk * Zk, axis=1))["khat"]
            restarts = []
            for k in range(args.restarts):
                r, mk = _map_row(dens, (x + fac.scale_matvec(Z[k])).reshape(plan.n_frames, -1))
                dx = mk.latents - mp.latents
                r.update(dz_norm=float(np.linalg.norm(fac.unscale_matvec(dx.reshape(-1)))),
                         dx_max=float(np.abs(dx).max()),
                         frames_moved=[int(t) for t in np.where(np.abs(dx).max(1) > 1e-3)[0]])
                restarts.append(r)
            if restarts:
                row["restarts"] = restarts
                row["best_restart_gain"] = max(r["log_density"] for r in restarts) - mp.log_density
            print(json.dumps({k: v for k, v in row.items() if k != "restarts"}), flush=True)
            res["utterances"].append(row)
    u = res["utterances"]
    res["summary"] = {"converged": f"{sum(r['converged'] for r in u)}/{len(u)}",
                      "grad_max_max": max(r["grad_max"] for r in u),
                      "seconds_mean": float(np.mean([r["seconds"] for r in u])),
                      "khat": [r.get("khat") for r in u],
                      **({"reference_log_density_difference_max_abs":
                          max(abs(r["reference"]["log_density_difference"]) for r in u),
                          "reference_marginal_sd_max_rel_difference":
                          max(r["reference"]["marginal_sd_max_rel_difference"] for r in u),
                          "reference_seconds_mean": float(np.mean([r["reference"]["seconds"] for r in u])),
                          "same_mode": sum(abs(r["reference"]["log_density_difference"]) < 1e-3 for r in u),
                          "aam_mse_at_map_mean": float(np.mean([r["reference"]["aam_mse_at_map"] for r in u])),
                          "aam_mse_at_reference_map_mean":
                              float(np.mean([r["reference"]["aam_mse_at_reference_map"] for r in u]))}
                         if args.reference else {}),
                      "loadavg_end": os.getloadavg()[0]}
    write_result(args.out, res)
    print(json.dumps(res["summary"]))


if __name__ == "__main__":
    main()
