"""Where the raw posterior's predictive variance comes from, against the error it should cover (issue 27).

For each utterance of a corpus, the model's raw (uncalibrated) Laplace synthesis posterior
(``predict_dist(..., "laplace")``, what ``synth --raw-bands`` writes) is a mixture over the
latent draws x⁽ᵏ⁾ of Gaussians N(μ(x⁽ᵏ⁾), σ²(x⁽ᵏ⁾)/w²). Its variance per entry is

    Var = E_k[σ²(x⁽ᵏ⁾)/w²]  +  Var_k[μ(x⁽ᵏ⁾)]
          (the GP's own      (the spread of the latent
           predictive)        posterior, pushed through μ)

(``SynthesisResult.gp_var`` and ``var − gp_var``). Printed and written per AAM parameter:
the mean squared error of the mixture mean, both parts, their ratio, the coverage of the
central 90 % band, and the share of the squared error that is each utterance's mean error
(an utterance-level offset, e.g. a head-pose offset: Σ_u T_u ē_u² / Σ e²). Run on held-out sentences and on training sentences to see whether
the bands are too narrow on new sentences only:

    python benchmarks/analysis/raw_variance_decomposition.py --model-dir MODEL --corpus data/dev40 \\
        --n 10 --json benchmarks/results/raw_variance_decomposition.json

``MODEL`` is a ``bayes-talk train`` output; the corpus is projected on its AAM.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from bayes_talk.corpus import load_corpus
from bayes_talk.base.files import write_json
from bayes_talk.pipeline.trained import load_trained


def decompose(model_dir: Path, corpus_dir: Path, n: int, seed: int = 0) -> dict:
    """The per-parameter decomposition (module docstring) over the first ``n`` utterances."""
    tm = load_trained(model_dir)
    corpus = list(load_corpus(corpus_dir, aam=model_dir / "aam.npz"))[:n]
    err, gp, spread, inside, offset = [], [], [], [], []
    for u in corpus:
        r = tm.uncalibrated.predict_dist(u, "laplace", seed=seed)
        err.append((u.aam - r.mean) ** 2)
        offset.append(len(u.aam) * (u.aam - r.mean).mean(0) ** 2)
        gp.append(r.gp_var)
        spread.append(r.var - r.gp_var)
        lo, hi = r.interval(0.9)
        inside.append((u.aam >= lo) & (u.aam <= hi))
    err, gp, spread, inside = (np.vstack(a) for a in (err, gp, spread, inside))
    var = gp + spread
    offset = np.sum(offset, axis=0)
    used = var.mean(0) > 0                       # parameters the model predicts at all
    return {
        "n_utterances": len(corpus), "n_frames": int(err.shape[0]),
        "per_param": {"mse": err.mean(0).tolist(), "gp_var": gp.mean(0).tolist(),
                      "latent_spread_var": spread.mean(0).tolist(),
                      "mse_over_var": (err.mean(0) / np.where(used, var.mean(0), np.nan)).tolist(),
                      "coverage_90": inside.mean(0).tolist(),
                      "utterance_mean_share": (offset / np.maximum(err.sum(0), 1e-300)).tolist()},
        "pooled": {"mse_over_var": float(err[:, used].sum() / var[:, used].sum()),
                   "latent_spread_share": float(spread[:, used].sum() / var[:, used].sum()),
                   "coverage_90": float(inside[:, used].mean()),
                   "utterance_mean_share": float(offset[used].sum() / err[:, used].sum())},
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model-dir", required=True, help="a bayes-talk train output")
    ap.add_argument("--corpus", action="append", required=True,
                    help="corpus directory (repeat for several, e.g. held-out and training)")
    ap.add_argument("--n", type=int, default=10, help="first N utterances of each corpus")
    ap.add_argument("--json", default=None, help="write the result here")
    a = ap.parse_args(argv)
    out = {"command": "python benchmarks/analysis/raw_variance_decomposition.py "
                      + " ".join(argv if argv is not None else sys.argv[1:]),
           "model_dir": Path(a.model_dir).name, "corpora": {}}
    for c in a.corpus:
        r = decompose(Path(a.model_dir), Path(c), a.n)
        out["corpora"][Path(c).name] = r
        print(f"{Path(c).name}: {json.dumps(r['pooled'])}", flush=True)
    if a.json:
        write_json(a.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
