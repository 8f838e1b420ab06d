"""Benchmark: how much the audio tells about the face beyond the phone labels.

A difference in differences. On an espeak corpus and a ``--speech vtl`` (VocalTractLab)
corpus of the same sentences and seed, a non-linear regressor (scikit-learn's
HistGradientBoostingRegressor, 5-fold GroupKFold by utterance, pooled out-of-fold R²)
predicts each face target per frame from

* ``labels``: one-hot phone labels of frames t-4..t+4, and
* ``labels+mfcc``: the same plus the 20 MFCCs of frames t-4..t+4;

the *gain* is R²(labels+mfcc) - R²(labels). Targets: the first three AAM parameters (per
utterance mean removed, as ``load_corpus`` gives them) and the face's lip aperture, jaw and
protrusion articulators (recomputed exactly from the corpus's random streams and checked
against its landmarks). Acceptance: the mean gain over the first three AAM parameters is
at least 0.03 larger on the articulatory corpus.

    PYTHONPATH=. .venv/bin/python benchmarks/audio_information.py [--n 60] [--seed 0]
        [--workdir DIR] [--workers 1] [--out benchmarks/results/audio_information.json]
    PYTHONPATH=. .venv/bin/python benchmarks/audio_information.py --quick   # 6 utterances -> results/quick/

``--workdir`` keeps the two corpora (reused when their manifests match, and then their
fits too, in ``audio_information_fit.json`` beside each manifest); VocalTractLab
must be installed (``pip install 'bayes_talk[articulatory]'``).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bayes_talk.base.files import write_json
from bayes_talk.corpus import build_corpus, load_corpus
from bayes_talk.data.phones import PHONE_INDEX, PHONES
from benchmarks.common import result_path, write_result

CONTEXT = 4
#: keywords of the regressor beyond its defaults (the quick mode's fewer boosting iterations)
REGRESSOR: dict = {}
ARTICULATORS = ("aperture", "jaw", "protrusion")


def _stack(x: np.ndarray, k: int) -> np.ndarray:
    """(T, D) -> (T, (2k+1) D): frames t-k..t+k, edges repeated."""
    pad = np.pad(x, ((k, k), (0, 0)), mode="edge")
    return np.concatenate([pad[j:j + len(x)] for j in range(2 * k + 1)], axis=1)


def _build(root: Path, n: int, seed: int, speech: str, workers: int) -> Path:
    m = root / "manifest.json"
    if m.exists():
        man = json.loads(m.read_text())
        same = (man.get("n_utterances"), man.get("seed"), man.get("speech", "espeak")) == (n, seed, speech)
        if same and speech == "vtl":   # and the same generator (version and sizes)
            from bayes_talk.corpus.build import _articulatory_manifest

            same = man.get("articulatory") == _articulatory_manifest()
        if same:
            return root
    return build_corpus(root, n_utterances=n, seed=seed, speech=speech, force=True, n_workers=workers)


def _articulators(corpus, seed: int, speech: str) -> list[np.ndarray]:
    """Per utterance (T, 3): the face's aperture, jaw, protrusion, recomputed from the
    build's streams (the espeak face from the phones; the vtl face from the cached tract)
    and checked against the stored landmarks."""
    import soundfile as sf

    from bayes_talk.data.articulatory import face_articulators, synthesize_articulatory
    from bayes_talk.data.face import ARTICULATORS as ALL
    from bayes_talk.data.face import face_landmarks, face_trajectories
    from bayes_talk.data.labels import read_lab

    out = []
    for i, u in enumerate(corpus.sequences):
        iv = read_lab(u.meta["label_path"])
        T = len(u.labels)
        given = None
        if speech == "vtl":
            y, sr = sf.read(u.audio_path, dtype="int16")
            res = synthesize_articulatory(iv, len(y), sr, (seed, i, 3),
                                          sizes=corpus.manifest["articulatory"]["variation"])
            if not np.array_equal(res.audio, y):
                raise RuntimeError(f"{u.audio_path}: the re-synthesised audio differs from the corpus")
            given = face_articulators(res.tract, T, 25.0)
        if i == 0:
            lm = face_landmarks(iv, T, fps=25.0, image_size=int(corpus.manifest["image_size"]),
                                rng=np.random.default_rng([seed, i, 1]), given=given)
            if not np.allclose(lm, u.landmarks):
                raise RuntimeError(f"{u.name}: recomputed landmarks differ from the corpus")
        tr = face_trajectories(iv, T, fps=25.0, rng=np.random.default_rng([seed, i, 1]), given=given)
        out.append(tr.articulators[:, [ALL.index(a) for a in ARTICULATORS]])
    return out


def _fit_all(feats: dict, y: np.ndarray, groups: np.ndarray, names: list[str], seed: int,
             res: dict) -> None:
    """Out-of-fold predictions of every target from every feature set; pooled R² into res."""
    from sklearn.ensemble import HistGradientBoostingRegressor
    from sklearn.metrics import r2_score
    from sklearn.model_selection import GroupKFold

    for fname, X in feats.items():
        pred = np.zeros_like(y)
        for tr, te in GroupKFold(n_splits=5).split(X, y, groups):
            for j in range(y.shape[1]):
                m = HistGradientBoostingRegressor(random_state=seed, **REGRESSOR).fit(X[tr], y[tr, j])
                pred[te, j] = m.predict(X[te])
        res[fname] = {n: float(r2_score(y[:, j], pred[:, j])) for j, n in enumerate(names)}
        print(fname, {k: round(v, 3) for k, v in res[fname].items()}, flush=True)


def _r2(corpus, arts: list[np.ndarray], seed: int) -> dict:
    lab, mf, y, groups = [], [], [], []
    for g, (u, a) in enumerate(zip(corpus.sequences, arts, strict=True)):
        onehot = np.zeros((len(u.labels), len(PHONES)))
        onehot[np.arange(len(u.labels)), [PHONE_INDEX[p] for p in u.labels]] = 1.0
        lab.append(_stack(onehot, CONTEXT))
        mf.append(_stack(u.mfcc, CONTEXT))
        y.append(np.concatenate([u.aam[:, :3], a], axis=1))
        groups.append(np.full(len(u.labels), g))
    lab, mf, y, groups = map(np.concatenate, (lab, mf, y, groups))
    feats = {"labels": lab, "labels+mfcc": np.concatenate([lab, mf], axis=1)}
    names = ["aam0", "aam1", "aam2", *ARTICULATORS]
    res: dict = {}
    from threadpoolctl import threadpool_limits

    # one OpenMP thread: on a shared, oversubscribed machine spinning OpenMP teams were
    # measured to stall the fits for minutes
    with threadpool_limits(1):
        _fit_all(feats, y, groups, names, seed, res)
    gain = {n: res["labels+mfcc"][n] - res["labels"][n] for n in names}

    gain["aam_mean3"] = float(np.mean([gain[n] for n in names[:3]]))
    return {"r2": res, "gain": gain, "n_frames": len(y), "n_utterances": len(corpus.sequences)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", default=None, help="keep (and reuse) the two corpora here")
    ap.add_argument("--workers", type=int, default=1, help="corpus-build workers (VocalTractLab "
                    "costs ~1.5 CPU-s per second of audio)")
    ap.add_argument("--quick", action="store_true", help="6 utterances, 20 boosting iterations")
    ap.add_argument("--out", default=None, help="default benchmarks/results/audio_information.json (--quick: results/quick/)")
    args = ap.parse_args()
    args.out = result_path("audio_information", args.quick, args.out)
    if args.quick:
        args.n = 6
        REGRESSOR["max_iter"] = 20
    import sklearn

    with tempfile.TemporaryDirectory() as td:
        work = Path(args.workdir) if args.workdir else Path(td)
        out: dict = {"n_utterances": args.n, "seed": args.seed, "context_frames": CONTEXT,
                     "regressor": "HistGradientBoostingRegressor (defaults"
                                  + (f"; {REGRESSOR}" if REGRESSOR else "") + "), GroupKFold(5) by utterance",
                     "load_start": [round(x, 2) for x in os.getloadavg()], "corpora": {}}
        for speech in ("espeak", "vtl"):
            t0 = time.perf_counter()
            root = _build(work / speech, args.n, args.seed, speech, args.workers)
            t_build = time.perf_counter() - t0
            corpus = load_corpus(root)
            # the fits of an unchanged corpus are reused from --workdir (keyed by its manifest)
            key = hashlib.sha256((root / "manifest.json").read_bytes()
                                 + f"|{CONTEXT}|{args.seed}|{sklearn.__version__}|{REGRESSOR}".encode()).hexdigest()
            saved = root / "audio_information_fit.json"
            old = json.loads(saved.read_text()) if saved.exists() else {}
            if old.get("key") == key:
                r = dict(old["result"], reused_fit=True)
            else:
                arts = _articulators(corpus, args.seed, speech)
                t0 = time.perf_counter()
                r = _r2(corpus, arts, args.seed)
                r.update(fit_s=round(time.perf_counter() - t0, 1),
                         aam_params=int(corpus.manifest["aam"]["n_params"]))
                write_json(saved, {"key": key, "result": r})
            r["build_s"] = round(t_build, 1)
            if speech == "vtl":
                out["variation"] = corpus.manifest["articulatory"]["variation"]
            out["corpora"][speech] = r
            print(speech, json.dumps(r["gain"], indent=None))
        d = out["corpora"]["vtl"]["gain"]["aam_mean3"] - out["corpora"]["espeak"]["gain"]["aam_mean3"]
        out["difference_in_gain_aam_mean3"] = float(d)
        out["accepted"] = bool(d >= 0.03)
        out["load_end"] = [round(x, 2) for x in os.getloadavg()]
    write_result(args.out, out)
    print(f"difference in AAM gain (vtl - espeak): {d:+.3f} (accept >= 0.03) -> {args.out}")


if __name__ == "__main__":
    from bayes_talk.base.executor import interruptible

    # `kill` stops the worker processes too, not only this one
    interruptible(main)
