"""From a corpus to a trained model directory, and from WAV + labels to a talking face.

This module is above ~400 lines because ``train`` and ``synth`` share the model bundle
(descriptor, audio settings, calibration, aligner) and its checks; splitting them would
split one file format across modules.

The data flow of the command line (``bayes-talk train`` / ``bayes-talk synth``):

    corpus dir ──load_corpus──▶ Utterances (MFCC, AAM params, frame labels)
              ──fit──▶ model (switching SGPDM with VLMM or phone states, or the 2009 SGPLVM)
    WAV + .lab/.TextGrid ──read_utterance──▶ Utterance without visual features
              ──synthesize──▶ AAM trajectory + predictive variance ──AAM.render──▶ frames ──▶ MP4

A model directory holds ``bayes_talk_model.json`` (what kind of model, feature settings,
the AAM offset), the model's own JSON + NPZ files, and a copy of the corpus AAM
(``aam.json`` + ``aam.npz``) so that synthesis can render without the corpus.
"""
from __future__ import annotations

import inspect
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bayes_talk.bundle import DESCRIPTOR, DESCRIPTOR_FORMAT, DESCRIPTOR_VERSION
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.registry import DEFAULT_MODEL, ESTIMATORS, make_estimator
from bayes_talk.files import check_format, write_json, write_npy, write_npz
from bayes_talk.synthesis.defaults import DEFAULT_METHOD, check_method

log = logging.getLogger(__name__)


def model_kinds() -> tuple[str, ...]:
    """The families ``train`` fits and ``synth`` runs: every registered estimator with a
    predictive distribution that is a method, not an evaluation's floor or ceiling."""
    return tuple(name for name, (cls, _) in ESTIMATORS.items() if cls.has_distribution() and not cls.reference)


#: :func:`model_kinds` when this module was imported (``train --model`` choices)
MODEL_KINDS = model_kinds()
#: fraction of the training utterances ``train`` holds out for the band calibration by default
DEFAULT_CALIBRATION = 0.2
_DEFAULT = object()


def read_utterance(wav: str | os.PathLike, labels: str | os.PathLike, fps: float = 25.0, *,
                   sample_rate: int | None = None, cmvn: str = "off", tier: str | None = None,
                   fmax: float | None = None, floor_dbfs: float | None = None) -> Utterance:
    """MFCCs and frame labels of a WAV and its HTK .lab or Praat TextGrid.

    ``sample_rate``: resample the audio to it (the model's training rate; one log line);
    ``cmvn``: the model's cepstral normalisation (:func:`bayes_talk.audio.cmvn`); ``tier``:
    the TextGrid tier holding the phones; ``fmax``: the model's mel filterbank edge (None:
    sr/2, the front end of models trained before it was recorded); ``floor_dbfs``: its
    absolute mel-power floor (None: none, likewise). Raises ValueError
    naming both files when the labels and the audio disagree in length by more than two
    frames.
    """
    from bayes_talk.audio import cmvn as _cmvn
    from bayes_talk.data.checks import check_audio_vs_labels
    from bayes_talk.data.labels import frame_labels, read_labels
    from bayes_talk.features.mfcc import frame_count, load_wav, mfcc

    wav, labels = Path(wav), Path(labels)
    y, sr = load_wav(wav, sample_rate)
    intervals = read_labels(labels, tier=tier)
    check_audio_vs_labels(wav, labels, y.size / sr, intervals[-1][1])
    T = frame_count(y.size, sr, fps)
    feats = _cmvn(mfcc(y, sr, T, fps=fps, where=str(wav), fmax=fmax, floor_dbfs=floor_dbfs), cmvn)
    return Utterance(wav.stem, feats, None, frame_labels(intervals, T, fps), audio_path=wav)


def new_model(kind: str, **overrides):
    """An untrained model of the given kind (see :data:`MODEL_KINDS`)."""
    if kind in model_kinds():
        return make_estimator(kind, **overrides)
    raise ValueError(f"unknown model kind {kind!r}; choose one of {', '.join(model_kinds())}")


