"""A linear pool of the calibrated posterior and the constant Gaussian, weighted by log score (issue 27).

The predictive (1 − w)·p_cal + w·N(m, v_d): p_cal the default posterior after its band
calibration, N(m, v_d) the constant Gaussian around the calibrated mean with the control's
variance (no coverage stages). w is fitted by log score on the calibration's training
hold-out (20 % of the training utterances, synthesised by a model trained on the other
80 %, as ``train`` does), globally and per AAM parameter; the pool is then scored on a
held-out corpus with a model trained on all utterances (its shipped calibration).

    python benchmarks/analysis/predictive_pool.py MODEL data/train250 data/dev40 --json out.json

MODEL is ``bayes-talk train data/train250 --out MODEL`` (the default family).
"""
import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bayes_talk.corpus import load_corpus
from bayes_talk.estimators.registry import make_estimator
from bayes_talk.pipeline import load_trained
from bayes_talk.calibration.bands import (
    BandCalibration,
    _constant_band,
    _shrunk,
    split_for_calibration,
)
from bayes_talk.posterior.sampling import sample_synthesis


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("train")
    ap.add_argument("test")
    ap.add_argument("--json", default="predictive_pool.json")
    a = ap.parse_args(argv)
    t0 = time.time()
    tm = load_trained(a.model_dir)
    train = list(load_corpus(a.train, cmvn=tm.audio.cmvn))
    dev = list(load_corpus(a.test, aam=Path(a.model_dir) / "aam.npz", cmvn=tm.audio.cmvn))
    fit_idx, held_idx = split_for_calibration(len(train), 0.2, 0)
    sub = make_estimator("ssgpdm-phone-ctx-mean")
    with ProcessPoolExecutor(2) as ex:
        sub.fit([train[i] for i in fit_idx], executor=ex)
    print("sub fitted", time.time() - t0, flush=True)
    held = [(sample_synthesis(sub, train[i].mfcc, train[i].labels, method="laplace", n_draws=64, seed=0,
                              log_warnings=False), train[i].aam) for i in held_idx]
    cal = BandCalibration.fit([r for r, _ in held], [z for _, z in held], method="laplace")
    print("held-out synthesised", time.time() - t0, flush=True)
    def parts(cal, r, z):
        lc = cal.apply(r).logpdf(z)
        lk = _constant_band(_shrunk(r, cal.mean_scale), cal.control_var).logpdf(z)
        return lc, lk
    hp = [parts(cal, r, z) for r, z in held]
    grid = np.round(np.linspace(0, 1, 21), 2)
    def score(P, w):
        n = sum(lc.size for lc, _ in P)
        with np.errstate(divide="ignore"):
            return sum(float(-np.logaddexp(np.log1p(-w) + lc, np.log(w) + lk).sum()) for lc, lk in P) / n
    held_scores = {float(w): score(hp, w) for w in grid}
    w_star = min(held_scores, key=held_scores.get)
    # per-parameter weights
    D = held[0][1].shape[1]
    def score_d(P, w, d):
        n = sum(lc.shape[0] for lc, _ in P)
        with np.errstate(divide="ignore"):
            return sum(float(-np.logaddexp(np.log1p(-w) + lc[:, d], np.log(w) + lk[:, d]).sum()) for lc, lk in P) / n
    w_d = np.array([min(grid, key=lambda w: score_d(hp, w, d)) for d in range(D)])
    shipped = tm.calibration
    devp = []
    for u in dev:
        r = sample_synthesis(tm.uncalibrated, u.mfcc, u.labels, method="laplace", n_draws=64, seed=0, log_warnings=False)
        devp.append(parts(shipped, r, u.aam))
    n = sum(lc.size for lc, _ in devp)
    with np.errstate(divide="ignore"):
        per_d = sum(float(-np.logaddexp(np.log1p(-w_d) + lc, np.log(w_d) + lk).sum()) for lc, lk in devp) / n
    out = {"held_out_scores": held_scores, "w_star": w_star, "w_per_param": w_d.tolist(),
           "dev_nlpd_posterior_calibrated": score(devp, 0.0), "dev_nlpd_constant_gaussian": score(devp, 1.0),
           "dev_nlpd_pool_w_star": score(devp, w_star), "dev_nlpd_pool_w_per_param": per_d,
           "dev_nlpd_pool_grid": {float(w): score(devp, w) for w in grid[::4]},
           "seconds": time.time() - t0}
    Path(a.json).write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "held_out_scores"}, indent=1))
    return 0

if __name__ == "__main__":
    sys.exit(main())
