"""From WAV + phone labels (or a transcript, or audio alone) to a talking face
(``bayes-talk synth``)::

    WAV + .lab/.TextGrid ──read_utterance──▶ Utterance without visual features
              ──model.predict_dist──▶ AAM trajectory + predictive distribution
              ──AAM.render──▶ frames ──▶ MP4, with the bands, diagnostics and uncertainty outputs

The model directory is read by :func:`bayes_talk.pipeline.trained.load_trained`; the audio
is featurised by the model's own front end (:mod:`bayes_talk.pipeline.front_end`); the
model is run through the estimator protocol with the options it declares
(``synthesis_options``), whatever its family.

Every stage of :func:`synth` is a progress stage (:func:`bayes_talk.base.progress.stage`):
loading the model, reading the audio, labelling it (alignment or recognition, without
labels), featurising it, the synthesis (its total the number of frames; the inference
reports through :func:`bayes_talk.base.progress.current`), writing the outputs (files) and
rendering the videos (frames). A run shows a bar per stage on a terminal and a heartbeat
line every few seconds elsewhere.
"""
from __future__ import annotations

import logging
import os
import warnings
from pathlib import Path

from bayes_talk.alignment.commands import DEFAULT_ALIGN_METHOD, label_audio
from bayes_talk.base.bundle import OutputSet, check_output_dir
from bayes_talk.base.files import write_json, write_npy, write_npz
from bayes_talk.base.progress import stage
from bayes_talk.base.video import write_video
from bayes_talk.data.labels import write_lab
from bayes_talk.features.audio import load_audio, speech_problem
from bayes_talk.pipeline.exports import (
    EXPORT_FORMATS,
    export_file_names,
    frame_export,
    write_landmark_track,
)
from bayes_talk.pipeline.front_end import front_end, read_utterance, utterance_from_intervals
from bayes_talk.pipeline.trained import TrainedModel, load_trained
from bayes_talk.pipeline.uncertainty_outputs import (
    BAND_LEVELS,
    VIDEO_DRAWS,
    plot_bands,
    read_truth,
    render_frames,
    uncertainty_frames,
    write_posterior_netcdf,
)
from bayes_talk.posterior.methods import DEFAULT_METHOD, INFERENCE, check_method
from bayes_talk.synthesis.sequential import lowpass

__all__ = ["SYNTH_OUTPUT_NAMES", "synth"]

log = logging.getLogger(__name__)

#: every file name synth can write (docs/outputs.md)
SYNTH_OUTPUT_NAMES = ("trajectory.npy", "variance.npy", "landmarks.npy", "segments.json", "face.mp4",
                      "bands.npz", "diagnostics.json", "labels.lab", "posterior.nc", "bands.png",
                      "uncertainty.mp4", *(n for f in EXPORT_FORMATS for n in export_file_names(f).values()))


def _calibration_factors(res, tm, attribute: str) -> list[float] | None:
    """The band calibration's per-parameter factors ``attribute`` (``mean_scale``: the mean
    factors a_d; ``pool_weight``: the stage-3 pool weights w_d) as applied to ``res``, or
    None when ``res`` was not calibrated or the calibration has none."""
    bc = res.diagnostics.get("band_calibration") if isinstance(res.diagnostics, dict) else None
    values = getattr(tm.calibration, attribute, None) if tm.calibration is not None else None
    if not bc or values is None:
        return None
    return [float(v) for v in values]


def _face_noise_record(res, tm) -> dict | None:
    """The observation term applied to ``res`` (its per-parameter shrinkage a_d, Student-t
    scale τ_d and degrees of freedom ν_d), or None when none was."""
    noise = getattr(tm.uncalibrated, "face_noise_", None)
    if noise is None or not res.diagnostics.get("face_noise"):
        return None
    return {"shrink": noise.shrink.tolist(), "scale": noise.scale.tolist(),
            "dof": [min(float(v), 1e6) for v in noise.dof], "gp_scale": noise.gp_scale.tolist()}


