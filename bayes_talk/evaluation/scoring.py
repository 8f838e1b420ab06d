"""Scoring of one test utterance and summaries of the harness's results: the per-utterance
metrics of :mod:`bayes_talk.evaluation.harness` (RMS, L1, L∞, NMSE, correlation, test
log-likelihood; for methods with a variance: 50/90 % coverage, CRPS, NLPD), their
summaries, and the JSON-safe copy of a result."""
from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

from bayes_talk.evaluation import metrics as M

VAR_FLOOR = 1e-10


def utterance_metrics(z: np.ndarray, pred, variance: np.ndarray, ll: float | None) -> dict[str, float]:
    """The point and probabilistic metrics of one utterance's prediction ``pred`` against the true features ``z``."""
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