def fit_model(model, train: list[Utterance], workers: int = 1, executor=None, scheduler: str | None = None):
    """Fit, training the switching model's states through ``executor`` (bayes_talk.executor:
    "local", "processes", "dask" or an ``Executor``, left open; None: ``workers`` processes,
    or this process when ``workers`` is 1, the default; ``scheduler``: a running dask scheduler), with a
    progress bar of states done / total on a terminal (bayes_talk.progress). The model
    does not depend on the executor."""
    from bayes_talk.executor import executor_for
    from bayes_talk.progress import ProgressMapper

    if "executor" not in inspect.signature(model.fit).parameters:
        return model.fit(train)
    with executor_for(executor, workers, scheduler) as ex:
        return model.fit(train, executor=ProgressMapper(ex, "training states", "state"))


def train(corpus_dir: str | os.PathLike, kind: str, out_dir: str | os.PathLike, workers: int = 1,
          force: bool = False, holdout: int | None = None,
          holdout_list: str | os.PathLike | None = None, cmvn: str = "mean", fmax: float | None = _DEFAULT,
          floor_dbfs: float | None = _DEFAULT,
          alignment: bool = True, executor=None, scheduler: str | None = None,
          calibrate_bands: float | None = None, **overrides) -> Path:
    """Train a model of ``kind`` on a corpus and save it to ``out_dir``.

    Every utterance is used unless some are held out: ``holdout`` = N, the corpus's last N
    utterances (corpus order), or ``holdout_list``, a file naming them one a line (see
    :func:`select_holdout`). The descriptor records the held-out names (``held_out``).

    ``cmvn``: per-utterance cepstral normalisation (bayes_talk.audio; "mean" by default);
    ``fmax``: mel filterbank edge (default ``features.mfcc.FMAX_HZ``; None: sr/2, as before).
    ``floor_dbfs``: absolute mel-power floor (default ``features.mfcc.FLOOR_DBFS``; None: none, as before).
    The bundle records the audio front end (sample rate, MFCC settings, ``cmvn``, feature
    statistics) and ends with ``bundle_manifest.json``, the SHA-256 of every file, written
    last (bayes_talk.bundle).

    ``alignment``: also fit the aligner / phone recogniser (docs/alignment.md) into the
    same directory, so that ``synth`` runs from a transcript or from audio alone.

    ``executor`` / ``scheduler``: what runs the featurisation and the per-state models
    (:func:`fit_model`; docs/scaling.md); the model does not depend on it. ``workers``:
    processes when no executor is given (default 1: this process; ``bayes-talk train``: 2).
    ``calibrate_bands``: a fraction (e.g. 0.2) of the training utterances to hold out for
    the band calibration of the Laplace posterior (switching models;
    bayes_talk.synthesis.band_calibration: one extra fit on the rest, saved as
    ``band_calibration.json`` and applied by ``synth``); None: no calibration.
    """
    from bayes_talk.audio import AudioSettings, feature_statistics
    from bayes_talk.bundle import begin_bundle, write_bundle_manifest
    from bayes_talk.data.corpus import load_corpus
    from bayes_talk.features import mfcc as _mf

    out = Path(out_dir)
    if kind not in model_kinds():
        raise ValueError(f"unknown model kind {kind!r}; choose one of {', '.join(model_kinds())}")
    if out.exists() and any(out.iterdir()) and not force:
        raise FileExistsError(f"{out} is not empty; choose another directory or pass --force")
    if calibrate_bands is not None and (not calibrates_bands(kind) or not 0 < calibrate_bands < 1):
        raise ValueError(f"calibrate_bands: expected a fraction in (0, 1) for a model with a whole-utterance "
                         f"posterior (a switching model), found {calibrate_bands!r} for {kind}")
    fmax = _mf.FMAX_HZ if fmax is _DEFAULT else fmax
    floor_dbfs = _mf.FLOOR_DBFS if floor_dbfs is _DEFAULT else floor_dbfs
    from bayes_talk.executor import executor_for

    with executor_for(executor, workers, scheduler) as ex:
        corpus = load_corpus(corpus_dir, cmvn=cmvn, fmax=fmax, floor_dbfs=floor_dbfs,
                             executor=ex if executor is not None or ex.parallel else None)
        train_seqs, held_out = select_holdout(corpus.sequences, holdout, holdout_list, where=str(corpus_dir))
        corpus.sequences = train_seqs
        model = fit_model(new_model(kind, **overrides), list(corpus.sequences), workers, executor=ex)
        band_cal = None
        if calibrate_bands is not None:
            from bayes_talk.synthesis.band_calibration import fit_band_calibration

            band_cal = fit_band_calibration(model, corpus.sequences, holdout=calibrate_bands,
                                            seed=model.get_params()["seed"],
                                            fit=lambda m, seqs: fit_model(m, seqs, workers, executor=ex),
                                            executor=ex)
    out.mkdir(parents=True, exist_ok=True)
    begin_bundle(out, DESCRIPTOR)
    audio = AudioSettings(sample_rate=int(corpus.sample_rate), fps=float(corpus.fps), n_mfcc=_mf.N_MFCC,
                          window_s=_mf.WINDOW_S, n_mels=_mf.N_MELS, cmvn=cmvn, fmax=fmax,
                          floor_dbfs=floor_dbfs).to_dict()
    audio["feature_statistics"] = feature_statistics([s.mfcc for s in corpus.sequences])
    model.save(out / model.bundle_path)
    offset = aam_offset(corpus)
    if corpus.aam is not None:
        corpus.aam.save(out / "aam.npz")
    if band_cal is not None:
        band_cal.save(out)
    write_json(out / DESCRIPTOR, {
        "format": DESCRIPTOR_FORMAT, "version": DESCRIPTOR_VERSION, "kind": kind,
        "corpus": str(Path(corpus_dir).resolve()), "n_train": len(corpus.sequences),
        "fps": corpus.fps, "aam_offset": offset.tolist(), "has_aam": corpus.aam is not None,
        "held_out": held_out,
        "audio": audio, "bundle_manifest": True,
    })
    if alignment:  # issue 13: labels for test audio without hand-made phone labels
        from bayes_talk.alignment.commands import fit_alignment

        fit_alignment(corpus.sequences).save(out)
    write_bundle_manifest(out)
    return out


