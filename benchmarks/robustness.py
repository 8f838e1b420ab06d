"""Robustness of synthesis to how the audio was recorded (issue 12).

Trains a model on a training corpus (``bayes-talk train``), then for each held-out
utterance synthesises (``pipeline.synth``'s path: read_utterance with the model's recorded
sample rate and cepstral normalisation, then the model's MAP synthesis) from

* the original WAV, and from variants of it: -6 dB, +6 dB, resampled to 16 kHz and
  44.1 kHz, stereo with one silent channel, and all-zero (silent) audio,

and reports the RMS difference of each variant's AAM trajectory from the original's,
averaged over utterances, and its ratio to the silent audio's difference (acceptance:
every ratio below 0.1). With ``--frontends new,before`` the same is measured for the front end
before issue 12 (no cepstral normalisation, mel bands up to sr/2, no resampling: a model
trained with ``cmvn="off", fmax=None`` and the audio read at its own rate; stereo is
downmixed by the new rule in both, so that row does not show the old channel average).

    python benchmarks/robustness.py --train data/v1/train250 --test data/v1/heldout40 \
        --frontends new,before --json benchmarks/results/robustness.json
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import soundfile as sf

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bayes_talk.features.audio import resample
from bayes_talk.features.mfcc import FLOOR_DBFS, FMAX_HZ
from bayes_talk.base.files import write_json
from bayes_talk.pipeline import load_trained, read_utterance, train

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


def synth_mean(tm, wav: Path, lab: Path, frontend: str) -> np.ndarray:
    if frontend == "new":
        utt = read_utterance(wav, lab, tm.fps, sample_rate=tm.audio.sample_rate, cmvn=tm.audio.cmvn,
                             fmax=tm.audio.fmax, floor_dbfs=tm.audio.floor_dbfs)
    else:  # before issue 12: the file's own rate, mel bands to sr/2, no normalisation
        utt = read_utterance(wav, lab, tm.fps, sample_rate=None, cmvn="off", fmax=None)
    res = tm.uncalibrated.synthesize(utt.mfcc, utt.labels, algorithm="optimise")
    return np.asarray(res.mean)


def measure(model_dir: Path, test: Path, n_test: int | None, frontend: str, work: Path) -> dict:
    tm = load_trained(model_dir)
    wavs = sorted((test / "utterances").glob("*.wav"))[:n_test]
    diffs: dict[str, list[float]] = {c: [] for c in CONDITIONS}
    for wav in wavs:
        lab = wav.with_suffix(".lab")
        y, sr = sf.read(str(wav), dtype="float64")
        ref = synth_mean(tm, wav, lab, frontend)
        for name, (yy, rr) in variants(y, sr).items():
            p = work / f"{wav.stem}_{name}.wav"
            sf.write(str(p), yy.astype(np.float32), rr, subtype="FLOAT")
            try:
                out = synth_mean(tm, p, lab, frontend)
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
    ap.add_argument("--train", default="data/v1/train250", help="training corpus")
    ap.add_argument("--test", default="data/v1/heldout40", help="held-out corpus")
    ap.add_argument("--model", default="ssgpdm-phone", help="model kind")
    ap.add_argument("--n-test", type=int, default=None, help="first N held-out utterances (default all)")
    ap.add_argument("--frontends", default="new",
                    help="comma-separated: new (this front end), before (before issue 12)")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/robustness.json"))
    a = ap.parse_args(argv)
    result = {"train_corpus": a.train, "test_corpus": a.test, "model": a.model, "algorithm": "optimise",
              "metric": "RMS over frames and AAM parameters of (variant trajectory - original trajectory), "
                        "mean over utterances", "frontends": {}}
    with tempfile.TemporaryDirectory(prefix="bt_robust_") as tmp:
        tmp = Path(tmp)
        known = {"new": ("new", "mean"), "before": ("before_issue12", "off")}
        runs = [known[f] for f in a.frontends.split(",")]
        for label, cm in runs:
            t0 = time.perf_counter()
            mdir = train(a.train, a.model, tmp / f"model_{cm}", cmvn=cm,
                         fmax=FMAX_HZ if label == "new" else None, floor_dbfs=FLOOR_DBFS if label == "new" else None)
            t1 = time.perf_counter()
            work = tmp / f"audio_{cm}"
            work.mkdir()
            r = measure(mdir, Path(a.test), a.n_test, "new" if label == "new" else "old", work)
            r.update(cmvn=cm, train_seconds=t1 - t0, measure_seconds=time.perf_counter() - t1)
            result["frontends"][label] = r
            print(label, json.dumps(r["ratio_to_silent"]), flush=True)
    write_json(a.json, result)
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
