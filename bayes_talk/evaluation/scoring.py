"""Scoring of one test utterance and summaries of the harness's results: the per-utterance
metrics of :mod:`bayes_talk.evaluation.harness` (RMS, L1, L∞, NMSE, correlation, test
log-likelihood; for methods with a variance: 50/90 % coverage, CRPS, NLPD; the field's
landmark metrics on the landmarks the AAM reconstructs: LVE, mouth-opening error, FDD and,
for a predictive mixed over draws of the path, the diversity, mean-of-samples and best-of-N
errors of its draws), their summaries, and the JSON-safe copy of a result."""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from bayes_talk.evaluation import metrics as M

VAR_FLOOR = 1e-10
#: predictive draws of the sample-based landmark metrics (``SystemConfig.sample_draws``)
SAMPLE_DRAWS = 16
#: the landmark metrics of every scored utterance (nan where undefined)
LANDMARK_KEYS = ("lve", "mouth_opening_mae", "fdd", "diversity", "mean_of_samples_lve", "best_of_n_lve")


@dataclass(frozen=True)
class LandmarkSpace:
    """How one test utterance's mean-removed AAM parameters become 2-D landmarks.

    aam: the AAM its features were projected through (anything with ``reconstruct_landmarks``,
        :meth:`bayes_talk.features.aam.AAM.reconstruct_landmarks`); offset: (D,) added to every
        parameter vector first, the utterance's own removed mean (so truth and prediction share
        it, as the AAM-space metrics compare mean-removed parameters); lips, mouth_pair, upper:
        the landmark regions (:data:`bayes_talk.data.face.LIP_LANDMARKS`, ``MOUTH_OPENING_PAIR``,
        ``UPPER_FACE_LANDMARKS``); n_draws, seed: the predictive draws of the sample metrics.
    """

    aam: Any
    offset: np.ndarray
    lips: np.ndarray
    mouth_pair: tuple[int, int]
    upper: np.ndarray
    n_draws: int = SAMPLE_DRAWS
    seed: int = 0

    def landmarks(self, params: np.ndarray) -> np.ndarray:
        """Landmarks (.., T, P, 2) of mean-removed parameters (.., T, D)."""
        p = np.asarray(params, dtype=np.float64)
        flat = p.reshape(-1, p.shape[-1]) + self.offset
        lm = self.aam.reconstruct_landmarks(flat)
        return lm.reshape(*p.shape[:-1], *lm.shape[1:])


def landmark_space(seq, n_draws: int = SAMPLE_DRAWS, seed: int = 0) -> LandmarkSpace | None:
    """The :class:`LandmarkSpace` of a test utterance: its AAM (``meta["aam_path"]``, the AAM its
    frames were projected through) and its removed mean (``meta["aam_mean"]``); None when it has
    no AAM (precomputed visual features), comes from a user corpus (whose landmarks follow the
    user's own layout) or the AAM's landmarks are not the built-in face's 57 (whose lip, mouth
    and upper-face regions the metrics need)."""
    from bayes_talk.corpus.workers import cached_aam
    from bayes_talk.data import face

    path = (seq.meta or {}).get("aam_path")
    if not path or seq.meta.get("corpus_kind") == "user":   # a user corpus's landmarks: its own layout
        return None
    aam = cached_aam(str(path))
    if aam.n_landmarks != face.N_LANDMARKS or aam.n_params != seq.aam.shape[1]:
        return None
    offset = np.asarray(seq.meta.get("aam_mean", np.zeros(aam.n_params)), dtype=np.float64)
    return LandmarkSpace(aam, offset, face.LIP_LANDMARKS, face.MOUTH_OPENING_PAIR, face.UPPER_FACE_LANDMARKS,
                         int(n_draws), int(seed))


def has_path_draws(result) -> bool:
    """True for a :class:`~bayes_talk.synthesis.result.SynthesisResult` that mixes over draws
    of the path: more than one component, and not all component means equal (the posterior
    methods). False for None, a single Gaussian, and a point path whose components differ only
    in their variances (the observation term's Student-t scale mixture around a MAP or
    Algorithm 1-2 path)."""
    if result is None or result.n_draws < 2:
        return False
    m = result.draw_mean.reshape((-1,) + result.draw_mean.shape[2:])
    return bool(np.any(m != m[0]))