def calibrates_bands(kind: str) -> bool:
    """Whether a model of ``kind`` takes a band calibration: it has a whole-utterance
    posterior (bayes_talk.synthesis.band_calibration calibrates its bands)."""
    return kind in ESTIMATORS and "posterior" in ESTIMATORS[kind][0].synthesis_options


def select_holdout(sequences: list[Utterance], holdout: int | None = None,
                   holdout_list: str | os.PathLike | None = None,
                   where: str = "corpus") -> tuple[list[Utterance], list[str]]:
    """(training sequences, held-out names): the last ``holdout`` utterances, or those
    named in the file ``holdout_list`` (one name a line; blank lines and ``#`` comments
    skipped). ValueError naming the problem: both given, N outside [0, n - 1], an unknown
    or repeated name, or nothing left to train on."""
    seqs = list(sequences)
    if holdout is not None and holdout_list is not None:
        raise ValueError("give either holdout (a count) or holdout_list (a file), not both")
    if holdout is not None:
        if not isinstance(holdout, (int, np.integer)) or isinstance(holdout, bool) or not 0 <= holdout < len(seqs):
            raise ValueError(f"holdout: expected an integer in [0, {len(seqs) - 1}] for the "
                             f"{len(seqs)} utterances of {where}, found {holdout!r}")
        names = [s.name for s in seqs[len(seqs) - int(holdout):]] if holdout else []
    elif holdout_list is not None:
        path = Path(holdout_list)
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{path}: cannot read the hold-out list ({exc})") from exc
        names = [ln.split("#", 1)[0].strip() for ln in lines]
        names = [n for n in names if n]
        known = {s.name for s in seqs}
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ValueError(f"{path}: utterance(s) {unknown[:5]} are not in {where} "
                             f"(its names look like {seqs[0].name!r})")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"{path}: utterance(s) {dup[:5]} listed more than once")
        if len(names) >= len(seqs):
            raise ValueError(f"{path}: holds out all {len(seqs)} utterances of {where}; nothing left to train on")
    else:
        return seqs, []
    out = set(names)
    return [s for s in seqs if s.name not in out], names


