"""Synthesis with the switching SGPDM: deena2010 Algorithms 1 and 2 (§4.2).

1. Segment the test labels into non-overlapping VLMM (or phone) states (§4.2.1).
2. For each segment [a, b) in state π, start from the nearest-neighbour initialisation
   inside π's model (§4.2.2) and

   * Algorithm 1 ("optimise", sequential optimisation): point optimisation when the
     segment is one frame long, sequence optimisation (deena2009 eq. 9) otherwise;
   * Algorithm 2 ("predict", sequential prediction): point-optimise the first frame,
     then run π's dynamics mean x_{t+1} = μ_x(x_t) for the rest of the segment.

   Both include the entry distribution ln N(x_a; μ_π, Σ_π) of eq. 12 on the first point.
3. Smoothness across states (§4.2.3; our reading in docs/switching.md): for a segment that
   starts at a > 0 the first latent point must also explain the last frame already
   synthesised: the objective gains ln N(ẑ_{a−1}; μ_Z(x_a), σ²_Z(x_a)/w² + s²_Δ) under π's
   visual GP. s²_Δ (per dimension) is the mean square frame-to-frame motion of the
   training visual features: ẑ_{a−1} is the previous frame, not the current one. Without
   s²_Δ (the literal reading) the visual GP, far more precise than the motion between
   frames, makes every segment's first frame copy the previous one; measurements in
   docs/switching.md. ``smoothness="off"`` makes segments independent.
4. ẑ_t = μ_Z(x̂_t) with per-dimension variance σ²_Z(x̂_t)/w² (eq. 10), then an optional
   zero-phase Butterworth low-pass (filtfilt) on the mean. The result is a one-component
   :class:`~bayes_talk.synthesis.result.SynthesisResult` (a Gaussian per entry; ``.latents``
   the (T, d) path).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from scipy.signal import butter, filtfilt

from bayes_talk.gp.threads import torch_threads
from bayes_talk.synthesis.initialisers import NearestNeighbour
from bayes_talk.synthesis.optimise import maximise_sequence
from bayes_talk.synthesis.result import SynthesisResult
from bayes_talk.synthesis.segment_objective import SEGMENT_MAX_ITER

if TYPE_CHECKING:
    from bayes_talk.models.switching import SwitchingModel

ALGORITHMS = ("optimise", "predict")

SMOOTHNESS = ("frame", "off")
DEFAULT_SMOOTHNESS = "frame"
_NN = NearestNeighbour()


#: the post-filter ``synth`` applies to a switching model's mean by default (Hz; deena2010
#: §4.2.3's zero-phase low-pass; the setting of every held-out figure in docs/results.md)
POST_FILTER_HZ = 4.0


def lowpass(Z: np.ndarray, cutoff_hz: float, fps: float = 25.0, order: int = 4) -> np.ndarray:
    """Zero-phase Butterworth low-pass along time (scipy.signal.filtfilt)."""
    if not 0 < cutoff_hz < fps / 2:
        raise ValueError(f"low-pass cutoff must be in (0, {fps / 2}) Hz, got {cutoff_hz}")
    b, a = butter(order, cutoff_hz / (fps / 2))
    padlen = 3 * max(len(a), len(b))
    if Z.shape[0] <= padlen:
        return Z.copy()
    return filtfilt(b, a, Z, axis=0)


def check_inputs(model: SwitchingModel, mfcc: np.ndarray, labels, audio_view: bool = False) -> np.ndarray:
    """``mfcc`` as float64 (T, D_y), checked against ``model`` and the frame ``labels``; with
    ``audio_view`` it is the model's audio view instead (:meth:`SwitchingModel.audio_input`,
    ``model.audio_view_dim`` columns: D_y plus the phonetic-context view's)."""
    mfcc = np.asarray(mfcc, dtype=np.float64)
    Dy = model.audio_view_dim if audio_view else model.dims_[0]
    if mfcc.ndim != 2 or mfcc.shape[1] != Dy:
        what = "audio view" if audio_view else "audio features"
        raise ValueError(f"{what}: expected shape (T, {Dy}), got {mfcc.shape}")
    if len(labels) != mfcc.shape[0]:
        raise ValueError(f"audio has {mfcc.shape[0]} frames but the labels have {len(labels)}")
    if not np.all(np.isfinite(mfcc)):
        raise ValueError("audio features contain NaN or inf")
    return mfcc


def synthesize(
    model: SwitchingModel,
    mfcc: np.ndarray,
    labels,
    algorithm: str = "optimise",
    smoothness: str | bool = DEFAULT_SMOOTHNESS,
    lowpass_hz: float | None = None,
    max_iter: int = SEGMENT_MAX_ITER,
    audio_view: bool = False,
) -> SynthesisResult:
    """Run Algorithm 1 (``"optimise"``) or 2 (``"predict"``) on one utterance.

    smoothness: "frame" or "off" (True = "frame", False = "off"); see the
    module docstring. audio_view: ``mfcc`` is already the audio view the state models
    explain (``model.audio_input(mfcc)``, e.g. audio simulated by the synthesis model's
    prior predictive), so it is used as it is instead of being transformed again.
    """
    if algorithm not in ALGORITHMS:
        raise ValueError(f"algorithm must be one of {ALGORITHMS}, got {algorithm!r}")
    smoothness = DEFAULT_SMOOTHNESS if smoothness is True else "off" if smoothness is False else smoothness
    if smoothness not in SMOOTHNESS:
        raise ValueError(f"smoothness must be one of {SMOOTHNESS}, got {smoothness!r}")
    mfcc = check_inputs(model, mfcc, labels, audio_view)
    with torch_threads(1):
        return _synthesize(model, mfcc, labels, algorithm, smoothness, lowpass_hz, max_iter, audio_view)