def landmark_metrics(z: np.ndarray, pred, space: LandmarkSpace | None) -> dict[str, float]:
    """The field's landmark metrics of one utterance (:data:`LANDMARK_KEYS`; metrics module
    docstring): LVE, mouth-opening MAE and FDD of the predicted mean's landmarks; for a
    predictive mixed over draws of the path (:func:`has_path_draws`) the diversity,
    mean-of-samples LVE and best-of-N LVE of ``space.n_draws`` seeded draws of it
    (``result.sample``) pushed through the AAM. nan where undefined (no landmark space; a point
    path's predictive for the sample metrics)."""
    out = dict.fromkeys(LANDMARK_KEYS, float("nan"))
    if space is None:
        return out
    truth = space.landmarks(z)
    mean = space.landmarks(pred.mean)
    reference = space.landmarks(np.zeros((1, z.shape[1])))[0]
    out["lve"] = float(M.lip_vertex_error([truth], [mean], space.lips)[0])
    out["mouth_opening_mae"] = float(M.mouth_opening_error([truth], [mean], space.mouth_pair)[0])
    out["fdd"] = float(M.upper_face_dynamics_deviation([truth], [mean], space.upper, [reference])[0])
    result = getattr(pred, "result", None)
    if has_path_draws(result):
        draws = space.landmarks(result.sample(space.n_draws, seed=space.seed))
        out["diversity"] = float(M.sample_diversity([draws])[0])
        out["mean_of_samples_lve"] = float(M.mean_of_samples_error([truth], [draws], space.lips)[0])
        out["best_of_n_lve"] = float(M.best_of_n_error([truth], [draws], space.lips)[0])
    return out


def utterance_metrics(z: np.ndarray, pred, variance: np.ndarray, ll: float | None,
                      landmarks: LandmarkSpace | None = None) -> dict[str, float]:
    """The point and probabilistic metrics of one utterance's prediction ``pred`` against the
    true features ``z``, and its landmark metrics in ``landmarks`` (:func:`landmark_metrics`;
    nan without one)."""
    mean = pred.mean
    out = {
        "mse": float(M.mse([z], [mean])[0]),
        "rms": float(M.rms([z], [mean])[0]),
        "l1": float(M.l1([z], [mean])[0]),
        "linf": float(M.linf([z], [mean])[0]),
        "nmse": float(M.normalised_mse([z], [mean], variance=variance)[0]),
        "corr": float(M.correlation([z], [mean])[0]),
    }
    if ll is not None:
        out["log_likelihood_per_frame"] = ll / z.shape[0]
    if pred.var is not None:
        sd = np.sqrt(np.maximum(pred.var, VAR_FLOOR))
        for level in (50, 90):  # the bands synth writes (the result's exact interval)
            lo, hi = pred.band(level / 100)
            out[f"coverage_{level}"] = M.coverage([z], [lo], [hi])
        out["crps"] = M.crps_gaussian([z], [mean], [sd])
        out["nlpd"] = M.nlpd_gaussian([z], [mean], [sd * sd])
    if getattr(pred, "mse_bias", None) is not None:  # oracle: remove its finite-sample bias
        b = np.asarray(pred.mse_bias, np.float64).mean(axis=0)
        keep = variance > 0
        out["mse_corrected"] = out["mse"] - float(b.mean())
        out["nmse_corrected"] = out["nmse"] - float(np.mean(b[keep] / variance[keep]))
    out.update(landmark_metrics(z, pred, landmarks))
    return out


def summary_stats(values: list[float]) -> dict[str, Any]:
    """Mean, std and 95% interval of the finite ``values`` (:func:`~bayes_talk.evaluation.metrics.summarise`); all None if none."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        v = np.asarray(values, dtype=np.float64)
        if not np.isfinite(v).any():
            return {"mean": None, "std": None, "ci95": [None, None], "n": 0}
        s = M.summarise(v)
    return s


def json_safe(obj: Any) -> Any:
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python, tuples -> lists."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    return obj


def calibration_inputs(name: str, pred) -> dict[str, Any]:
    """{"calibration": predictive, "calibration_raw": the predictive before the calibration
    (the GP predictive alone), "calibration_control": the plain constant-band control,
    "calibration_<ablation>": the observation term's ablations} of a method with a variance
    (a Gaussian SynthesisResult where the method gives mean and variance only); all but the
    first where the method has them."""
    from bayes_talk.synthesis.result import SynthesisResult

    if pred.var is None:
        return {}
    res = pred.result if pred.result is not None else SynthesisResult.gaussian(
        pred.mean, np.maximum(pred.var, VAR_FLOOR), method=name)
    out = {"calibration": res}
    if pred.raw is not None:
        out["calibration_raw"] = pred.raw
    if getattr(pred, "control", None) is not None:
        out["calibration_control"] = pred.control
    for ablation, r in (getattr(pred, "ablations", None) or {}).items():
        out[f"calibration_{ablation.replace('-', '_')}"] = r
    return out