def aam_offset(corpus) -> np.ndarray:
    """What to add back to mean-removed AAM parameters before rendering: the AAM's own mean
    parameters plus the average of the removed per-sequence means."""
    means = [s.meta["aam_mean"] for s in corpus.sequences if "aam_mean" in s.meta]
    Dz = corpus.sequences[0].aam.shape[1]
    avg = np.mean(means, axis=0) if means else np.zeros(Dz)
    return np.asarray(avg, dtype=np.float64)


@dataclass
class TrainedModel:
    kind: str
    model: object
    aam: object | None
    offset: np.ndarray
    fps: float
    audio: object = None  # bayes_talk.audio.AudioSettings
    calibration: object = None  # bayes_talk.synthesis.band_calibration.BandCalibration, if trained with one


def load_trained(model_dir: str | os.PathLike) -> TrainedModel:
    """Load a directory written by :func:`train`; errors name the file and the problem."""
    from bayes_talk.audio import AudioSettings
    from bayes_talk.bundle import BUNDLE_MANIFEST, verify_bundle
    from bayes_talk.features.aam import AAM

    d = Path(model_dir)
    p = d / DESCRIPTOR
    if not p.exists():
        extra = (" -- its save was interrupted; train it again" if (d / "arrays.npz").exists()
                 or (d / "sgpdm").exists() else "")
        raise FileNotFoundError(f"{d} is not a bayes_talk model directory (no {DESCRIPTOR}){extra}")
    try:
        desc = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p} is truncated or not JSON ({exc})") from None
    check_format(desc, DESCRIPTOR_FORMAT, DESCRIPTOR_VERSION, str(p))
    if desc.get("bundle_manifest") or (d / BUNDLE_MANIFEST).exists():
        verify_bundle(d)
    else:
        log.warning("%s has no %s (saved before bundles were hashed): its files cannot be checked "
                    "to belong together", d, BUNDLE_MANIFEST)
    kind = desc["kind"]
    if kind not in ESTIMATORS:
        raise ValueError(f"{p}: kind {kind!r} is no registered model family (expected one of "
                         f"{', '.join(model_kinds())})")
    cls = ESTIMATORS[kind][0]
    model = cls.load(d / cls.bundle_path)
    aam = AAM.load(d / "aam.npz") if desc.get("has_aam") else None
    if aam is not None and aam.n_params != len(desc["aam_offset"]):
        from bayes_talk.bundle import BundleError

        raise BundleError(f"{d / 'aam.npz'}: an AAM with {aam.n_params} parameters, but the model in {d} "
                          f"was trained on {len(desc['aam_offset'])}: the AAM does not belong to this model")
    from bayes_talk.synthesis.band_calibration import BandCalibration

    return TrainedModel(kind, model, aam, np.asarray(desc["aam_offset"]), float(desc.get("fps", 25.0)),
                        AudioSettings.from_dict(desc.get("audio"), where=str(d)), BandCalibration.load(d))


#: every file name synth can write (docs/outputs.md)
SYNTH_OUTPUT_NAMES = ("trajectory.npy", "variance.npy", "landmarks.npy", "segments.json", "face.mp4",
                      "bands.npz", "diagnostics.json", "labels.lab", "posterior.nc", "bands.png",
                      "uncertainty.mp4")


