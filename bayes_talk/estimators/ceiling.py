"""The floor and the ceiling of an evaluation as estimators: ``zero`` and ``oracle``
(registered in :data:`bayes_talk.estimators.registry.ESTIMATORS`).

``zero`` predicts every utterance's own mean, i.e. 0 after per-utterance mean removal
(deena2010 §3.2), with the training corpus's per-dimension variance as its predictive
variance. ``oracle`` is the Monte-Carlo conditional mean of a *built* corpus's generator
given the true phone timing, ``mean_K = (1/K) sum_k z_k`` with predictive variance
``s^2 (1 + 1/K)`` and the finite-sample MSE bias ``s^2 / K`` of the K-draw average; the
maths, and how the evaluation corrects for that bias, are in
:mod:`bayes_talk.evaluation.ceiling`.

Both are references, not methods: their mean is the target the methods are measured
against, so the evaluation never post-filters it (:attr:`Estimator.reference`).
"""
from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any, ClassVar, Self

import numpy as np

from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import Estimator
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["MSE_BIAS", "ORACLE_DRAWS", "OracleModel", "ZeroModel", "oracle_draws"]

#: generator draws per utterance of method ``oracle`` (SystemConfig.oracle_draws)
ORACLE_DRAWS = 32
#: the key of ``SynthesisResult.diagnostics`` holding a known (T, D) finite-sample excess of
#: the squared error (the oracle's s^2 / K), which the evaluation subtracts
MSE_BIAS = "mse_bias"


class ZeroModel(Estimator):
    """``zero``: predicts 0 (each utterance's own mean) with the training variance."""

    name: ClassVar[str] = "zero"
    reference: ClassVar[bool] = True

    def fit(self, train: list[Utterance]) -> Self:
        """Nothing to learn but the per-dimension variance of ``train``; returns ``self``."""
        z = np.concatenate([np.asarray(s.aam, np.float64) for s in train])
        self.variance_ = z.var(axis=0)
        return self

    def moments(self, seq: Utterance) -> tuple[np.ndarray, np.ndarray]:
        """Zero mean and the training corpus's per-dimension variance (the still-face floor)."""
        self._require_fitted()
        T = seq.n_frames
        return np.zeros((T, self.variance_.size)), np.broadcast_to(self.variance_, (T, self.variance_.size)).copy()

    def predict(self, seq: Utterance) -> np.ndarray:
        """The (T, D) zero trajectory."""
        return self.moments(seq)[0]

    def predict_var(self, seq: Utterance) -> np.ndarray:
        """The (T, D) training variance of every dimension."""
        return self.moments(seq)[1]

    def predict_dist(self, seq: Utterance) -> SynthesisResult:
        """N(0, training variance) per frame and dimension."""
        return SynthesisResult.gaussian(*self.moments(seq), method=self.name)

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        return {}, {"variance": self.variance_}

    def _set_state(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        self.variance_ = np.asarray(arrays["variance"], np.float64)


def _generator_context(seq: Utterance) -> dict:
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
                         "(load it with bayes_talk.corpus.load_corpus)")
    return meta


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
    from bayes_talk.corpus.render import render_frames
    from bayes_talk.data.face import face_landmarks

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


class OracleModel(Estimator):
    """``oracle``: Monte-Carlo conditional mean of the generator given the true timing."""

    name: ClassVar[str] = "oracle"
    reference: ClassVar[bool] = True

    def __init__(self, n_draws: int = ORACLE_DRAWS, seed: int = 0) -> None:
        self.n_draws, self.seed = n_draws, seed

    def fit(self, train: list[Utterance]) -> Self:
        """Nothing to learn (the generator is known); returns ``self``."""
        self.n_train_ = len(train)
        return self

    def moments(self, seq: Utterance) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mean_K, predictive variance s^2 (1 + 1/K), finite-sample MSE bias s^2 / K)."""
        from bayes_talk.corpus.workers import cached_aam

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

    def predict(self, seq: Utterance) -> np.ndarray:
        """The (T, D) K-draw average."""
        self._require_fitted()
        return self.moments(seq)[0]

    def predict_dist(self, seq: Utterance) -> SynthesisResult:
        """N(mean_K, s^2 (1 + 1/K)) per entry, with ``diagnostics[MSE_BIAS]`` = s^2 / K."""
        self._require_fitted()
        mean, var, bias = self.moments(seq)
        return SynthesisResult.gaussian(mean, var, method=self.name, diagnostics={MSE_BIAS: bias})

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        return {"n_train": self.n_train_}, {}

    def _set_state(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        self.n_train_ = int(meta["n_train"])
