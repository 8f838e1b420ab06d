"""The floor and the ceiling of an evaluation: methods ``zero`` and ``oracle``.
The two estimators are :mod:`bayes_talk.estimators.ceiling`; this module holds the maths
and the scores built on them.

``zero`` predicts every utterance's own mean, i.e. 0 after per-utterance mean removal
(deena2010 §3.2), with the training corpus's per-dimension variance as its predictive
variance (so its coverage can be scored). It is the "still face" every method must beat.

``oracle`` is the best possible prediction for a *built* corpus given the exact phone
timing. The generator (:func:`bayes_talk.data.face.face_landmarks`; for a ``--speech vtl``
corpus with the jaw and lips from a fresh draw of the vocal tract's articulatory variation,
:func:`bayes_talk.data.articulatory.articulatory_draws`) is known, so the
minimum-MSE prediction of the mean-removed AAM parameters ``z`` given the phone intervals
``I`` is the conditional mean ``mu = E[z | I]``. It is estimated by Monte Carlo: K draws of
the generator with fresh randomness and the utterance's true intervals
(``meta["intervals"]``, read from its ``.lab``), each rendered exactly as the corpus was
(:func:`bayes_talk.corpus.renderer_settings` of its format version), projected through
the AAM the test frames were projected through (``meta["aam_path"]``), and mean-removed per
utterance like the truth::

    z_k = P(render(face_landmarks(I, rng_k))) - mean_t(...),   mean_K = (1/K) sum_k z_k,
    s^2 = across-draw sample variance (ddof 1) per frame and dimension.

Finite-sample bias. The truth is one more independent draw, so per entry
``E (z - mean_K)^2 = E (z - mu)^2 + sigma^2 / K``: the K-draw average scores worse than the
ideal oracle by ``sigma^2 / K``. :class:`~bayes_talk.evaluation.systems.Prediction` carries ``mse_bias = s^2 / K``; the
harness reports, beside the raw figures, ``mse_corrected = mse - mean(s^2 / K)`` and
``nmse_corrected = nmse - mean_d(mean_t(s^2_td / K) / v_d)`` (unbiased for the K -> inf
oracle, since ``E s^2 = sigma^2``). The gain fractions use the corrected oracle figures.
ACC (correlation) is reported uncorrected (slightly pessimistic for the oracle).
The predictive variance is that of a new draw around ``mean_K``: ``s^2 (1 + 1/K)``.

Gain fraction (:func:`add_gain_fractions`): for every method, on AMSE and on NMSE,
``(zero - method) / (zero - oracle)``: 0 = no better than a still face, 1 = as good as
the generator itself. Only when both ``zero`` and ``oracle`` were run.
"""
from __future__ import annotations

import warnings
from typing import Any

import numpy as np

__all__ = ["add_gain_fractions", "corpus_generator", "gain_fraction", "score_with_ceiling"]


def corpus_generator(manifest: dict) -> str:
    """Which generator made a corpus: ``espeak`` / ``vtl`` (built; the manifest's
    ``speech``, espeak before it existed) or ``user`` (recorded data)."""
    if manifest.get("kind") != "built":
        return "user"
    return str(manifest.get("speech", "espeak"))


def gain_fraction(zero: float | None, method: float | None, oracle: float | None) -> float | None:
    """``(zero - method) / (zero - oracle)``; None if undefined (missing or zero == oracle)."""
    if zero is None or method is None or oracle is None or zero == oracle:
        return None
    return float((zero - method) / (zero - oracle))


def _mean(entry: dict, *keys: str) -> float | None:
    for k in keys:
        v = entry.get(k)
        if isinstance(v, dict) and v.get("mean") is not None:
            return float(v["mean"])
    return None


def add_gain_fractions(methods: dict[str, Any]) -> bool:
    """Add ``gain_fraction = {"amse": .., "nmse": ..}`` to every method entry of an
    evaluation result when both ``zero`` and ``oracle`` are present (the oracle's
    bias-corrected figures when available). Returns whether it did."""
    if "zero" not in methods or "oracle" not in methods:
        return False
    z, o = methods["zero"], methods["oracle"]
    for entry in methods.values():
        entry["gain_fraction"] = {
            "amse": gain_fraction(_mean(z, "mse"), _mean(entry, "mse_corrected", "mse"),
                                  _mean(o, "mse_corrected", "mse")),
            "nmse": gain_fraction(_mean(z, "nmse"), _mean(entry, "nmse_corrected", "nmse"),
                                  _mean(o, "nmse_corrected", "nmse")),
        }
    return True


def score_with_ceiling(truth: list[np.ndarray], preds: dict[str, list[np.ndarray]],
                       biases: dict[str, list[np.ndarray]] | None = None) -> dict[str, dict[str, float]]:
    """AMSE, NMSE (bias-corrected where ``biases`` gives s^2/K), ACC and -- with ``zero``
    and ``oracle`` among ``preds`` -- the gain fractions of every method, for a list of
    test utterances (``make demo``; the harness computes the same per utterance).
    NMSE normalises by the pooled variance of the test truth, as the harness does."""
    from bayes_talk.evaluation.metrics import acc, mse, normalised_mse

    biases = biases or {}
    v = np.concatenate(truth).var(axis=0)
    keep = v > 0
    rows: dict[str, dict[str, Any]] = {}
    for name, p in preds.items():
        m = mse(truth, p)
        n = normalised_mse(truth, p, variance=v)
        if name in biases:
            b = [np.asarray(x).mean(axis=0) for x in biases[name]]
            m = m - np.array([x.mean() for x in b])
            n = n - np.array([np.mean(x[keep] / v[keep]) for x in b])
        with warnings.catch_warnings():  # zero is constant: its ACC is undefined (nan)
            warnings.simplefilter("ignore", RuntimeWarning)
            rows[name] = {"amse": float(np.mean(m)), "nmse": float(np.mean(n)), "acc": acc(truth, p)}
    if "zero" in rows and "oracle" in rows:
        z, o = rows["zero"], rows["oracle"]
        for r in rows.values():
            r["gain_amse"] = gain_fraction(z["amse"], r["amse"], o["amse"])
            r["gain_nmse"] = gain_fraction(z["nmse"], r["nmse"], o["nmse"])
    return rows