def _mean_shrinkage(res, tm) -> list[float] | None:
    """The band calibration's per-parameter mean factors a_d applied to ``res``, or None."""
    bc = res.diagnostics.get("band_calibration") if isinstance(res.diagnostics, dict) else None
    if not bc or tm.calibration is None or tm.calibration.mean_scale is None:
        return None
    return [float(a) for a in tm.calibration.mean_scale]


def _pool_weight(res, tm) -> list[float] | None:
    """The band calibration's per-parameter pool weights w_d (stage 3) applied to ``res``, or None."""
    bc = res.diagnostics.get("band_calibration") if isinstance(res.diagnostics, dict) else None
    if not bc or tm.calibration is None or tm.calibration.pool_weight is None:
        return None
    return [float(w) for w in tm.calibration.pool_weight]


def _trajectory_description(res, lowpass_hz) -> str:
    """What ``trajectory.npy`` holds, in words (written to ``diagnostics.json``)."""
    calibrated = isinstance(res.diagnostics, dict) and "band_calibration" in res.diagnostics
    has_c = getattr(res, "mean_function", None) is not None
    toward = ("the model's explicit mean function c_t (its phonetic-context view)" if has_c
              else "0 (the parameter's training mean)")
    what = (f"the mean of the band-calibrated {res.method} predictive: the posterior mean with each AAM "
            f"parameter's part beyond {toward} multiplied by the calibration's mean factor a_d "
            "(mean_shrinkage; 1 = unchanged, 0 = the parameter is predicted as that mean function); "
            "the bands' pool with the constant band (pool_weight) leaves the mean unchanged" if calibrated else
            f"the mean of the {res.method} posterior predictive (no band calibration applied)")
    filt = f", low-passed at {lowpass_hz:g} Hz (zero phase)" if lowpass_hz is not None else ""
    return what + filt + "; mean-removed AAM parameters (add the model's offset)"