def _synthesize(model, mfcc, labels, algorithm, smoothness, lowpass_hz, max_iter,
                audio_view: bool = False) -> SynthesisResult:
    segments = model.segment(list(labels))
    audio = mfcc if audio_view else model.audio_input(mfcc, labels)   # what the state models' audio GPs explain
    T, Dz = mfcc.shape[0], model.dims_[1]
    d = model.config.latent_dim
    mean, var, X = np.zeros((T, Dz)), np.zeros((T, Dz)), np.zeros((T, d))
    used: list[tuple[str, ...]] = []
    for seg in segments:
        a, b = seg.start, seg.stop
        key, m = model.model_for(seg.state)
        used.append(key)
        z_prev = mean[a - 1:a].copy() if a > 0 else None
        # Algorithm 1 optimises the whole segment; Algorithm 2 (and one-frame segments)
        # optimise its first frame only and roll the dynamics mean forward.
        n_opt = b - a if algorithm == "optimise" else 1
        Xs = maximise_state_segment(m, audio[a:a + n_opt], z_prev, model.entry_[key], smoothness, max_iter,
                               model.motion_var_)
        if n_opt < b - a:
            Xs = _roll_dynamics(m, Xs[0], b - a)
        X[a:b] = Xs
        mean[a:b], var[a:b] = m.predict_view("visual", Xs)
    offset = model.visual_offset(audio) if model.config.context_mean else None
    if offset is not None:   # the explicit mean function c_t (SwitchingConfig.context_mean)
        mean = mean + offset
    if lowpass_hz is not None:
        mean = lowpass(mean, lowpass_hz)
    return SynthesisResult.gaussian(mean, var, X, method=algorithm, segments=segments, model_states=used,
                                    mean_function=offset)


def maximise_state_segment(m, Y: np.ndarray, z_prev: np.ndarray | None, entry, smoothness: str,
                      max_iter: int, motion_var: np.ndarray) -> np.ndarray:
    """Latent points of one segment (or of its first frame) under state model ``m``.

    The objective is :func:`~bayes_talk.synthesis.optimise.sequence_log_density`
    (maximised by :func:`~bayes_talk.synthesis.optimise.maximise_sequence`). With
    smoothness "frame" (docs/switching.md) x_a itself must explain the last synthesised
    frame, which differs from the current one by the frame-to-frame motion (variance
    ``motion_var``).
    """
    X0 = _NN(m, "audio", Y)
    dyn = m.dynamics_predictor_ if len(Y) > 1 else None
    smooth = None
    if z_prev is not None and smoothness == "frame":
        smooth = (m.predictors_["visual"], z_prev, motion_var)
    return maximise_sequence(m.predictors_["audio"], Y, X0, dyn, first=entry, smooth=smooth, max_iter=max_iter)


def _roll_dynamics(m, x1: np.ndarray, n: int) -> np.ndarray:
    """x_1 given, x_{t+1} = μ_x(x_t) (Algorithm 2); a model without dynamics stays put."""
    out = [np.asarray(x1, dtype=np.float64)]
    dyn = m.dynamics_predictor_
    with torch.no_grad():
        for _ in range(n - 1):
            if dyn is None:
                out.append(out[-1].copy())
                continue
            mu, _ = dyn.mean_var(torch.as_tensor(out[-1][None, :]))
            out.append(mu[0].numpy())
    return np.vstack(out)


__all__ = ["ALGORITHMS", "SEGMENT_MAX_ITER", "SynthesisResult", "lowpass", "synthesize", "synthesize_many"]


def _synthesize_job(job: tuple) -> SynthesisResult:
    model, mfcc, labels, kw = job
    return synthesize(model, mfcc, labels, **kw)


def synthesize_many(model: SwitchingModel, utterances: list, workers: int = 2, executor=None,
                    **kw) -> list[SynthesisResult]:
    """:func:`synthesize` for many ``(mfcc, labels)`` pairs, through ``executor``
    (bayes_talk.base.executor; None: ``workers`` processes, or this process when 1).

    Utterances are independent, so on a machine with several cores throughput scales with
    the processes (each runs torch with one thread); each task carries the model.
    Results come back in input order and equal the one-process results.
    """
    from bayes_talk.base.executor import executor_for

    jobs = [(model, np.asarray(m), list(lab), kw) for m, lab in utterances]
    if executor is None and len(jobs) <= 1:
        workers = 1
    with executor_for(executor, workers) as ex:
        return ex.map(_synthesize_job, jobs)
