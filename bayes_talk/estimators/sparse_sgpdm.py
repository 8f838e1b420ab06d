"""The evaluation system ``sparse-sgpdm``: one sparse shared GPDM
(:class:`~bayes_talk.models.sparse_sgpdm.SparseSGPDM`) on every frame of every training
utterance — the whole-corpus model deena2010 called intractable — and its synthesis: the
utterance's latents by maximising the sparse model's sequence density of the audio
(:func:`bayes_talk.synthesis.latents.infer_latents`, nearest-neighbour start), then the
visual GP predictive at them. Labels are not used."""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import numpy as np

from bayes_talk.base.files import read_model_files
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import Estimator
from bayes_talk.models.sparse_sgpdm import SparseSGPDM, SparseSGPDMConfig
from bayes_talk.synthesis.latents import infer_latents
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["CorpusSparseSGPDM"]


class CorpusSparseSGPDM(Estimator):
    """One :class:`SparseSGPDM` on all training frames (views ``audio`` = MFCCs, ``visual`` =
    AAM parameters, one sequence per utterance); ``synthesize`` as in the module docstring."""

    name: ClassVar[str] = "sparse-sgpdm"

    def __init__(self, latent_dim: int = 6, n_inducing: int = 200, max_iter: int = 300, seed: int = 0,
                 synth_max_iter: int = 100) -> None:
        self.latent_dim, self.n_inducing, self.max_iter = latent_dim, n_inducing, max_iter
        self.seed, self.synth_max_iter = seed, synth_max_iter

    def fit(self, train: Sequence) -> CorpusSparseSGPDM:
        """Train on all frames of ``train`` (utterances with ``mfcc``, ``aam``)."""
        if not train:
            raise ValueError("no training sequences")
        cfg = SparseSGPDMConfig(latent_dim=self.latent_dim, n_inducing=self.n_inducing,
                                max_iter=self.max_iter, seed=self.seed)
        views = {"audio": np.vstack([s.mfcc for s in train]), "visual": np.vstack([s.aam for s in train])}
        lens = [int(s.mfcc.shape[0]) for s in train]
        self.model_ = SparseSGPDM.from_config(cfg).fit(views, seq_lengths=lens)
        return self

    def synthesize(self, mfcc: np.ndarray, labels=None, max_iter: int | None = None) -> SynthesisResult:
        """Visual features (the one synthesis result type, a single Gaussian per frame)."""
        self._require_fitted()
        X = infer_latents(self.model_, "audio", np.asarray(mfcc, np.float64), "nn", "sequence",
                          max_iter=self.synth_max_iter if max_iter is None else max_iter)
        mu, var = self.model_.predict_view("visual", X)
        return SynthesisResult.gaussian(mu, var, X, method="sparse-sgpdm")

    def predict(self, seq: Utterance) -> np.ndarray:
        """Mean AAM trajectory of a test utterance (from its MFCCs)."""
        return self.synthesize(seq.mfcc, seq.labels).mean

    def predict_dist(self, seq: Utterance) -> SynthesisResult:
        """The visual GP predictive at the utterance's latents (:meth:`synthesize`)."""
        return self.synthesize(seq.mfcc, seq.labels)

    def _get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        meta, arrays = self.model_.state()
        return {"model": meta}, arrays

    def _set_state(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        self.model_ = SparseSGPDM.from_state(meta["model"], arrays)

    @classmethod
    def read_legacy(cls, path: str | os.PathLike) -> CorpusSparseSGPDM:
        """A system saved in the earlier per-family layout: ``<path>.json`` + ``<path>.npz`` (a
        trained-model directory's ``sparse_sgpdm.*``); one saved before
        the estimator's settings were recorded keeps its latent dimension and inducing
        inputs, the defaults for the rest. Errors name the damaged file."""
        path = Path(path)
        meta, arrays = read_model_files(path.with_suffix(".json"), path.with_suffix(".npz"))
        est = meta.get("estimator") if isinstance(meta, dict) else None
        model = SparseSGPDM.from_state(meta, arrays)
        obj = (cls(**est["params"]) if est is not None
               else cls(latent_dim=model.config.latent_dim, n_inducing=model.config.n_inducing))
        obj.model_ = model
        return obj
