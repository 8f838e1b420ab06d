"""Where the calibrated posterior loses log score to the constant-band control (issue 27).

Synthesises held-out utterances with a trained model's default posterior (raw, then its
band calibration, then the constant-band control), and breaks the mixture NLPD down by AAM
parameter and by switching state; then scores variance-shrunk variants of the raw mixture
(v'^k = (1 − λ) v^k + λ v̄_d) calibrated on the first half of the utterances and scored on
the second half (a design probe on development data, not a result).

    python benchmarks/analysis/predictive_density.py MODEL data/dev40 --json /tmp/density.json
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bayes_talk.corpus import load_corpus
from bayes_talk.pipeline import load_trained
from bayes_talk.calibration.bands import BandCalibration
from bayes_talk.posterior.sampling import sample_synthesis


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("test")
    ap.add_argument("--n-test", type=int, default=40)
    ap.add_argument("--json", default="/tmp/density.json")
    a = ap.parse_args(argv)
    tm = load_trained(a.model_dir)
    cal: BandCalibration = tm.calibration
    corpus = list(load_corpus(a.test, aam=Path(a.model_dir) / "aam.npz", cmvn=tm.audio.cmvn))[: a.n_test]
    raws, truths = [], []
    for u in corpus:
        raws.append(sample_synthesis(tm.uncalibrated, u.mfcc, u.labels, method="laplace", n_draws=64, seed=0,
                                     log_warnings=False))
        truths.append(u.aam)
        print(f"{u.name}: k̂ {raws[-1].diagnostics.get('khat'):.2f}", flush=True)
    out: dict = {}
    # the shipped calibration's stages one at a time (fitted on the training hold-out)
    from bayes_talk.calibration.bands import _constant_band, _shrunk
    n_all = sum(z.size for z in truths)
    stage = {
        "stages_0_1_2 (shipped)": lambda r: cal.apply(r),
        "stages_0_1 (no level map)": lambda r: replace(cal, level_raw=None).apply(r),
        "control_gaussian (no stages 1-2)": lambda r: _constant_band(_shrunk(r, cal.mean_scale), cal.control_var),
        "control (shipped)": lambda r: cal.control_result(r),
    }
    out["nlpd_by_stage"] = {k: float(sum(-f(r).logpdf(z).sum() for r, z in zip(raws, truths)) / n_all)
                            for k, f in stage.items()}
    print(json.dumps(out["nlpd_by_stage"], indent=1), flush=True)
    by_state: dict[str, list] = defaultdict(lambda: [0.0, 0.0, 0.0])
    per_param = {"calibrated": [], "control": [], "raw": []}
    for r, z in zip(raws, truths):
        c, k = cal.apply(r), cal.control_result(r)
        lc, lk, lr = -c.logpdf(z), -k.logpdf(z), -r.logpdf(z)
        per_param["calibrated"].append(lc.sum(0))
        per_param["control"].append(lk.sum(0))
        per_param["raw"].append(lr.sum(0))
        for seg, key in zip(r.segments, r.model_states):
            acc = by_state[" ".join(key)]
            acc[0] += lc[seg.start:seg.stop].sum()
            acc[1] += lk[seg.start:seg.stop].sum()
            acc[2] += lc[seg.start:seg.stop].size
    n = sum(z.size for z in truths)
    for key, v in per_param.items():
        tot = np.sum(v, 0)
        out[f"nlpd_{key}"] = float(tot.sum() / n)
        out[f"nlpd_{key}_per_param"] = (tot / (n / truths[0].shape[1])).round(3).tolist()
    worst = sorted(by_state.items(), key=lambda kv: -(kv[1][0] - kv[1][1]))[:15]
    out["states_worst_vs_control"] = [{"state": s, "nlpd_cal": a_ / e, "nlpd_control": b / e, "entries": int(e)}
                                      for s, (a_, b, e) in worst]
    # variance shrinkage towards the per-parameter mean component variance, fit on half A
    half = len(raws) // 2
    A, B = list(zip(raws[:half], truths[:half])), list(zip(raws[half:], truths[half:]))
    vbar = np.mean(np.concatenate([r.draw_var.reshape(-1, r.n_dims) for r, _ in A]), 0)
    probe = {}
    for lam in (0.0, 0.25, 0.5, 0.75, 1.0):
        def blend(r, lam=lam):
            return replace(r, draw_var=(1 - lam) * r.draw_var + lam * vbar)
        cb = BandCalibration.fit([blend(r) for r, _ in A], [z for _, z in A], method="laplace", with_control=False)
        nl = sum(float(-cb.apply(blend(r)).logpdf(z).sum()) for r, z in B) / sum(z.size for _, z in B)
        cv = np.mean([np.mean((z >= lo) & (z <= hi)) for r, z in B for lo, hi in [cb.apply(blend(r)).interval(0.9)]])
        probe[f"{lam:g}"] = {"nlpd_B": nl, "cov90_B": float(cv)}
        print(f"λ={lam}: NLPD(B) {nl:.4f} cov90 {cv:.3f}", flush=True)
    cb = BandCalibration.fit([r for r, _ in A], [z for _, z in A], method="laplace")
    probe["control_B"] = sum(float(-cb.control_result(r).logpdf(z).sum()) for r, z in B) / sum(z.size for _, z in B)
    out["variance_shrinkage_probe"] = probe
    # linear pool of the calibrated posterior with its constant-band control (fit on A, score on B)
    pool = {}
    for w in (0.0, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0):
        tot = 0.0
        for r, z in B:
            lc, lk = cb.apply(r).logpdf(z), cb.control_result(r).logpdf(z)
            with np.errstate(divide="ignore"):
                tot += float(-np.logaddexp(np.log1p(-w) + lc, np.log(w) + lk).sum())
        pool[f"{w:g}"] = tot / sum(z.size for _, z in B)
        print(f"pool w={w}: NLPD(B) {pool[f'{w:g}']:.4f}", flush=True)
    out["linear_pool_probe"] = pool
    Path(a.json).write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if not k.endswith("per_param")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
