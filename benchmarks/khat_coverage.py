"""Does the warning's k̂ predict where the calibrated bands fail?

A default ``synth`` warns when the Laplace posterior's PSIS k̂ lies above the largest k̂ of
the held-out utterances its band calibration was fitted on
(:meth:`bayes_talk.calibration.bands.BandCalibration.domain`). A warning means
something only if the calibrated bands of the utterances it flags are worse than those of
the utterances it lets through. This script measures that on held-out utterances, through
``pipeline.synth`` exactly as ``bayes-talk synth`` runs it (no video):

* per utterance: frames, k̂, the MAP's log density per frame, whether it warned, the calibrated 50 % / 90 % coverage of the
  held-out face (``bands.npz`` against the utterance's AAM parameters projected on the
  model's AAM, the space of ``trajectory.npy``) and the squared error of the mean in units
  of the parameter's variance (NMSE-like);
* over utterances: the Spearman correlation of k̂ with the 90 % coverage error
  |cov90 − 0.9| and with the coverage itself, and the pooled coverage of the flagged and
  of the unflagged utterances (frames × parameters pooled).

    python benchmarks/khat_coverage.py --model-dir MODEL --test data/dev40 --first 10 --n-test 20 \\
        --out benchmarks/results/khat_coverage.json
    python benchmarks/khat_coverage.py --quick     # -> benchmarks/results/quick/khat_coverage.json

``MODEL`` is a ``bayes-talk train`` output (with its band calibration). ``--snr-db S`` adds
white noise (seeded) at S dB below the utterance's RMS before synthesis: a recording unlike
the training audio, to see which statistic moves when the bands do fail.
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
from scipy.stats import spearmanr

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bayes_talk.corpus import load_corpus
from bayes_talk.pipeline import synth
from benchmarks.common import (
    QUICK_TEST_UTTERANCES,
    bench_corpus,
    bench_model,
    result_path,
    write_result,
)


def _inside(truth: np.ndarray, bands, level: int) -> np.ndarray:
    """(T, D) booleans: the truth inside the central ``level`` % band."""
    lo, hi = bands[f"lower{level}"], bands[f"upper{level}"]
    if lo.shape != truth.shape:
        raise ValueError(f"bands.npz lower{level} has shape {lo.shape}, the held-out face {truth.shape}")
    return (truth >= lo) & (truth <= hi)


def _noisy(wav: Path, snr_db: float, rng, out: Path) -> Path:
    """``wav`` with white noise ``snr_db`` dB below its RMS, written to ``out``."""
    y, sr = sf.read(str(wav), dtype="float64")
    noise = rng.standard_normal(y.shape) * np.sqrt(np.mean(y ** 2)) * 10 ** (-snr_db / 20)
    sf.write(str(out), (y + noise).astype(np.float32), sr, subtype="FLOAT")
    return out


def measure(model_dir: Path, test: Path, first: int, n_test: int, work: Path,
            snr_db: float | None = None, seed: int = 0) -> dict:
    """Per-utterance k̂, warning and calibrated coverage, and their association (module docstring)."""
    corpus = {u.name: u for u in load_corpus(test, aam=model_dir / "aam.npz")}
    var = np.vstack([u.aam for u in corpus.values()]).var(0)
    wavs = sorted((test / "utterances").glob("*.wav"))[first:first + n_test]
    rows, hits = [], {True: {50: [], 90: []}, False: {50: [], 90: []}}
    rng = np.random.default_rng(seed)
    for wav in wavs:
        t0 = time.perf_counter()
        out = work / wav.stem
        audio = wav if snr_db is None else _noisy(wav, snr_db, rng, work / f"{wav.stem}_noisy.wav")
        synth(model_dir, audio, wav.with_suffix(".lab"), out, video=False)
        diag = json.loads((out / "diagnostics.json").read_text())
        truth = corpus[wav.stem].aam
        mean = np.load(out / "trajectory.npy")
        with np.load(out / "bands.npz") as b:
            inside = {lv: _inside(truth, b, lv) for lv in (50, 90)}
        flagged = bool(diag.get("problems"))
        for lv in (50, 90):
            hits[flagged][lv].append(inside[lv].ravel())
        inner = diag.get("diagnostics", {})
        lp = inner.get("map_log_density")
        rows.append({"utterance": wav.stem, "frames": len(truth), "khat": inner.get("khat"),
                     "map_log_density_per_frame": None if lp is None else lp / len(truth),
                     "warned": flagged, "warnings": diag.get("problems", []),
                     "coverage_50": float(inside[50].mean()), "coverage_90": float(inside[90].mean()),
                     "nmse": float((((mean - truth) ** 2) / var).mean()),
                     "seconds": round(time.perf_counter() - t0, 1)})
        r = rows[-1]
        print(f"{wav.stem}: k̂ {r['khat']:.2f} lp/T {r['map_log_density_per_frame']:.1f} warned {flagged} cov50 {r['coverage_50']:.3f} "
              f"cov90 {r['coverage_90']:.3f} nmse {r['nmse']:.3f}", flush=True)
    k = np.array([r["khat"] for r in rows], float)
    c90 = np.array([r["coverage_90"] for r in rows])
    nmse = np.array([r["nmse"] for r in rows])

    def rho(a, b):
        s = spearmanr(a, b)
        return {"rho": float(s.statistic), "p": float(s.pvalue)}

    pooled = {("flagged" if f else "unflagged"): {
        "n_utterances": len(hits[f][90]),
        **{f"coverage_{lv}": (float(np.concatenate(hits[f][lv]).mean()) if hits[f][lv] else None)
           for lv in (50, 90)}} for f in (True, False)}
    return {"n_utterances": len(rows), "first": first, "snr_db": snr_db,
            "spearman_khat_vs_abs_cov90_error": rho(k, np.abs(c90 - 0.9)),
            "spearman_khat_vs_cov90": rho(k, c90), "spearman_khat_vs_nmse": rho(k, nmse),
            "spearman_khat_vs_frames": rho(k, [r["frames"] for r in rows]),
            "pooled_coverage": pooled, "per_utterance": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--model-dir", default=None, help="a bayes-talk train output")
    ap.add_argument("--test", default=None, help="held-out corpus directory")
    ap.add_argument("--first", type=int, default=0, help="index of the first held-out utterance")
    ap.add_argument("--n-test", type=int, default=20, help="number of held-out utterances")
    ap.add_argument("--snr-db", type=float, default=None, help="add white noise this many dB below the RMS")
    ap.add_argument("--seed", type=int, default=0, help="seed of the added noise")
    ap.add_argument("--quick", action="store_true", help="the quick model and held-out corpus")
    ap.add_argument("--out", default=None, help="default benchmarks/results/khat_coverage.json (--quick: results/quick/)")
    a = ap.parse_args(argv)
    a.out = result_path("khat_coverage", a.quick, a.out)
    if a.quick:
        a.n_test = QUICK_TEST_UTTERANCES
    a.model_dir = a.model_dir or bench_model(a.quick)
    a.test = a.test or bench_corpus("test", a.quick)
    with tempfile.TemporaryDirectory(prefix="bt_khat_") as tmp:
        r = measure(Path(a.model_dir), Path(a.test), a.first, a.n_test, Path(tmp), a.snr_db, a.seed)
    r.update(model_dir=Path(a.model_dir).name, test_corpus=Path(a.test).name)
    write_result(a.out, r)
    print(json.dumps({k: v for k, v in r.items() if k != "per_utterance"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