def _trajectory_description(res, lowpass_hz) -> str:
    """What ``trajectory.npy`` holds, in words (written to ``diagnostics.json``)."""
    calibrated = isinstance(res.diagnostics, dict) and "band_calibration" in res.diagnostics
    has_c = getattr(res, "mean_function", None) is not None
    toward = ("the model's explicit mean function c_t (its phonetic-context view)" if has_c
              else "0 (the parameter's training mean)")
    if isinstance(res.diagnostics, dict) and res.diagnostics.get("face_noise"):
        filt = f", low-passed at {lowpass_hz:g} Hz (zero phase)" if lowpass_hz is not None else ""
        return (f"the mean of the {res.method} predictive with the model's observation term: the posterior "
                f"mean with each AAM parameter's part beyond {toward} multiplied by the term's shrinkage a_d "
                f"(face_noise.shrink; 1 = unchanged, 0 = that mean function){filt}; mean-removed AAM "
                "parameters (add the model's offset)")
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
          sampler_options: dict | None = None, lowpass_hz: float | None = None,
          export: str | None = None) -> dict[str, Path]:
    """Synthesise a face for WAV + labels; writes the AAM trajectory, its variance, the
    landmarks, the segmentation and an MP4 with the audio into ``out_dir``.

    ``model_dir``: a directory written by ``train``, or the :class:`TrainedModel` that
    :func:`~bayes_talk.pipeline.trained.load_trained` read from one (used as it is: many
    files synthesised with one load, :func:`bayes_talk.pipeline.batch.synth_many`).

    posterior: for a switching model, the whole-utterance synthesis posterior by "laplace"
    (the default), "nuts", "pg-nuts" (particle Gibbs ∘ NUTS ∘ mode jumps), "emcee" or "vi"
    (docs/uncertainty.md "Which sampler"): the trajectory and variance are
    the posterior mixture's mean and variance, and ``bands.npz`` (central 50 % and 90 %
    bands: lower50, upper50, lower90, upper90) and ``diagnostics.json`` (MAP convergence,
    R-hat, ESS, divergences, warnings) are written too; "map": the paper's sequential path
    (``algorithm`` 1 or 2, deena2010) with the GP variance, the only choice (and the
    default) for an sgplvm model. A posterior whose diagnostics fail the convergence checks
    (bayes_talk.posterior.sampling) is logged as a WARNING and marked ``"converged": false``
    in ``diagnostics.json``.

    The audio is resampled to the model's training rate and normalised as in training
    (bayes_talk.features.audio); ``tier`` names the TextGrid tier with the phones. With ``force``
    the files of an earlier run in ``out_dir`` that this run does not write are removed
    (only files recorded by that run; bayes_talk.base.bundle.OutputSet).

    Without ``labels``: the phone labels come from aligning ``text`` (or the
    ``transcript`` file) to the audio, or, with neither, from the phone recogniser (a
    warning says so); they are written to ``labels.lab`` in ``out_dir``.

    Every run also writes, from the one synthesis result
    (bayes_talk.synthesis.result.SynthesisResult, whatever the method): ``bands.npz`` (its
    exact central 50 % / 90 % bands, the ones ``evaluate`` scores), ``posterior.nc`` (its
    ArviZ InferenceData), ``bands.png`` (the first AAM parameters: mean, bands, and the
    ``truth`` when given: a .npy (T, n_params) in the space of ``trajectory.npy``) and, with
    a video, ``uncertainty.mp4`` (the mean face beside the per-pixel standard deviation of
    rendered predictive draws; bayes_talk.pipeline.uncertainty_outputs).

    ``calibrated``: the predictive as ``train`` calibrated it, whatever the ``posterior``:
    with the model's observation term (:class:`~bayes_talk.synthesis.face_noise.FaceNoise`,
    fitted on held-out training utterances; the default ``train --calibration noise``) or its
    post-hoc band calibration (``train --calibration bands``); False: the GP predictive
    alone. What was applied is recorded in ``diagnostics.json``.

    ``lowpass_hz``: the zero-phase low-pass of deena2010 §4.2.3
    (:data:`~bayes_talk.synthesis.sequential.POST_FILTER_HZ`, 4 Hz, in the paper) applied to
    the mean of a model that takes it (its ``post_filter``: the switching models), the bands
    moving with it; None (the default): off, as ``evaluate`` scores the output. Recorded in
    ``segments.json``; docs/results.md measures what the filter does to the scores.

    ``export``: "json" or "csv" also writes ``frames.<export>`` (per frame: time, the AAM
    parameters' mean, sd and exact 5/50/95 % quantiles, the landmarks and their sd over seeded
    predictive draws) and, with an AAM, ``landmarks_track.<export>`` (the plain landmark track);
    bayes_talk.pipeline.exports, docs/outputs.md. None (the default): neither.
    """
    check_output_dir(out_dir)   # a file or an unwritable place: refused before any work
    exports = {} if export is None else export_file_names(export)
    for key, flag in (("pg_particles", "--pg-particles"), ("stop_at_targets", "--all-draws")):
        if (sampler_options or {}).get(key) is not None and posterior != "pg-nuts":
            raise ValueError(f"{flag} applies to --posterior pg-nuts, not {posterior!r}")
    if (sampler_options or {}).get("workers") is not None and posterior not in ("nuts", "pg-nuts"):
        raise ValueError(f"--workers runs NUTS chains in parallel: it applies to --posterior nuts or pg-nuts, "
                         f"not {posterior!r}")
    with stage("loading model", unit="files"):
        tm = model_dir if isinstance(model_dir, TrainedModel) else load_trained(model_dir)
    choices = tm.model.synthesis_options
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
    with stage("reading audio", unit="files"):
        _check_speech(wav, recognise=labels is None and text is None and transcript is None)
    derived = None
    if labels is None:
        with stage("labelling" if text is None and transcript is None else "aligning the transcript",
                   unit="files"):
            derived = _derived_labels(tm.directory, wav, text, transcript, align_method)
    elif text is not None or transcript is not None:
        raise ValueError("give either phone labels (--labels) or a transcript (--text/--transcript), not both")
    front = front_end(tm.audio)
    with stage("featurising audio", unit="files"):
        utt = (read_utterance(wav, labels, tm.fps, tier=tier, **front) if derived is None
               else utterance_from_intervals(wav, derived, tm.fps, **front))
    if truth is not None:
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
    if exports:
        names["export"] = exports["frames"]
        if tm.aam is not None:
            names["track"] = exports["track"]
    existing = sorted({n for n in list(names.values()) + outputs.present() if (out / n).exists()})
    if existing and not force:
        raise FileExistsError(f"{out} already holds {existing}; choose another directory or pass --force")
    out.mkdir(parents=True, exist_ok=True)
    model = tm.model if calibrated else tm.uncalibrated
    if not calibrated and getattr(model, "face_noise_", None) is not None:
        options = {**options, "face_noise": False}
    with stage("synthesis", total=utt.mfcc.shape[0], unit="frames") as synthesis:
        res = model.predict_dist(utt, **options)
        post_filter_hz = lowpass_hz if tm.model.post_filter else None
        if post_filter_hz is not None:
            res = res.shift(lowpass(res.mean, float(post_filter_hz), fps=tm.fps) - res.mean)
        synthesis.update(res.n_frames)
    segs = [{"state": list(s.state), "start": s.start, "stop": s.stop} for s in res.segments]
    written = {}
    to_render = video and tm.aam is not None
    n_files = sum(k not in ("video", "uncertainty") and (k != "landmarks" or tm.aam is not None) for k in names)
    with stage("writing outputs", total=n_files, unit="files") as writing:
        written.update(_write_outputs(out, names, res, truth, tm, derived, posterior, seed, segs,
                                      post_filter_hz, writing, exports))
    if to_render:
        n_frames = res.n_frames * (2 + VIDEO_DRAWS)   # face.mp4, the mean and the draws of uncertainty.mp4
        with stage("rendering video", total=n_frames, unit="frames"):
            written.update(_write_videos(out, names, res, tm, wav, seed))
    outputs.commit(list(written.values()))
    return written


