"""``make demo``: the main job on the built-in corpus, end to end.

1. build (or reuse) a small built-in corpus in ``OUT/corpus`` with the speech generator
   :data:`DEMO_SPEECH` (:func:`demo_speech`), and say which generator the corpus has;
2. hold out the last utterances, train the default model of ``train`` on the rest (the
   switching SGPDM with right-context phone states and ±2 frames of audio, ``DEMO_MODEL``)
   with its observation term (bayes_talk.synthesis.face_noise) fitted on 20 % of the training
   utterances held out, as ``train`` does;
3. synthesise the held-out sentences from their audio and phone labels: the default, what
   ``synth`` writes (the whole-utterance synthesis posterior, Laplace, with the observation
   term), the same posterior raw (the GP predictive alone), and the paper's Algorithm 1
   (sequential optimisation) and Algorithm 2 (sequential prediction) with the same model and
   the paper's zero-phase 4 Hz post-filter (deena2010 §4.2.3), beside Brand's Voice
   Puppetry, the per-phone mean face and the ridge / MLP regressions on label and MFCC
   context windows; the default's 90 % band coverage, in all and over the silences;
4. print AMSE and ACC against the ground truth and write ``OUT/metrics.json``, with the
   floor and the ceiling (:mod:`bayes_talk.evaluation.ceiling`): ``zero`` (a still face)
   and ``oracle`` (the generator's mean given the true timing; ``DEMO_ORACLE_DRAWS`` = 8
   draws here to keep the demo short, 32 in ``evaluate``; its AMSE/NMSE are bias-corrected
   for the finite number of draws), and every method's fraction of the achievable gain
   ``(zero - method) / (zero - oracle)`` on AMSE and on NMSE;
5. write ``OUT/side_by_side.mp4``: ground truth | synthesis (posterior mean), with the speech,
   each side captioned (``DEMO_VIDEO_LABELS``);
6. show the uncertainty of that utterance's posterior (bayes_talk.pipeline.uncertainty_outputs):
   ``OUT/bands.png`` (the first AAM parameters: mean, 50 %/90 % bands, ground truth),
   ``OUT/uncertainty.mp4`` (mean face | per-pixel standard deviation of rendered draws) and
   ``OUT/posterior.nc`` (ArviZ InferenceData with the truth as observed data).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from bayes_talk.pipeline import DEFAULT_MODEL

DEMO_UTTERANCES = 60
#: The speech generator of the demo's corpus, chosen by ``benchmarks/audio_information.py``
#: (docs/benchmarks.md): on the articulatory corpus (``vtl``) the MFCCs add R²
#: 0.060 over the phone labels on the first three AAM parameters, on the espeak corpus
#: -0.006 (40 utterances): only there does the audio tell the face anything the labels do
#: not. Without VocalTractLab installed the demo falls back to ``espeak`` and says so.
DEMO_SPEECH = "vtl"
DEMO_HELD_OUT = 6
LOWPASS_HZ = 4.0
DEMO_ORACLE_DRAWS = 8
#: the captions above the two sides of side_by_side.mp4
DEMO_VIDEO_LABELS = ("ground truth", "synthesis (mean)")
#: the default model of ``train`` (bayes_talk.pipeline.DEFAULT_MODEL): right-context phone states,
#: the phonetic-context view as the visual mean function
DEMO_MODEL = DEFAULT_MODEL


def demo_speech(preferred: str = DEMO_SPEECH) -> tuple[str, str]:
    """(generator, why): ``preferred`` if it can run here, else ``espeak`` with the reason
    (``vtl`` needs the optional VocalTractLab package)."""
    from bayes_talk.corpus.build import SPEECH_GENERATORS

    if preferred not in SPEECH_GENERATORS:
        raise ValueError(f"demo speech generator: expected one of {sorted(SPEECH_GENERATORS)}, found {preferred!r}")
    if preferred == "vtl":
        from bayes_talk.data.articulatory import require_vtl

        try:
            require_vtl()
        except RuntimeError as exc:
            return "espeak", f"falling back to espeak: {exc}"
        return "vtl", ("VocalTractLab, one vocal tract for the voice and the face: the audio carries "
                       "information about the face beyond the labels (benchmarks/audio_information.py)")
    return preferred, SPEECH_GENERATORS[preferred]


def run_demo(out: Path, n_utterances: int = DEMO_UTTERANCES, n_test: int = DEMO_HELD_OUT, seed: int = 0,
             workers: int = 1) -> int:
    """Build a small corpus, train, synthesise and score held-out utterances into ``out`` (``make demo``,
    ``workers`` = 2 processes); returns the exit status."""
    from bayes_talk.base.executor import executor_for
    from bayes_talk.base.video import side_by_side, write_video
    from bayes_talk.corpus import build_corpus, load_corpus
    from bayes_talk.data.phones import SILENCE
    from bayes_talk.estimators.baselines import REGISTRY
    from bayes_talk.estimators.calibrated import calibrate_model
    from bayes_talk.estimators.registry import make_estimator
    from bayes_talk.evaluation.ceiling import corpus_generator
    from bayes_talk.evaluation.metrics import acc, amse
    from bayes_talk.pipeline import DEFAULT_CALIBRATED_MODEL, aam_offset
    from bayes_talk.synthesis.sequential import lowpass

    out = Path(out)
    t0 = time.time()
    cdir = out / "corpus"
    if not (cdir / "manifest.json").exists():
        speech, why = demo_speech()
        print(f"[demo] building a {n_utterances}-utterance corpus in {cdir} with speech generator "
              f"{speech!r} ({why}) ...", flush=True)
        build_corpus(cdir, n_utterances=n_utterances, seed=seed, n_workers=workers, speech=speech)
    corpus = load_corpus(cdir, n_workers=workers)
    generator = corpus_generator(corpus.manifest)
    print(f"[demo] speech generator of the corpus: {generator}", flush=True)
    seqs = list(corpus.sequences)
    train, test = seqs[:-n_test], seqs[-n_test:]
    print(f"[demo] corpus ready ({len(train)} train / {len(test)} test utterances, "
          f"{corpus.sequences[0].aam.shape[1]} AAM parameters) after {time.time() - t0:.0f} s", flush=True)

    t1 = time.time()
    with executor_for(None, workers) as ex:   # as `bayes-talk train` does
        model = calibrate_model(make_estimator(DEMO_MODEL, seed=seed), train, DEFAULT_CALIBRATED_MODEL,
                                seed=seed, executor=ex)
    train_s = time.time() - t1
    print(f"[demo] trained {len(model.models_)} state models ({DEMO_MODEL}) and fitted the observation term "
          f"on {model.face_noise_.info['n_utterances']} held-out training utterances, "
          f"calibrated model: {DEFAULT_CALIBRATED_MODEL}, in {train_s:.0f} s", flush=True)

    truth = [s.aam for s in test]
    rows: dict[str, dict] = {}
    kept: dict[str, list] = {}  # predicted means, for the gain fractions
    t2 = time.time()
    raw = [model.predict_dist(s, posterior="laplace", seed=seed, face_noise=False) for s in test]
    post = [model.observe(p, s.labels) for p, s in zip(raw, test)]   # what `synth` writes
    for s, p in zip(test, post):   # the posterior's warnings, as synth
        for w in p.warnings:
            print(f"[demo] WARNING {s.name}: {w}", flush=True)
    default = f"{DEMO_MODEL}-posterior (default)"
    inside = [(t >= lo) & (t <= hi) for t, (lo, hi) in zip(truth, (p.interval(0.9) for p in post))]
    silent = [np.asarray([lab == SILENCE for lab in s.labels]) for s in test]
    rows[default] = {
        "amse": amse(truth, [p.mean for p in post]), "acc": acc(truth, [p.mean for p in post]),
        "synth_frames_per_second": sum(s.n_frames for s in test) / (time.time() - t2),
        "map_converged": sum(p.map.converged for p in raw),
        "coverage_90": float(np.concatenate(inside).mean()),
        "coverage_90_silence": float(np.concatenate([h[m] for h, m in zip(inside, silent)]).mean())}
    kept[default] = [p.mean for p in post]
    rows[f"{DEMO_MODEL}-posterior, raw (the GP predictive alone)"] = {
        "amse": amse(truth, [p.mean for p in raw]), "acc": acc(truth, [p.mean for p in raw])}
    kept[f"{DEMO_MODEL}-posterior, raw (the GP predictive alone)"] = [p.mean for p in raw]
    for alg in ("optimise", "predict"):
        t2 = time.time()
        res = [model.synthesize(s.mfcc, s.labels, algorithm=alg) for s in test]
        fps = sum(s.n_frames for s in test) / (time.time() - t2)
        smooth = [lowpass(r.mean, LOWPASS_HZ) for r in res]
        name = f"{DEMO_MODEL}-{alg} (Algorithm {1 if alg == 'optimise' else 2}) +{LOWPASS_HZ:g}Hz"
        rows[name] = {"amse": amse(truth, smooth), "acc": acc(truth, smooth), "synth_frames_per_second": fps}
        kept[name] = smooth
    for name in ("voice-puppetry", "hmm-mean", "context-ridge", "context-mlp"):
        ref = REGISTRY[name]().fit(train)
        pred = [ref.predict(s) for s in test]
        rows[name] = {"amse": amse(truth, pred), "acc": acc(truth, pred)}
        kept[name] = pred
    _add_ceiling(rows, kept, train, test, seed)

    w = max(len(n) for n in rows) + 2
    print(f"\n{'method':<{w}}{'AMSE':>10}{'NMSE':>8}{'ACC':>8}{'gain AMSE':>10}{'gain NMSE':>10}{'frames/s':>10}")
    for name, r in rows.items():
        fps = r.get("synth_frames_per_second")
        gains = "".join("" if r.get(k) is None else f"{r[k]:>10.3f}" for k in ("gain_amse", "gain_nmse"))
        gains = gains or " " * 20
        nmse = "" if r.get("nmse") is None else f"{r['nmse']:>8.3f}"
        print(f"{name:<{w}}{r['amse']:>10.4f}{nmse or ' ' * 8}{r['acc']:>8.3f}{gains}"
              f"{'' if fps is None else f'{fps:10.0f}'}")
    print("(AMSE: average mean squared error of the AAM parameters over the held-out utterances; NMSE: "
          "the same divided by each parameter's ground-truth variance; ACC: average correlation "
          "coefficient of predicted and true parameter tracks (deena2010 §5); higher is better only for ACC)")
    print("(gain = (zero - method) / (zero - oracle): 0 = a still face, 1 = the generator's own mean "
          f"given the true timing; oracle from {DEMO_ORACLE_DRAWS} draws, bias-corrected)")
    var_gt = float(np.mean([t.var(0).mean() for t in truth]))
    print(f"(mean ground-truth variance per AAM parameter: {var_gt:.4f})")
    print(f"(the default's 90 % band holds the truth on {rows[default]['coverage_90']:.3f} of the entries, "
          f"{rows[default]['coverage_90_silence']:.3f} of those in silence)")

    # side-by-side video of the first held-out utterance
    s, r = test[0], post[0]
    offset = aam_offset(type("C", (), {"sequences": train})())
    gt_frames = corpus.aam.render(s.aam + s.meta.get("aam_mean", offset))
    syn_frames = corpus.aam.render(r.mean + offset)
    video = write_video(out / "side_by_side.mp4",
                        side_by_side(gt_frames, syn_frames, labels=DEMO_VIDEO_LABELS), corpus.fps,
                        audio_path=s.audio_path, overwrite=True)
    shown = _show_uncertainty(out, r, s, corpus, offset)
    summary = {"corpus": str(cdir), "speech": generator, "n_train": len(train), "n_test": len(test),
               "calibrated_model": DEFAULT_CALIBRATED_MODEL, "train_seconds": train_s,
               "n_state_models": len(model.models_), "methods": rows, "video": str(video),
               "uncertainty": {k: str(v) for k, v in shown.items()},
               "total_seconds": time.time() - t0}
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(summary, indent=1))
    tmp.replace(out / "metrics.json")
    print(f"\n[demo] wrote {video} (ground truth | synthesis) and {out / 'metrics.json'}; "
          f"total {time.time() - t0:.0f} s")
    print(f"[demo] the uncertainty of {s.name}: {shown['plot']} (mean, 50 %/90 % bands, truth), "
          f"{shown['uncertainty']} (mean face | per-pixel sd), {shown['posterior']} (az.from_netcdf)")
    return 0


def _show_uncertainty(out: Path, r, s, corpus, offset: np.ndarray) -> dict[str, Path]:
    """bands.png, uncertainty.mp4 and posterior.nc of the posterior ``r`` of utterance ``s``."""
    from bayes_talk.base.video import write_video
    from bayes_talk.pipeline.uncertainty_outputs import (
        plot_bands,
        uncertainty_frames,
        write_posterior_netcdf,
    )

    return {"plot": plot_bands(out / "bands.png", r, s.aam, fps=corpus.fps,
                                    title=f"{s.name}: posterior ({r.method}) mean, 50 %/90 % bands, truth"),
            "uncertainty": write_video(out / "uncertainty.mp4", uncertainty_frames(corpus.aam, r, offset),
                                             corpus.fps, audio_path=s.audio_path, overwrite=True),
            "posterior": write_posterior_netcdf(out / "posterior.nc", r, s.aam)}


def _add_ceiling(rows: dict, kept: dict, train: list, test: list, seed: int) -> None:
    """Add the ``zero`` and ``oracle`` rows and every kept method's gain fractions."""
    from bayes_talk.estimators.ceiling import OracleModel, ZeroModel
    from bayes_talk.evaluation.ceiling import score_with_ceiling

    zero = ZeroModel().fit(train)
    kept["zero"] = [zero.predict(s) for s in test]
    oracle = OracleModel(n_draws=DEMO_ORACLE_DRAWS, seed=seed)
    out = [oracle.moments(s) for s in test]
    kept["oracle"] = [o[0] for o in out]
    scores = score_with_ceiling([s.aam for s in test], kept, {"oracle": [o[2] for o in out]})
    for name, sc in scores.items():
        rows.setdefault(name, {}).update(sc)
