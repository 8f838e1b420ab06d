"""The single-model system of deena2009: one SGPDM over audio and visual features with an
MLP back-constraint from audio and GP dynamics (d = 8), synthesised by sequence
optimisation (eq. 9) from one of two initialisers:

* SGPLVM A — the back-constraint X* = g(Ŷ; φ);
* SGPLVM B — HMM/Viterbi over a random subset of training latent points (§4.2).

Training frames are capped (``max_frames``, whole 25-frame chunks chosen with the seed)
because one GP over a whole corpus costs O(N³).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from bayes_talk.data.sequence import Sequence as Utterance
from bayes_talk.models.sgpdm import SGPDM, SGPDMConfig
from bayes_talk.synthesis.initialisers import INITIALISERS


@dataclass
class SGPLVMResult:
    mean: np.ndarray
    var: np.ndarray
    latents: np.ndarray


class SGPLVM:
    """deena2009's shared GPLVM with back-constraint and dynamics."""

    def __init__(self, latent_dim: int = 8, max_frames: int = 1500, chunk: int = 25, max_iter: int = 200,
                 init: str = "back-constraint", seed: int = 0):
        if init not in INITIALISERS:
            raise ValueError(f"unknown initialiser {init!r}; choose one of {sorted(INITIALISERS)}")
        self.latent_dim, self.max_frames, self.chunk = latent_dim, max_frames, chunk
        self.max_iter, self.init, self.seed = max_iter, init, seed

    @property
    def name(self) -> str:
        return "sgplvm-a" if self.init == "back-constraint" else "sgplvm-b" if self.init == "hmm" else "sgplvm-nn"

    def fit(self, train: Sequence[Utterance]) -> SGPLVM:
        if not train:
            raise ValueError("no training sequences")
        rng = np.random.default_rng(self.seed)
        chunks = [(i, a, min(a + self.chunk, s.n_frames)) for i, s in enumerate(train)
                  for a in range(0, s.n_frames, self.chunk)]
        order = rng.permutation(len(chunks))
        chosen, n = [], 0
        for j in order:
            i, a, b = chunks[j]
            if n + b - a > self.max_frames:
                continue
            chosen.append(chunks[j])
            n += b - a
        chosen.sort()
        audio = np.vstack([train[i].mfcc[a:b] for i, a, b in chosen])
        visual = np.vstack([train[i].aam[a:b] for i, a, b in chosen])
        cfg = SGPDMConfig(latent_dim=self.latent_dim, back_constraint="audio", init="pca-concat",
                          max_iter=self.max_iter, seed=self.seed)
        self.model_ = SGPDM(cfg).fit({"audio": audio, "visual": visual}, seq_lengths=[b - a for _, a, b in chosen])
        return self

    def synthesize(self, mfcc: np.ndarray, labels=None, init: str | None = None, max_iter: int = 100) -> SGPLVMResult:
        X = self.model_.infer_latents("audio", mfcc, init or self.init, "sequence", max_iter=max_iter)
        mu, var = self.model_.predict_view("visual", X)
        return SGPLVMResult(mu, var, X)

    def predict(self, seq: Utterance, **kw) -> np.ndarray:
        return self.synthesize(seq.mfcc, seq.labels, **kw).mean

    def save(self, path) -> None:
        self.model_.save(path)

    @classmethod
    def load(cls, path, init: str = "back-constraint") -> SGPLVM:
        obj = cls(init=init)
        obj.model_ = SGPDM.load(path)
        obj.latent_dim = obj.model_.config.latent_dim
        return obj