def synth(model_dir, wav, labels, out_dir, algorithm: str = "optimise", init: str | None = None,
          force: bool = False, video: bool = True, posterior: str | None = None, n_draws: int | None = None,
          seed: int = 0, tier: str | None = None, text: str | None = None,
          transcript: str | os.PathLike | None = None, align_method: str | None = None,
          truth: str | os.PathLike | None = None, calibrated: bool = True,
          sampler_options: dict | None = None, lowpass_hz: float | None = _DEFAULT) -> dict[str, Path]:
    """Synthesise a face for WAV + labels; writes the AAM trajectory, its variance, the
    landmarks, the segmentation and an MP4 with the audio into ``out_dir``.

    posterior: for a switching model, the whole-utterance synthesis posterior by "laplace"
    (the default), "nuts", "pg-nuts" (particle Gibbs ∘ NUTS ∘ mode jumps), "emcee" or "vi"
    (docs/uncertainty.md "Which sampler"): the trajectory and variance are
    the posterior mixture's mean and variance, and ``bands.npz`` (central 50 % and 90 %
    bands: lower50, upper50, lower90, upper90) and ``diagnostics.json`` (MAP convergence,
    R-hat, ESS, divergences, warnings) are written too; "map": the paper's sequential path
    (``algorithm`` 1 or 2, deena2010) with the GP variance, the only choice (and the
    default) for an sgplvm model. A posterior whose diagnostics fail the convergence checks
    (bayes_talk.synthesis.posterior) is logged as a WARNING and marked ``"converged": false``
    in ``diagnostics.json``.

    The audio is resampled to the model's training rate and normalised as in training
    (bayes_talk.audio); ``tier`` names the TextGrid tier with the phones. With ``force``
    the files of an earlier run in ``out_dir`` that this run does not write are removed
    (only files recorded by that run; bayes_talk.bundle.OutputSet).

    Without ``labels`` (issue 13): the phone labels come from aligning ``text`` (or the
    ``transcript`` file) to the audio, or, with neither, from the phone recogniser (a
    warning says so); they are written to ``labels.lab`` in ``out_dir``.

    Every run (issue 10) also writes, from the one synthesis result
    (bayes_talk.synthesis.result.SynthesisResult, whatever the method): ``bands.npz`` (its
    exact central 50 % / 90 % bands, the ones ``evaluate`` scores), ``posterior.nc`` (its
    ArviZ InferenceData), ``bands.png`` (the first AAM parameters: mean, bands, and the
    ``truth`` when given: a .npy (T, n_params) in the space of ``trajectory.npy``) and, with
    a video, ``uncertainty.mp4`` (the mean face beside the per-pixel standard deviation of
    rendered predictive draws; bayes_talk.uncertainty_outputs).

    ``calibrated``: apply the model's band calibration (``band_calibration.json``, fitted by
    ``train --calibrate-bands``) when ``posterior`` is the method it was fitted on; False:
    the raw posterior bands. Whether it was applied is recorded in ``diagnostics.json``.

    ``lowpass_hz``: the zero-phase low-pass of deena2010 §4.2.3 applied to a switching
    model's mean, the bands moving with it (default
    :data:`~bayes_talk.synthesis.sequential.POST_FILTER_HZ`, 4 Hz, the setting of the
    held-out figures in docs/results.md; None: off). Recorded in ``segments.json``.
    """
    from bayes_talk.bundle import OutputSet, check_output_dir
    from bayes_talk.video import write_video

    check_output_dir(out_dir)   # a file or an unwritable place: refused before any work
    if (sampler_options or {}).get("pg_particles") is not None and posterior != "pg-nuts":
        raise ValueError(f"--pg-particles applies to --posterior pg-nuts, not {posterior!r}")
    tm = load_trained(model_dir)
    choices = type(tm.model).synthesis_options
    if posterior is None:
        posterior = DEFAULT_METHOD if "posterior" in choices else "map"
    check_method(posterior)
    if posterior != "map" and posterior not in choices.get("posterior", ()):
        raise ValueError(f"--posterior {posterior} needs a model with a whole-utterance posterior (a switching "
                         f"model); this model is {tm.kind!r}: use --posterior map")
    if init is not None and init not in choices.get("init", ()):
        raise ValueError(f"--init {init}: a {tm.kind} model initialises by "
                         f"{' or '.join(choices.get('init', ())) or 'no initialiser'}")
    options = _synthesis_options(choices, posterior, algorithm, init, n_draws, seed, sampler_options)
    _check_speech(wav, recognise=labels is None and text is None and transcript is None)
    derived = None
    if labels is None:
        derived = _derived_labels(model_dir, wav, text, transcript, align_method)
    elif text is not None or transcript is not None:
        raise ValueError("give either phone labels (--labels) or a transcript (--text/--transcript), not both")
    front = {"sample_rate": tm.audio.sample_rate, "cmvn": tm.audio.cmvn, "fmax": tm.audio.fmax,
             "floor_dbfs": tm.audio.floor_dbfs}
    utt = (read_utterance(wav, labels, tm.fps, tier=tier, **front) if derived is None
           else _utterance_from_intervals(wav, derived, tm.fps, **front))
    if truth is not None:
        from bayes_talk.uncertainty_outputs import read_truth

        truth = read_truth(truth, (utt.mfcc.shape[0], len(tm.offset)))
    out = Path(out_dir)
    outputs = OutputSet(out, SYNTH_OUTPUT_NAMES)
    names = {"trajectory": "trajectory.npy", "variance": "variance.npy", "landmarks": "landmarks.npy",
             "segments": "segments.json", "video": "face.mp4"}
    if derived is not None:
        names["labels"] = "labels.lab"
    names.update(bands="bands.npz", posterior="posterior.nc", plot="bands.png")
    if video and tm.aam is not None:
        names["uncertainty"] = "uncertainty.mp4"
    if posterior != "map":
        names.update(diagnostics="diagnostics.json")
    existing = sorted({n for n in list(names.values()) + outputs.present() if (out / n).exists()})
    if existing and not force:
        raise FileExistsError(f"{out} already holds {existing}; choose another directory or pass --force")
    out.mkdir(parents=True, exist_ok=True)
    res = tm.model.predict_dist(utt, **options)
    if calibrated and tm.calibration is not None and tm.calibration.method == posterior:
        res = tm.calibration.apply(res)
    post_filter_hz = None
    if tm.model.post_filter:
        from bayes_talk.synthesis.sequential import POST_FILTER_HZ, lowpass

        post_filter_hz = POST_FILTER_HZ if lowpass_hz is _DEFAULT else lowpass_hz
        if post_filter_hz is not None:
            res = res.shift(lowpass(res.mean, float(post_filter_hz), fps=tm.fps) - res.mean)
    segs = [{"state": list(s.state), "start": s.start, "stop": s.stop} for s in res.segments]
    written = {}
    if derived is not None:
        from bayes_talk.data.labels import write_lab

        write_lab(out / names["labels"], derived)
        written["labels"] = out / names["labels"]
    written.update(_write_uncertainty(out, names, res, truth, tm, wav, video, seed))
    if posterior != "map":
        problems = list(res.warnings)
        if problems:
            # each warning names its failed checks and what to try (posterior._convergence_warnings);
            # more draws help the samplers, not an approximation's k̂ (laplace, vi)
            log.warning("--posterior %s did not converge (%s): treat the mean, variance and bands as "
                        "unreliable%s", posterior, "; ".join(problems),
                        "; raise --draws or --warmup" if posterior in ("nuts", "pg-nuts", "emcee") else "")
        write_json(out / names["diagnostics"], {"method": posterior, "n_draws": res.n_draws, "seed": seed,
                                                "converged": not problems, "problems": problems,
                                                "trajectory_holds": _trajectory_description(res, post_filter_hz),
                                                "mean_shrinkage": _mean_shrinkage(res, tm),
                                                "pool_weight": _pool_weight(res, tm),
                                                "diagnostics": res.diagnostics})
        written.update(diagnostics=out / names["diagnostics"])
    for key, arr in (("trajectory", res.mean), ("variance", res.var)):
        write_npy(out / names[key], arr)
        written[key] = out / names[key]
    write_json(out / names["segments"], {"segments": segs, "fps": tm.fps,
                                         "post_filter_hz": post_filter_hz})
    written["segments"] = out / names["segments"]
    if tm.aam is not None:
        params = res.mean + tm.offset
        lms, _ = tm.aam.reconstruct(params)
        write_npy(out / names["landmarks"], lms)
        written["landmarks"] = out / names["landmarks"]
        if video:
            write_video(out / names["video"], tm.aam.render(params), tm.fps, audio_path=wav, overwrite=True)
            written["video"] = out / names["video"]
    outputs.commit(list(written.values()))
    return written