def _write_outputs(out: Path, names: dict, res, truth, tm: TrainedModel, derived, posterior: str, seed: int,
                   segs: list, post_filter_hz, writing, exports: dict | None = None) -> dict[str, Path]:
    """Every output of :func:`synth` but the videos, from the synthesis result ``res``, with the
    per-frame export and the landmark track when ``exports`` names them; ``writing`` (a progress
    stage) advances per file."""
    written = {}
    if derived is not None:
        write_lab(out / names["labels"], derived)
        written["labels"] = out / names["labels"]
    written.update(_write_uncertainty(out, names, res, truth, tm, writing))
    if posterior != "map":
        problems = list(res.warnings)
        if problems:
            # each warning names its failed checks and what to try (posterior._convergence_warnings);
            # more draws help the samplers, not an approximation's k̂ (laplace, vi)
            log.warning("--posterior %s did not converge (%s): treat the mean, variance and bands as "
                        "unreliable%s", posterior, "; ".join(problems),
                        "; raise --draws or --warmup" if "rhat_ess" in INFERENCE[posterior].diagnostics else "")
        write_json(out / names["diagnostics"], {"method": posterior, "n_draws": res.n_draws, "seed": seed,
                                                "converged": not problems, "problems": problems,
                                                "trajectory_holds": _trajectory_description(res, post_filter_hz),
                                                "mean_shrinkage": _calibration_factors(res, tm, "mean_scale"),
                                                "face_noise": _face_noise_record(res, tm),
                                                "pool_weight": _calibration_factors(res, tm, "pool_weight"),
                                                "diagnostics": res.diagnostics})
        written.update(diagnostics=out / names["diagnostics"])
        writing.advance()
    for key, arr in (("trajectory", res.mean), ("variance", res.var)):
        write_npy(out / names[key], arr)
        written[key] = out / names[key]
        writing.advance()
    write_json(out / names["segments"], {"segments": segs, "fps": tm.fps,
                                         "post_filter_hz": post_filter_hz})
    written["segments"] = out / names["segments"]
    writing.advance()
    if tm.aam is not None:
        lms, _ = tm.aam.reconstruct(res.mean + tm.offset)
        write_npy(out / names["landmarks"], lms)
        written["landmarks"] = out / names["landmarks"]
        writing.advance()
    if exports:
        fx = frame_export(res, tm.fps, aam=tm.aam, offset=tm.offset if tm.aam is not None else None, seed=seed)
        written["export"] = fx.write(out / names["export"])
        writing.advance()
        if fx.landmarks is not None:
            written["track"] = write_landmark_track(out / names["track"], fx.landmarks, tm.fps, tm.aam.image_shape)
            writing.advance()
    return written


