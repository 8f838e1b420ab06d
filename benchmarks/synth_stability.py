"""Does a default ``synth`` warn on normal utterances, and is its mean stable?

Two acceptance checks on held-out utterances, through ``pipeline.synth`` exactly
as ``bayes-talk synth`` runs it (the model's default posterior, its band calibration, its
post-filter; no video):

* **warnings**: the convergence warnings each synthesis records (``diagnostics.json``
  ``problems``); acceptance: none on 10 held-out utterances;
* **stability**: white noise at −60 dBFS (RMS 10⁻³ of full scale, seeded) added to each
  WAV, the utterance synthesised again with the same labels; the change of the written
  trajectory (``trajectory.npy``, the calibrated predictive mean) at every frame in units
  of the parameter's standard deviation over the held-out corpus's frames (projected on
  the model's AAM);
  acceptance: max over frames and parameters < 0.5.

``--perturbation resample`` instead writes each WAV resampled to 44.1 kHz (the model
resamples it back to its training rate, with a logged warning): a feature change larger
than the noise's, which the −50 dBFS MFCC floor absorbs; it tests whether the joint MAP
lands in the same posterior mode for nearly the same input.

    python benchmarks/synth_stability.py --model-dir MODEL --test data/dev40 --n-test 10 \\
        [--perturbation noise|resample] [--out benchmarks/results/synth_stability.json]
    python benchmarks/synth_stability.py --quick    # the quick model and held-out corpus -> results/quick/

``MODEL`` is a ``bayes-talk train`` output (with its band calibration).
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

from bayes_talk.corpus import load_corpus
from bayes_talk.pipeline import synth
from benchmarks.common import (
    bench_corpus,
    bench_model,
    result_path,
    write_result,
)

#: level of the added white noise, dB relative to full scale (RMS)
NOISE_DBFS = -60.0
#: the rate ``--perturbation resample`` writes
RESAMPLE_HZ = 44100


def _run(model_dir: Path, wav: Path, lab: Path, out: Path) -> tuple[np.ndarray, dict]:
    synth(model_dir, wav, lab, out, video=False)
    diag = json.loads((out / "diagnostics.json").read_text()) if (out / "diagnostics.json").exists() else {}
    return np.load(out / "trajectory.npy"), diag


def _perturbed(wav: Path, y: np.ndarray, sr: int, perturbation: str, rng: np.random.Generator, work: Path) -> Path:
    """The utterance's audio perturbed: −60 dBFS white noise added, or resampled to 44.1 kHz."""
    out = work / f"{wav.stem}_{perturbation}.wav"
    if perturbation == "noise":
        noise = rng.standard_normal(y.shape) * 10 ** (NOISE_DBFS / 20)
        sf.write(str(out), (y + noise).astype(np.float32), sr, subtype="FLOAT")
    else:
        from bayes_talk.features.audio import resample
        sf.write(str(out), resample(y, sr, RESAMPLE_HZ), RESAMPLE_HZ, subtype="FLOAT")
    return out


def measure(model_dir: Path, test: Path, n_test: int, seed: int, work: Path, perturbation: str = "noise") -> dict:
    """The per-utterance warnings and noise shifts (module docstring)."""
    # the held-out faces projected on the model's AAM (the space trajectory.npy is in)
    corpus = load_corpus(test, aam=model_dir / "aam.npz")
    sd = np.vstack([u.aam for u in corpus]).std(0)
    wavs = sorted((test / "utterances").glob("*.wav"))[:n_test]
    rng = np.random.default_rng(seed)
    rows = []
    for wav in wavs:
        lab = wav.with_suffix(".lab")
        y, sr = sf.read(str(wav), dtype="float64")
        t0 = time.perf_counter()
        ref, diag = _run(model_dir, wav, lab, work / f"{wav.stem}_orig")
        changed = _perturbed(wav, y, sr, perturbation, rng, work)
        out, diag_n = _run(model_dir, changed, lab, work / f"{wav.stem}_{perturbation}_out")
        T = min(len(out), len(ref))
        shift = np.abs(out[:T] - ref[:T]) / sd
        frame = int(np.argmax(shift.max(1)))
        inner = diag.get("diagnostics", {})
        rows.append({"utterance": wav.stem, "frames": len(ref), "warnings": diag.get("problems", []),
                     "warnings_with_noise": diag_n.get("problems", []),
                     "khat": inner.get("khat"), "map_converged": inner.get("map_converged"),
                     "map_log_density": [inner.get("map_log_density"),
                                         diag_n.get("diagnostics", {}).get("map_log_density")],
                     "max_shift_sd": float(shift.max()), "frame_of_max_shift": frame,
                     "frames_over_0.5sd": int(np.sum(shift.max(1) >= 0.5)),
                     "seconds": time.perf_counter() - t0})
        print(f"{wav.stem}: warnings {len(rows[-1]['warnings'])}, max shift {shift.max():.3f} sd "
              f"(frame {frame})", flush=True)
    return {"n_utterances": len(rows), "perturbation": perturbation,
            "noise_dbfs": NOISE_DBFS if perturbation == "noise" else None,
            "resample_hz": RESAMPLE_HZ if perturbation == "resample" else None,
            "utterances_with_warnings": sum(bool(r["warnings"]) for r in rows),
            "max_shift_sd": max(r["max_shift_sd"] for r in rows),
            "all_shifts_below_0.5sd": all(r["max_shift_sd"] < 0.5 for r in rows),
            "per_utterance": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--model-dir", default=None, help="a bayes-talk train output")
    ap.add_argument("--test", default=None, help="held-out corpus directory")
    ap.add_argument("--n-test", type=int, default=10, help="first N held-out utterances")
    ap.add_argument("--seed", type=int, default=0, help="seed of the added noise")
    ap.add_argument("--perturbation", choices=("noise", "resample"), default="noise",
                    help="-60 dBFS white noise added, or the WAV resampled to 44.1 kHz")
    ap.add_argument("--quick", action="store_true", help="the quick model and 2 utterances of the quick held-out corpus")
    ap.add_argument("--out", default=None, help="default benchmarks/results/synth_stability.json (--quick: results/quick/)")
    a = ap.parse_args(argv)
    a.out = result_path("synth_stability", a.quick, a.out)
    if a.quick:
        a.n_test = 2
    a.model_dir = a.model_dir or bench_model(a.quick)
    a.test = a.test or bench_corpus("test", a.quick)
    with tempfile.TemporaryDirectory(prefix="bt_stability_") as tmp:
        r = measure(Path(a.model_dir), Path(a.test), a.n_test, a.seed, Path(tmp), a.perturbation)
    r.update(model_dir=Path(a.model_dir).name, test_corpus=Path(a.test).name, seed=a.seed)
    write_result(a.out, r)
    print(json.dumps({k: v for k, v in r.items() if k != "per_utterance"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