def _write_uncertainty(out: Path, names: dict, res, truth, tm: TrainedModel, wav, video: bool,
                       seed: int) -> dict[str, Path]:
    """bands.npz, posterior.nc, bands.png and (with a video and an AAM) uncertainty.mp4 of
    the synthesis result ``res`` (see :func:`synth`)."""
    from bayes_talk.uncertainty_outputs import (
        BAND_LEVELS,
        plot_bands,
        uncertainty_frames,
        write_posterior_netcdf,
    )
    from bayes_talk.video import write_video

    written = {}
    bands = {}
    for q in BAND_LEVELS:
        lo, hi = res.interval(q)
        bands[f"lower{round(100 * q)}"], bands[f"upper{round(100 * q)}"] = lo, hi
    written["bands"] = write_npz(out / names["bands"], bands)
    written["posterior"] = write_posterior_netcdf(out / names["posterior"], res, truth)
    written["plot"] = plot_bands(out / names["plot"], res, truth, fps=tm.fps)
    if "uncertainty" in names:
        frames = uncertainty_frames(tm.aam, res, tm.offset, seed=seed)
        written["uncertainty"] = write_video(out / names["uncertainty"], frames, tm.fps,
                                                   audio_path=wav, overwrite=True)
    return written


def _synthesis_options(choices: dict, posterior: str, algorithm: str, init: str | None, n_draws: int | None,
                       seed: int, sampler_options: dict | None) -> dict:
    """The keyword arguments of the model's ``predict_dist`` for synth's choices, among those
    the model takes (``choices``, its ``synthesis_options``): "map" is the model's own path
    (``algorithm`` where it has one), any other ``posterior`` the whole-utterance posterior
    with its draws, seed and sampler options."""
    opts: dict = {} if init is None else {"init": init}
    if posterior != "map":
        return {**opts, "posterior": posterior, "n_draws": n_draws, "seed": seed, **_sampler_args(sampler_options)}
    if "algorithm" in choices:
        opts["algorithm"] = algorithm
    return opts