def _write_uncertainty(out: Path, names: dict, res, truth, tm: TrainedModel, writing) -> dict[str, Path]:
    """bands.npz, posterior.nc and bands.png of the synthesis result ``res`` (see
    :func:`synth`); ``writing`` (a progress stage) advances per file."""
    written = {}
    bands = {}
    for q in BAND_LEVELS:
        lo, hi = res.interval(q)
        bands[f"lower{round(100 * q)}"], bands[f"upper{round(100 * q)}"] = lo, hi
    written["bands"] = write_npz(out / names["bands"], bands)
    writing.advance()
    written["posterior"] = write_posterior_netcdf(out / names["posterior"], res, truth)
    writing.advance()
    written["plot"] = plot_bands(out / names["plot"], res, truth, fps=tm.fps)
    writing.advance()
    return written


def _write_videos(out: Path, names: dict, res, tm: TrainedModel, wav, seed: int) -> dict[str, Path]:
    """uncertainty.mp4 (the mean face beside the per-pixel s.d. of rendered draws) and
    face.mp4 (the mean face) with the audio, each rendered frame advancing the open
    progress stage (:func:`bayes_talk.pipeline.uncertainty_outputs.render_frames`)."""
    written = {}
    frames = uncertainty_frames(tm.aam, res, tm.offset, seed=seed)
    written["uncertainty"] = write_video(out / names["uncertainty"], frames, tm.fps, audio_path=wav, overwrite=True)
    del frames
    written["video"] = write_video(out / names["video"], render_frames(tm.aam, res.mean + tm.offset), tm.fps,
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
    ``target_accept``, ``max_tree_depth``, ``pg_particles``, ``workers``: processes running the
    chains, ``stop_at_targets``: pg-nuts's stopping rule; None entries keep the library defaults)."""
    opts = {k: v for k, v in (options or {}).items() if v is not None}
    unknown = set(opts) - {"chains", "warmup", "target_accept", "max_tree_depth", "pg_particles", "workers",
                           "stop_at_targets"}
    if unknown:
        raise ValueError(f"unknown sampler options {sorted(unknown)}")
    kw = {k: opts.pop(k) for k in ("chains", "warmup") if k in opts}
    return {**kw, "sampler_kw": opts} if opts else kw


def _check_speech(wav, recognise: bool) -> None:
    """No speech in ``wav`` (:func:`bayes_talk.features.audio.speech_problem`): an error before the
    phone recogniser invents phones for it; a warning when labels or a transcript were given
    (the face then follows them, not the audio). The file's own warnings (clipping, an MP3
    without its gapless header) are left to the load that makes the features, so that each
    is said once."""
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
    if model_dir is None:
        raise ValueError(f"{wav}: no phone labels given, and the model was not loaded from a directory, so "
                         "it has no aligner or phone recogniser; give the labels")
    return label_audio(model_dir, wav, text=text, transcript=transcript,
                       method=align_method or DEFAULT_ALIGN_METHOD).intervals
