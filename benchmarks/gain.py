"""Does a quieter recording give another face?

A model (``--model-dir``, a ``bayes-talk train`` output) synthesises each held-out utterance
from its WAV and labels as ``synth`` does (the model's front end, its default posterior, seed
0), and again from the same WAV with its 16-bit samples scaled by each of ``--gains`` dB
(rounded back to 16 bits, as a quieter recording would be). For every gain it reports

* ``trajectory``: the RMS over frames of the change of the synthesised trajectory, over the
  original trajectory's standard deviation, averaged over the AAM parameters (acceptance:
  ≤ 0.02 at -6 and -20 dB);
* ``features``: the same measure of the change of the model's MFCCs (after its level and
  cepstral normalisation).

    python benchmarks/gain.py --model-dir data/model --test data/dev40 --n-test 10
    python benchmarks/gain.py --quick     # the quick model and held-out corpus -> results/quick/
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import soundfile as sf

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bayes_talk.pipeline import load_trained, read_utterance
from bayes_talk.pipeline.front_end import front_end
from benchmarks.common import bench_corpus, bench_model, result_path, write_result

GAINS_DB = (-6.0, -20.0)


def moved(x: np.ndarray, ref: np.ndarray) -> float:
    """RMS over frames of ``x - ref``, over ``ref``'s standard deviation, averaged over columns."""
    sd = ref.std(axis=0)
    keep = sd > 0
    return float(np.mean(np.sqrt(np.mean((x - ref) ** 2, axis=0))[keep] / sd[keep]))


def measure(model_dir: Path, test: Path, n_test: int | None, gains: tuple[float, ...], work: Path) -> dict:
    tm = load_trained(model_dir)
    front = front_end(tm.audio)
    options = {"posterior": "laplace", "seed": 0} if "posterior" in tm.model.synthesis_options else {}
    rows = []
    for wav in sorted((test / "utterances").glob("*.wav"))[:n_test]:
        lab = wav.with_suffix(".lab")
        x, sr = sf.read(str(wav), dtype="int16")
        ref_utt = read_utterance(wav, lab, tm.fps, **front)
        ref = tm.model.predict_dist(ref_utt, **options).mean
        row = {"utterance": wav.stem, "n_frames": int(ref.shape[0])}
        for g in gains:
            p = work / f"{wav.stem}_{g:+.0f}dB.wav"
            sf.write(str(p), np.round(x * 10 ** (g / 20)).astype(np.int16), sr, subtype="PCM_16")
            utt = read_utterance(p, lab, tm.fps, **front)
            out = tm.model.predict_dist(utt, **options).mean
            row[f"{g:+.0f}dB"] = {"trajectory": moved(out, ref), "features": moved(utt.mfcc, ref_utt.mfcc)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    mean = {f"{g:+.0f}dB": {k: float(np.mean([r[f"{g:+.0f}dB"][k] for r in rows])) for k in ("trajectory", "features")}
            for g in gains}
    worst = {f"{g:+.0f}dB": float(max(r[f"{g:+.0f}dB"]["trajectory"] for r in rows)) for g in gains}
    return {"audio": tm.audio.to_dict(), "synthesis": options or "the model's own path", "mean": mean,
            "worst_trajectory": worst, "n_utterances": len(rows), "per_utterance": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--model-dir", default=None, help="a bayes-talk train output (default: the suite's model)")
    ap.add_argument("--test", default=None, help="held-out corpus (default: the suite's)")
    ap.add_argument("--n-test", type=int, default=3, help="first N held-out utterances")
    ap.add_argument("--gains", default=",".join(f"{g:g}" for g in GAINS_DB), help="gains in dB, comma-separated")
    ap.add_argument("--quick", action="store_true", help="the quick model and held-out corpus")
    ap.add_argument("--out", default=None, help="default benchmarks/results/gain.json (--quick: results/quick/)")
    a = ap.parse_args(argv)
    a.out = result_path("gain", a.quick, a.out)
    a.model_dir = Path(a.model_dir or bench_model(a.quick))
    a.test = Path(a.test or bench_corpus("test", a.quick))
    gains = tuple(float(g) for g in a.gains.split(","))
    result = {"model_dir": os.path.relpath(a.model_dir.resolve(), ROOT),
              "test_corpus": os.path.relpath(a.test.resolve(), ROOT), "gains_db": list(gains),
              "metric": "RMS over frames of (quieter - original), over the original's sd, mean over columns"}
    with tempfile.TemporaryDirectory(prefix="bt_gain_") as tmp:
        t0 = time.perf_counter()
        result.update(measure(a.model_dir, a.test, a.n_test, gains, Path(tmp)))
        result["measure_seconds"] = time.perf_counter() - t0
    print(json.dumps({"mean": result["mean"], "worst_trajectory": result["worst_trajectory"]}), flush=True)
    write_result(a.out, result)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
