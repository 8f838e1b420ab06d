"""Robustness of synthesis to how the audio was recorded.

A model (``--model-dir``, a ``bayes-talk train`` output; or one trained here on ``--train``
with ``--model`` kind) synthesises each held-out utterance (``pipeline.read_utterance`` with
the model's recorded sample rate and cepstral normalisation, then the model's MAP synthesis)
from

* the original WAV, and from variants of it: -6 dB, +6 dB, resampled to 16 kHz and
  44.1 kHz, stereo with one silent channel, and all-zero (silent) audio,

and reports the RMS difference of each variant's AAM trajectory from the original's,
averaged over utterances, and its ratio to the silent audio's difference (acceptance:
every ratio below 0.1).

    python benchmarks/robustness.py --train data/train250 --test data/heldout40 \
        [--model ssgpdm-phone] [--out benchmarks/results/robustness.json]
    python benchmarks/robustness.py --model-dir MODEL --test data/heldout40
    python benchmarks/robustness.py --quick     # the quick model and held-out corpus -> results/quick/
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

from bayes_talk.features.audio import resample
from bayes_talk.pipeline import load_trained, read_utterance, train
from benchmarks.common import bench_corpus, bench_model, result_path, write_result

CONDITIONS = ("minus6dB", "plus6dB", "sr16000", "sr44100", "stereo_one_silent", "silent")


def variants(y: np.ndarray, sr: int) -> dict[str, tuple[np.ndarray, int]]:
    """The recording variants of mono ``y`` at ``sr`` Hz: name -> (samples, rate)."""
    return {
        "minus6dB": (y * 10 ** (-6 / 20), sr),
        "plus6dB": (y * 10 ** (6 / 20), sr),
        "sr16000": (resample(y, sr, 16000), 16000),
        "sr44100": (resample(y, sr, 44100), 44100),
        "stereo_one_silent": (np.stack([y, np.zeros_like(y)], axis=1), sr),
        "silent": (np.zeros_like(y), sr),
    }


def synth_mean(tm, wav: Path, lab: Path) -> np.ndarray:
    utt = read_utterance(wav, lab, tm.fps, sample_rate=tm.audio.sample_rate, cmvn=tm.audio.cmvn,
                         fmax=tm.audio.fmax, floor_dbfs=tm.audio.floor_dbfs, level_dbfs=tm.audio.level_dbfs)
    res = tm.uncalibrated.synthesize(utt.mfcc, utt.labels, algorithm="optimise")
    return np.asarray(res.mean)


def measure(model_dir: Path, test: Path, n_test: int | None, work: Path) -> dict:
    tm = load_trained(model_dir)
    wavs = sorted((test / "utterances").glob("*.wav"))[:n_test]
    diffs: dict[str, list[float]] = {c: [] for c in CONDITIONS}
    for wav in wavs:
        lab = wav.with_suffix(".lab")
        y, sr = sf.read(str(wav), dtype="float64")
        ref = synth_mean(tm, wav, lab)
        for name, (yy, rr) in variants(y, sr).items():
            p = work / f"{wav.stem}_{name}.wav"
            sf.write(str(p), yy.astype(np.float32), rr, subtype="FLOAT")
            try:
                out = synth_mean(tm, p, lab)
            except ValueError as exc:  # e.g. 16 kHz audio without resampling: not a frame grid
                diffs[name].append(float("nan"))
                print(f"{wav.stem} {name}: {exc}", file=sys.stderr)
                continue
            T = min(len(out), len(ref))
            diffs[name].append(float(np.sqrt(np.mean((out[:T] - ref[:T]) ** 2))))
    rms = {c: float(np.nanmean(v)) if np.isfinite(v).any() else None for c, v in diffs.items()}
    ratio = {c: (rms[c] / rms["silent"] if rms[c] is not None and rms["silent"] else None)
             for c in CONDITIONS if c != "silent"}
    return {"rms_difference_from_original": rms, "ratio_to_silent": ratio,
            "all_below_0.1": all(r is not None and r < 0.1 for r in ratio.values()),
            "n_utterances": len(wavs), "per_utterance": diffs}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--model-dir", default=None, help="a bayes-talk train output (default: the suite's model)")
    ap.add_argument("--train", default=None, help="train a --model on this corpus instead of --model-dir")
    ap.add_argument("--model", default="ssgpdm-phone", help="model kind trained on --train")
    ap.add_argument("--test", default=None, help="held-out corpus (default: the suite's)")
    ap.add_argument("--n-test", type=int, default=None, help="first N held-out utterances (default all)")
    ap.add_argument("--quick", action="store_true", help="the quick model and held-out corpus")
    ap.add_argument("--out", default=None, help="default benchmarks/results/robustness.json (--quick: results/quick/)")
    a = ap.parse_args(argv)
    a.out = result_path("robustness", a.quick, a.out)
    if a.quick or a.model_dir is None and a.train is None:
        a.model_dir = a.model_dir or bench_model(a.quick)
    a.test = a.test or bench_corpus("test", a.quick)
    result = {"model_dir": None if a.model_dir is None else os.path.relpath(Path(a.model_dir).resolve(), ROOT),
              "train_corpus": None if a.model_dir else a.train, "model": None if a.model_dir else a.model,
              "test_corpus": os.path.relpath(Path(a.test).resolve(), ROOT), "algorithm": "optimise",
              "metric": "RMS over frames and AAM parameters of (variant trajectory - original trajectory), "
                        "mean over utterances"}
    with tempfile.TemporaryDirectory(prefix="bt_robust_") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        mdir = Path(a.model_dir) if a.model_dir else train(a.train, a.model, tmp / "model")
        t1 = time.perf_counter()
        work = tmp / "audio"
        work.mkdir()
        r = measure(mdir, Path(a.test), a.n_test, work)
        r.update(train_seconds=None if a.model_dir else t1 - t0, measure_seconds=time.perf_counter() - t1)
        result.update(r)
        print(json.dumps(r["ratio_to_silent"]), flush=True)
    write_result(a.out, result)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
