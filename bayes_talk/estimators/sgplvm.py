"""The single-model system of deena2009: one SGPDM over audio and visual features with an
MLP back-constraint from audio and GP dynamics (d = 8), synthesised by sequence
optimisation (eq. 9) from one of two initialisers:

* SGPLVM A — the back-constraint X* = g(Ŷ; φ);
* SGPLVM B — HMM/Viterbi over a random subset of training latent points (§4.2).

Training frames are capped (``max_frames``, whole 25-frame chunks chosen with the seed)
because one GP over a whole corpus costs O(N³).

Early stopping (``validation_frames``, our addition; docs/model.md "Latent collapse"):
the MAP objective of this model is maximised by shrinking the back-constrained latents
to a point, after which the visual prediction is the training mean. Training therefore
monitors the visual RMS error of SGPLVM A's prediction μ_Z(g(ŷ)) on held-out chunks
(taken from the chunks left over by the frame cap, else from the chosen ones) and keeps
the parameters with the lowest error. The same held-out chunks then calibrate the
visual predictive variance (:meth:`SGPDM.calibrate_variance`, one factor per AAM
parameter, at the latents SGPLVM A's sequence optimisation finds for each chunk): an
early-stopped MAP fit reports noise levels far below its real error.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import numpy as np

from bayes_talk.base.files import read_model_files
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import Estimator
from bayes_talk.gp.threads import torch_threads
from bayes_talk.models.sgpdm import SGPDM, SGPDMConfig
from bayes_talk.synthesis.initialisers import INITIALISERS, initialise
from bayes_talk.synthesis.latents import infer_latents
from bayes_talk.synthesis.result import SynthesisResult


class SGPLVM(Estimator):
    """deena2009's shared GPLVM with back-constraint and dynamics (an estimator)."""

    synthesis_options: ClassVar[dict[str, tuple[str, ...]]] = {"init": tuple(INITIALISERS)}

    def __init__(self, latent_dim: int = 8, max_frames: int = 1500, chunk: int = 25, max_iter: int = 200,
                 init: str = "back-constraint", seed: int = 0, validation_frames: int = 300):
        if init not in INITIALISERS:
            raise ValueError(f"unknown initialiser {init!r}; choose one of {sorted(INITIALISERS)}")
        if validation_frames < 0:
            raise ValueError(f"validation_frames must be >= 0, got {validation_frames}")
        self.latent_dim, self.max_frames, self.chunk = latent_dim, max_frames, chunk
        self.max_iter, self.init, self.seed = max_iter, init, seed
        self.validation_frames = validation_frames
        self.calibration_iter = 100

    @property
    def name(self) -> str:  # type: ignore[override]
        """Method name: ``sgplvm-a`` (back-constraint init.), ``sgplvm-b`` (HMM) or ``sgplvm-nn``."""
        return "sgplvm-a" if self.init == "back-constraint" else "sgplvm-b" if self.init == "hmm" else "sgplvm-nn"

    def fit(self, train: Sequence[Utterance]) -> SGPLVM:
        """Train on whole 25-frame chunks of ``train`` (≤ ``max_frames`` frames), early-stopped
        on ≤ ``validation_frames`` held-out frames (0: no early stopping, ``max_iter`` iterations)."""
        if not train:
            raise ValueError("no training sequences")
        rng = np.random.default_rng(self.seed)
        chunks = [(i, a, min(a + self.chunk, s.n_frames)) for i, s in enumerate(train)
                  for a in range(0, s.n_frames, self.chunk)]
        order = [chunks[j] for j in rng.permutation(len(chunks))]
        chosen, rest = _take(order, self.max_frames)
        held = []
        if self.validation_frames > 0:
            if sum(b - a for _, a, b in rest) < self.validation_frames // 2:  # too few left over: hold out chosen chunks
                rest, chosen = chosen[:max(1, len(chosen) // 7)], chosen[max(1, len(chosen) // 7):]
            held, _ = _take(rest, self.validation_frames)
        if not chosen:
            raise ValueError(f"too few training frames ({sum(s.n_frames for s in train)}) to train an SGPLVM")
        chosen.sort()
        audio = np.vstack([train[i].mfcc[a:b] for i, a, b in chosen])
        visual = np.vstack([train[i].aam[a:b] for i, a, b in chosen])
        cfg = SGPDMConfig(latent_dim=self.latent_dim, back_constraint="audio", init="pca-concat",
                          max_iter=self.max_iter, seed=self.seed)
        self.training_chunks_, self.validation_chunks_ = chosen, sorted(held)
        monitor = None
        if held:
            a_val = [train[i].mfcc[a:b] for i, a, b in self.validation_chunks_]
            z_val = np.vstack([train[i].aam[a:b] for i, a, b in self.validation_chunks_])

            def monitor(model: SGPDM) -> float:
                X = initialise("back-constraint", model, "audio", np.vstack(a_val))
                mu, _ = model.predict_view("visual", X)
                return float(np.sqrt(np.mean((mu - z_val) ** 2)))

        with torch_threads(1):  # as every other GP entry point (bayes_talk.gp.threads)
            self.model_ = SGPDM.from_config(cfg).fit({"audio": audio, "visual": visual},
                                                     seq_lengths=[b - a for _, a, b in chosen], monitor=monitor)
            if held:  # calibrate at the latents SGPLVM A's sequence optimisation finds for each chunk
                X_val = np.vstack([infer_latents(self.model_, "audio", y, "back-constraint", "sequence",
                                                 max_iter=self.calibration_iter) for y in a_val])
                self.model_.calibrate_variance("visual", X_val, z_val)
        return self

    def _is_fitted(self) -> bool:
        return hasattr(self, "model_")

    def synthesize(self, mfcc: np.ndarray, labels=None, init: str | None = None,
                   max_iter: int = 100) -> SynthesisResult:
        """Sequence optimisation (eq. 9) of the latents of ``mfcc`` from initialiser ``init``
        (None: the estimator's), then the visual GP's Gaussian predictive at them (eq. 10), a
        one-component :class:`~bayes_talk.synthesis.result.SynthesisResult`; ``labels`` unused."""
        self._require_fitted()
        with torch_threads(1):  # small L-BFGS-B problems: extra BLAS threads only contend (gp.threads)
            X = infer_latents(self.model_, "audio", mfcc, init or self.init, "sequence", max_iter=max_iter)
            mu, var = self.model_.predict_view("visual", X)
        return SynthesisResult.gaussian(mu, var, X, method="sgplvm")

    def predict(self, seq: Utterance, **kw) -> np.ndarray:
        """Mean visual trajectory of ``seq`` (its mfcc only)."""
        return self.synthesize(seq.mfcc, seq.labels, **kw).mean

    def predict_dist(self, seq: Utterance, **kw) -> SynthesisResult:
        """Mean, calibrated variance and latents of ``seq``'s visual trajectory."""
        return self.synthesize(seq.mfcc, seq.labels, **kw)

    def _get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        meta, arrays = self.model_.state()
        return {"model": meta, "calibration_iter": self.calibration_iter,
                "training_chunks": _chunks(getattr(self, "training_chunks_", None)),
                "validation_chunks": _chunks(getattr(self, "validation_chunks_", None))}, arrays

    def _set_state(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        with torch_threads(1):  # the predictors' Cholesky factors exactly as fit computed them
            self.model_ = SGPDM.from_state(meta["model"], arrays)
        self.calibration_iter = int(meta["calibration_iter"])
        for k in ("training_chunks", "validation_chunks"):
            if meta.get(k) is not None:
                setattr(self, k + "_", [tuple(c) for c in meta[k]])

    @classmethod
    def read_legacy(cls, path: str | os.PathLike) -> SGPLVM:
        """A model saved in the earlier per-family layout: ``<path>.json`` + ``<path>.npz`` (a
        trained-model directory's ``sgpdm.*``). One saved before the
        estimator's settings were recorded keeps its latent dimension and the defaults."""
        path = Path(path)
        meta, arrays = read_model_files(path.with_suffix(".json"), path.with_suffix(".npz"))
        est = meta.get("estimator") if isinstance(meta, dict) else None
        with torch_threads(1):
            model = SGPDM.from_state(meta, arrays)
        if est is not None:
            obj = cls(**est["params"])
            obj.calibration_iter = int(est.get("calibration_iter", obj.calibration_iter))
        else:
            obj = cls(latent_dim=model.config.latent_dim)
        obj.model_ = model
        return obj


def _chunks(chunks: list | None) -> list | None:
    """(utterance, start, stop) chunks as JSON lists of ints."""
    return None if chunks is None else [[int(x) for x in c] for c in chunks]


def _take(chunks: list[tuple[int, int, int]], max_frames: int) -> tuple[list, list]:
    """Greedily take chunks (in the given order) while the total stays ≤ max_frames;
    returns (taken, the rest)."""
    taken, rest, n = [], [], 0
    for c in chunks:
        if n + c[2] - c[1] <= max_frames:
            taken.append(c)
            n += c[2] - c[1]
        else:
            rest.append(c)
    return taken, rest
