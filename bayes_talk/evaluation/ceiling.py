"""The floor and the ceiling of an evaluation: methods ``zero`` and ``oracle`` (issue 9).

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
(:func:`bayes_talk.data.corpus.renderer_settings` of its format version), projected through
the AAM the test frames were projected through (``meta["aam_path"]``), and mean-removed per
utterance like the truth::

    z_k = P(render(face_landmarks(I, rng_k))) - mean_t(...),   mean_K = (1/K) sum_k z_k,
    s^2 = across-draw sample variance (ddof 1) per frame and dimension.

Finite-sample bias. The truth is one more independent draw, so per entry
``E (z - mean_K)^2 = E (z - mu)^2 + sigma^2 / K``: the K-draw average scores worse than the
ideal oracle by ``sigma^2 / K``. :class:`Prediction` carries ``mse_bias = s^2 / K``; the
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
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["OracleModel", "ZeroModel", "add_gain_fractions", "corpus_generator", "gain_fraction",
           "oracle_draws"]

#: generator draws per utterance of method ``oracle`` (SystemConfig.oracle_draws)
ORACLE_DRAWS = 32


@dataclass
class ZeroModel:
    """``zero``: predicts 0 (each utterance's own mean) with the training variance."""

    variance: np.ndarray | None = None

    def fit(self, train: list) -> ZeroModel:
        """Nothing to learn; returns ``self``."""
        z = np.concatenate([np.asarray(s.aam, np.float64) for s in train])
        self.variance = z.var(axis=0)
        return self

    def predict(self, seq) -> tuple[np.ndarray, np.ndarray]:
        """Zero mean and the utterance's own per-dimension variance (the still-face floor)."""
        if self.variance is None:
            raise RuntimeError("ZeroModel: call fit first")
        T = seq.n_frames
        return np.zeros((T, self.variance.size)), np.broadcast_to(self.variance, (T, self.variance.size)).copy()


def _generator_context(seq) -> dict:
    """What the oracle needs from a test utterance's meta; a clear error when absent."""
    meta = seq.meta or {}
    if meta.get("corpus_kind") != "built":
        raise ValueError(
            f"method 'oracle' needs a corpus built by `bayes-talk corpus build` (its face generator "
            f"is known); utterance {seq.name!r} comes from a {meta.get('corpus_kind', 'user')!r} corpus "
            f"({meta.get('label_path', 'unknown path')}). Use 'zero' and the baselines on user corpora.")
    missing = [k for k in ("intervals", "aam_path", "image_size", "renderer") if meta.get(k) is None]
    if missing:
        raise ValueError(f"method 'oracle': utterance {seq.name!r} lacks {missing} in its meta "
                         "(load it with bayes_talk.data.corpus.load_corpus)")
    return meta


def corpus_generator(manifest: dict) -> str:
    """Which generator made a corpus: ``espeak`` / ``vtl`` (built; the manifest's
    ``speech``, espeak before it existed) or ``user`` (recorded data)."""
    if manifest.get("kind") != "built":
        return "user"
    return str(manifest.get("speech", "espeak"))


def oracle_draws(intervals: list, n_frames: int, aam, *, n_draws: int, seed: int | list[int],
                 image_size: int, renderer: dict, fps: float = 25.0,
                 mean_removal: bool = True, speech: str = "espeak") -> np.ndarray:
    """(K, T, D) AAM parameters of ``n_draws`` generator draws for the given timing.

    Draw k uses ``np.random.default_rng([*seed, k])``; each is rendered with
    ``renderer`` (render_frames keyword arguments), projected through ``aam`` and, if
    ``mean_removal``, has its own per-utterance mean removed (as the corpus truth has).
    ``speech="vtl"`` (an articulatory corpus, :mod:`bayes_talk.data.articulatory`): the
    face's jaw and lips come from a fresh draw of the vocal tract's articulatory variation
    (``default_rng([*seed, k, 3])``) given the same phones and durations, the rest of the
    face from ``default_rng([*seed, k])`` -- the conditional mean then averages over both.
    """
    from bayes_talk.data.face import face_landmarks
    from bayes_talk.data.render import render_frames

    if int(n_draws) < 2:
        raise ValueError(f"oracle: n_draws must be >= 2 (the bias correction needs a variance), "
                         f"found {n_draws}")
    seed = list(np.atleast_1d(seed).astype(np.int64).tolist())
    if speech == "vtl":
        from bayes_talk.data.articulatory import articulatory_draws

        given = articulatory_draws(intervals, int(n_frames), fps,
                                   [np.random.default_rng([*seed, k, 3]) for k in range(int(n_draws))])
    elif speech == "espeak":
        given = [None] * int(n_draws)
    else:
        raise ValueError(f"oracle: unknown speech generator {speech!r} (expected 'espeak' or 'vtl')")
    out = []
    for k in range(int(n_draws)):
        lm = face_landmarks(intervals, int(n_frames), fps=fps, image_size=int(image_size),
                            rng=np.random.default_rng([*seed, k]), given=given[k])
        p = np.asarray(aam.project(render_frames(lm, image_size=int(image_size), **renderer), lm), np.float64)
        out.append(p - p.mean(axis=0) if mean_removal else p)
    return np.stack(out)


@dataclass
class OracleModel:
    """``oracle``: Monte-Carlo conditional mean of the generator given the true timing."""

    n_draws: int = ORACLE_DRAWS
    seed: int = 0

    def fit(self, train: list) -> OracleModel:  # nothing to learn: the generator is known
        """Nothing to learn (the generator is known); returns ``self``."""
        return self

    def predict(self, seq) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mean_K, predictive variance s^2 (1 + 1/K), finite-sample MSE bias s^2 / K)."""
        from bayes_talk.data.corpus.workers import cached_aam

        meta = _generator_context(seq)
        aam = cached_aam(str(meta["aam_path"]))
        # fresh randomness: a 4-entry seed never equals the corpus's [seed, i, 1] streams
        key = [int(self.seed), 9, zlib.crc32(str(seq.name).encode("utf-8"))]
        draws = oracle_draws(meta["intervals"], seq.n_frames, aam, n_draws=self.n_draws, seed=key,
                             image_size=int(meta["image_size"]), renderer=dict(meta["renderer"]),
                             mean_removal=bool(meta.get("mean_removed", True)),
                             speech=str(meta.get("speech", "espeak")))
        if draws.shape[1:] != np.shape(seq.aam):
            raise ValueError(f"method 'oracle': draws for {seq.name!r} have shape {draws.shape[1:]}, "
                             f"the utterance's features {np.shape(seq.aam)} (AAM {Path(meta['aam_path'])})")
        K = draws.shape[0]
        s2 = draws.var(axis=0, ddof=1)
        return draws.mean(axis=0), s2 * (1.0 + 1.0 / K), s2 / K


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
