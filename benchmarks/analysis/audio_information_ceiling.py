"""Ceiling of ``benchmarks/audio_information.py`` on a ``--speech vtl`` corpus (issue 25):
how much of the first three AAM parameters the *true* shared articulation explains beyond
the phone labels, i.e. the most the audio could add.

The same regressor and protocol as the benchmark (HistGradientBoostingRegressor defaults,
one thread, GroupKFold(5) by utterance, pooled out-of-fold R²) with the features
``labels`` (one-hot labels of frames t-4..t+4) and ``labels+true`` (the same plus the
face's jaw, aperture, spread and protrusion of frames t-2..t+2, recomputed from the cached
tract exactly as the build drove the face). Also the in-sample R² of a linear fit of each
AAM parameter on the shared articulators, on the face-only components (upper-lip raise,
lower-lip tuck, brow, blink, pose) and on both: which part of the face the audio can
share at all.

    PYTHONPATH=. .venv/bin/python benchmarks/analysis/audio_information_ceiling.py CORPUS_DIR
        [--out benchmarks/results/audio_information_ceiling.json]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from audio_information import CONTEXT, _stack

SHARED = ("jaw", "aperture", "spread", "protrusion")
SHARED_CONTEXT = 2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("corpus")
    ap.add_argument("--out", default=str(Path(__file__).parents[1] / "results" / "audio_information_ceiling.json"))
    args = ap.parse_args()
    import soundfile as sf
    from sklearn.ensemble import HistGradientBoostingRegressor
    from sklearn.linear_model import LinearRegression
    from sklearn.metrics import r2_score
    from sklearn.model_selection import GroupKFold
    from threadpoolctl import threadpool_limits

    from bayes_talk.data.articulatory import face_articulators, synthesize_articulatory
    from bayes_talk.corpus import load_corpus
    from bayes_talk.data.face import face_trajectories
    from bayes_talk.data.face.coarticulation import ARTICULATORS
    from bayes_talk.data.labels import read_lab
    from bayes_talk.data.phones import PHONE_INDEX, PHONES
    from bayes_talk.base.files import write_json

    c = load_corpus(args.corpus)
    if c.manifest.get("speech") != "vtl":
        raise SystemExit(f"{args.corpus}: expected a --speech vtl corpus, found speech={c.manifest.get('speech')!r}")
    seed = int(c.manifest["seed"])
    lab, true, only, y, g = [], [], [], [], []
    for i, u in enumerate(c.sequences):
        iv, T = read_lab(u.meta["label_path"]), len(u.labels)
        wav, sr = sf.read(u.audio_path, dtype="int16")
        res = synthesize_articulatory(iv, len(wav), sr, (seed, i, 3), sizes=c.manifest["articulatory"]["variation"])
        if not np.array_equal(res.audio, wav):
            raise RuntimeError(f"{u.audio_path}: the re-synthesised audio differs from the corpus")
        tr = face_trajectories(iv, T, fps=25.0, rng=np.random.default_rng([seed, i, 1]),
                               given=face_articulators(res.tract, T, 25.0))
        onehot = np.zeros((T, len(PHONES)))
        onehot[np.arange(T), [PHONE_INDEX[p] for p in u.labels]] = 1.0
        lab.append(_stack(onehot, CONTEXT))
        a = tr.articulators
        true.append(_stack(a[:, [ARTICULATORS.index(n) for n in SHARED]], SHARED_CONTEXT))
        only.append(np.column_stack([a[:, [ARTICULATORS.index("raise"), ARTICULATORS.index("tuck")]],
                                     tr.brow, tr.blink, tr.pose]))
        y.append(u.aam[:, :3])
        g.append(np.full(T, i))
    lab, true, only, y, g = map(np.concatenate, (lab, true, only, y, g))
    names = ["aam0", "aam1", "aam2"]
    out: dict = {"corpus_n_utterances": len(c.sequences), "n_frames": len(y),
                 "linear_in_sample_r2": {}, "r2": {}}
    for fname, X in {"shared articulators": true, "face-only": only, "both": np.hstack([true, only])}.items():
        out["linear_in_sample_r2"][fname] = {n: float(LinearRegression().fit(X, y[:, j]).score(X, y[:, j]))
                                             for j, n in enumerate(names)}
    with threadpool_limits(1):
        for fname, X in {"labels": lab, "labels+true": np.hstack([lab, true])}.items():
            pred = np.zeros_like(y)
            for trn, te in GroupKFold(n_splits=5).split(X, y, g):
                for j in range(3):
                    m = HistGradientBoostingRegressor(random_state=seed).fit(X[trn], y[trn, j])
                    pred[te, j] = m.predict(X[te])
            out["r2"][fname] = {n: float(r2_score(y[:, j], pred[:, j])) for j, n in enumerate(names)}
            print(fname, {k: round(v, 3) for k, v in out["r2"][fname].items()}, flush=True)
    gain = [out["r2"]["labels+true"][n] - out["r2"]["labels"][n] for n in names]
    out["ceiling_gain_aam_mean3"] = float(np.mean(gain))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_json(args.out, out)
    print(f"ceiling of the AAM gain (true articulators): {np.mean(gain):+.3f} -> {args.out}")


if __name__ == "__main__":
    main()
