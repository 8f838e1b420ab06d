"""Two routes to a raw 90 % band that covers 0.85-0.95 on new sentences, measured (issue 27, session 15).

The raw (uncalibrated) Laplace synthesis posterior of the default model covers 0.72 at 90 %
on the development sentences, and 93 % of its variance is the visual GPs' own predictive
variance (``raw_variance_decomposition.py``). Two questions, on the first ``--n`` utterances
of a corpus:

``tempered``
    Does correcting the over-counted audio evidence widen the bands enough? The synthesis
    density multiplies the per-frame audio predictives p(y_t | x_t) and so treats the test
    frames' audio as independent given the latents; the exact joint predictive over the
    utterance's frames counts less evidence. As a stand-in, the audio terms are raised to a
    power η ≤ 1 (ln p = η Σ_t ln p(y_t | x_t) + dynamics + entry + smoothness), an in-process
    patch of the density's audio rows (``joint._Terms.audio_grad``; nothing else changes), and
    the raw decomposition is taken per η.
``scale``
    How much larger would the visual GPs' variance have to be? A Gaussian band with variance
    c·σ²_GP + (the latent spread) per entry, around the posterior mean, for several c: its
    90 % coverage and NLPD. c = the training sentences' MSE/var (1.49, session 14) is what a
    noise level honest on the training data -- the most a latent-integrating model could
    learn from them -- would give.

    python benchmarks/analysis/raw_band_routes.py tempered --model-dir MODEL --corpus data/dev40 \\
        --n 10 --eta 1,0.3,0.1,0.03 --json benchmarks/results/raw_band_tempered_dev_s15.json
    python benchmarks/analysis/raw_band_routes.py scale --model-dir MODEL --corpus data/dev40 \\
        --n 10 --json benchmarks/results/raw_band_variance_scale_dev_s15.json

``MODEL`` is a ``bayes-talk train --no-calibrate-bands`` output (the raw posterior is the
same with or without the calibration).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import norm

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from raw_variance_decomposition import decompose

from bayes_talk.corpus import load_corpus
from bayes_talk.base.files import write_json
from bayes_talk.pipeline.trained import load_trained

SCALES = (1.0, 1.49, 2.0, 2.5, 3.0, 3.35, 4.0, 5.0)


@contextlib.contextmanager
def tempered_audio(eta: float):
    """Inside the block, the synthesis density's audio terms are η · ln p(y_t | x_t) (and
    their gradients η · ∂/∂x): an in-process patch of ``joint._Terms.audio_grad``, restored
    on exit. Everything that builds an :class:`UtteranceDensity` inside the block (the Laplace
    posterior, ``evaluate`` run in this process with ``--executor local``) sees it."""
    from bayes_talk.synthesis import joint

    original = joint._Terms.audio_grad

    def audio_grad(self, R, k):
        ll, gx = original(self, R, k)
        return eta * ll, eta * gx

    joint._Terms.audio_grad = audio_grad
    try:
        yield
    finally:
        joint._Terms.audio_grad = original


def tempered(model_dir: Path, corpus_dir: Path, n: int, etas: list[float]) -> dict:
    """The raw decomposition with the audio terms raised to each power η (module docstring)."""
    out = {}
    for eta in etas:
        with tempered_audio(eta):
            r = decompose(model_dir, corpus_dir, n)
        pp = r["per_param"]
        used = np.array(pp["gp_var"]) > 0
        summary = {k: v for k, v in r.items() if not isinstance(v, dict)}
        summary.update(r["pooled"])
        summary.update({"mse_mean": float(np.mean(np.array(pp["mse"])[used])),
                        "gp_var_mean": float(np.mean(np.array(pp["gp_var"])[used])),
                        "spread_var_mean": float(np.mean(np.array(pp["latent_spread_var"])[used]))})
        out[str(eta)] = summary
        print(eta, json.dumps(summary), flush=True)
    return out


def variance_scale(model_dir: Path, corpus_dir: Path, n: int) -> dict:
    """90 % coverage and NLPD of a Gaussian band with variance c·σ²_GP + spread, per c."""
    tm = load_trained(model_dir)
    err, gp, spread = [], [], []
    for u in list(load_corpus(corpus_dir, aam=model_dir / "aam.npz"))[:n]:
        r = tm.uncalibrated.predict_dist(u, "laplace", seed=0)
        err.append(u.aam - r.mean)
        gp.append(r.gp_var)
        spread.append(r.var - r.gp_var)
    err, gp, spread = (np.vstack(a) for a in (err, gp, spread))
    used = (gp + spread).mean(0) > 0                  # parameters the model predicts
    e, g, s = err[:, used], gp[:, used], spread[:, used]
    z = norm.ppf(0.95)
    out = {}
    for c in SCALES:
        v = c * g + s
        out[str(c)] = {"cov90_gauss": float(np.mean(np.abs(e) <= z * np.sqrt(v))),
                       "nlpd_gauss": float(np.mean(0.5 * np.log(2 * np.pi * v) + 0.5 * e**2 / v))}
        print(c, out[str(c)], flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("route", choices=("tempered", "scale"))
    ap.add_argument("--model-dir", type=Path, required=True)
    ap.add_argument("--corpus", type=Path, required=True)
    ap.add_argument("--n", type=int, default=10)
    ap.add_argument("--eta", default="1,0.3,0.1,0.03", help="powers of the audio terms (tempered)")
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args(argv)
    settings = {"route": args.route, "model": args.model_dir.name, "corpus": args.corpus.name, "n": args.n}
    if args.route == "tempered":
        settings["eta"] = [float(e) for e in args.eta.split(",")]
        result = tempered(args.model_dir, args.corpus, args.n, settings["eta"])
    else:
        settings["scales"] = list(SCALES)
        result = variance_scale(args.model_dir, args.corpus, args.n)
    write_json(args.json, {"settings": settings, "results": result})
    return 0


if __name__ == "__main__":
    sys.exit(main())