def _sampler_args(options: dict | None) -> dict:
    """``sample_synthesis`` keywords from synth's sampler options (``chains``, ``warmup``,
    ``target_accept``, ``max_tree_depth``, ``pg_particles``; None entries keep the library defaults)."""
    opts = {k: v for k, v in (options or {}).items() if v is not None}
    unknown = set(opts) - {"chains", "warmup", "target_accept", "max_tree_depth", "pg_particles"}
    if unknown:
        raise ValueError(f"unknown sampler options {sorted(unknown)}")
    kw = {k: opts.pop(k) for k in ("chains", "warmup") if k in opts}
    return {**kw, "sampler_kw": opts} if opts else kw


def _check_speech(wav, recognise: bool) -> None:
    """No speech in ``wav`` (:func:`bayes_talk.audio.speech_problem`): an error before the
    phone recogniser invents phones for it; a warning when labels or a transcript were given
    (the face then follows them, not the audio). The file's own warnings (clipping, an MP3
    without its gapless header) are left to the load that makes the features, so that each
    is said once."""
    import warnings

    from bayes_talk.audio import load_audio, speech_problem

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        y, sr = load_audio(wav)
    problem = speech_problem(y, sr)
    if problem is None:
        return
    if recognise:
        raise ValueError(f"{wav}: no speech found, the audio is {problem}; the phone recogniser would "
                         "invent phones for it. Check the file, or give --labels/--text if this is intended")
    warnings.warn(f"{wav}: no speech found, the audio is {problem}: the face follows the given labels, "
                  "not the audio", UserWarning, stacklevel=3)


def _derived_labels(model_dir, wav, text, transcript, align_method) -> list[tuple[float, float, str]]:
    """Phone intervals from the alignment models of ``model_dir`` (aligner or recogniser)."""
    from bayes_talk.alignment.commands import DEFAULT_ALIGN_METHOD, label_audio

    return label_audio(model_dir, wav, text=text, transcript=transcript,
                       method=align_method or DEFAULT_ALIGN_METHOD).intervals


def _utterance_from_intervals(wav, intervals, fps: float = 25.0, *, sample_rate: int | None = None,
                              cmvn: str = "off", fmax: float | None = None,
                              floor_dbfs: float | None = None) -> Utterance:
    """MFCCs (the model's front end, as :func:`read_utterance`) and frame labels of a WAV
    whose phone intervals were derived from its audio."""
    from bayes_talk.audio import cmvn as _cmvn
    from bayes_talk.data.labels import frame_labels
    from bayes_talk.features.mfcc import frame_count, load_wav, mfcc

    wav = Path(wav)
    y, sr = load_wav(wav, sample_rate)
    T = frame_count(y.size, sr, fps)
    return Utterance(wav.stem, _cmvn(mfcc(y, sr, T, fps=fps, where=str(wav), fmax=fmax, floor_dbfs=floor_dbfs),
                                     cmvn), None,
                    frame_labels(intervals, T, fps), audio_path=wav)
