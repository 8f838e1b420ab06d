"""The switching shared GPDM as an estimator (deena2010; docs/switching.md).

:class:`SwitchingSGPDM` is the generative model of :mod:`bayes_talk.models.switching`
(``fit``, state lookup, its saved ``state``; ``save`` / ``load`` are the estimator's) with the
inference of :mod:`bayes_talk.synthesis` on top: ``synthesize`` runs deena2010's
Algorithm 1 or 2 (:func:`bayes_talk.synthesis.sequential.synthesize`), ``predict`` returns
its mean, ``predict_dist`` its mean and GP predictive variance. The whole-utterance
posterior is :func:`bayes_talk.posterior.sampling.sample_synthesis` (it takes this
estimator as its model). A model trained by ``train`` carries the face's observation term
(:class:`~bayes_talk.synthesis.face_noise.FaceNoise`, fitted on held-out training
utterances), and every prediction, whatever its inference method, ends with it.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import ClassVar

import numpy as np

from bayes_talk.calibration.bands import held_out_domain
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import Estimator
from bayes_talk.models.switching import SwitchingModel
from bayes_talk.posterior import sampling as synthesis_posterior
from bayes_talk.posterior.diagnostics import is_sampler_warning
from bayes_talk.posterior.methods import INFERENCE
from bayes_talk.synthesis.face_noise import FaceNoise
from bayes_talk.synthesis.result import SynthesisResult
from bayes_talk.synthesis.sequential import SEGMENT_MAX_ITER, synthesize

__all__ = ["SwitchingSGPDM"]


class SwitchingSGPDM(SwitchingModel, Estimator):
    """Switching shared GPDM: ``fit`` on utterances, ``synthesize`` / ``predict`` /
    ``predict_dist`` from audio + labels (constructor arguments: :class:`SwitchingConfig
    <bayes_talk.models.switching.SwitchingConfig>`)."""

    #: "posterior": the names of the inference table, a live view (a method added to it is a choice)
    synthesis_options: ClassVar[dict[str, tuple[str, ...]]] = {
        "algorithm": ("optimise", "predict"), "init": ("nn",), "posterior": INFERENCE.keys()}
    post_filter: ClassVar[bool] = True
    #: the face's observation term (N1 of bayes_talk.synthesis.face_noise), or None (the GP
    #: predictive alone): set by ``train`` from held-out training utterances
    face_noise_: FaceNoise | None = None

    def _is_fitted(self) -> bool:
        return bool(self.models_)

    def _get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        meta, arrays = self.state()
        if self.face_noise_ is not None:
            meta = {**meta, "face_noise": self.face_noise_.to_dict()}
        return meta, arrays

    def _set_state(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        self.restore(meta, arrays)
        noise = meta.get("face_noise")
        self.face_noise_ = None if noise is None else FaceNoise.from_dict(noise, where="switching model face_noise")

    def with_face_noise(self, noise: FaceNoise | None) -> SwitchingSGPDM:
        """This model with the observation term ``noise`` (None: without one); returns self."""
        if noise is not None and noise.n_dims != self.dims_[-1]:
            raise ValueError(f"face noise fitted for {noise.n_dims} AAM parameters; the model predicts {self.dims_[-1]}")
        self.face_noise_ = noise
        return self

    def synthesize(self, mfcc: np.ndarray, labels: Sequence[str], algorithm: str = "optimise",
                   smoothness: str | bool = True, lowpass_hz: float | None = None,
                   max_iter: int | None = None) -> SynthesisResult:
        """Visual features for new audio: see :func:`bayes_talk.synthesis.sequential.synthesize`
        (``max_iter`` None: its ``SEGMENT_MAX_ITER``)."""
        self._require_fitted()
        return synthesize(self, mfcc, labels, algorithm=algorithm, smoothness=smoothness,
                          lowpass_hz=lowpass_hz, max_iter=SEGMENT_MAX_ITER if max_iter is None else max_iter)

    def predict(self, seq: Utterance, **kw) -> np.ndarray:
        """Mean AAM trajectory for a test utterance (uses its mfcc and labels only): that of
        deena2010's sequential path, with the observation term's mean shrinkage where the
        model has one."""
        return self.predict_dist(seq, **kw).mean

    def predict_dist(self, seq: Utterance, posterior: str | None = None, *, n_draws: int | None = None,
                     seed: int = 0, log_warnings: bool = False, init: str = "nn", face_noise: bool = True,
                     **kw) -> SynthesisResult:
        """The predictive distribution of ``seq``'s visual features.

        ``posterior`` None: deena2010's sequential path (Algorithm 1, or 2 with
        ``algorithm="predict"``; ``kw`` as :meth:`synthesize`), its mean and GP predictive
        variance, with latents and segments. A method of
        :data:`~bayes_talk.posterior.methods.INFERENCE` (e.g. "laplace"): the
        whole-utterance synthesis posterior,
        :func:`bayes_talk.posterior.sampling.sample_synthesis` with ``n_draws``, ``seed``
        and ``kw``; its failed convergence checks are in ``.warnings`` (logged too with
        ``log_warnings``). ``init``: the initialiser of the path, nearest neighbour ("nn"),
        the only one of the switching model. ``face_noise``: end with the model's observation
        term (:attr:`face_noise_`, when it has one; False: the GP predictive alone)."""
        if init != "nn":
            raise ValueError(f"the switching model initialises by nearest neighbour ('nn'), not {init!r}")
        if posterior is None:
            res = self.synthesize(seq.mfcc, seq.labels, **kw)
        else:
            self._require_fitted()
            res = synthesis_posterior.sample_synthesis(self, seq.mfcc, seq.labels, method=posterior, n_draws=n_draws,
                                                       seed=seed, log_warnings=log_warnings, **kw)
        return self.observe(res, seq.labels) if face_noise else res

    def observe(self, result: SynthesisResult, labels) -> SynthesisResult:
        """``result`` (a synthesis without the observation term) with it: the predictive of
        the face (:meth:`FaceNoise.apply <bayes_talk.synthesis.face_noise.FaceNoise.apply>`);
        unchanged when the model has no term. Its warnings follow the held-out criterion
        (:func:`bayes_talk.calibration.bands.held_out_domain`, recorded under
        ``diagnostics["face_noise"]["domain"]``): the term was fitted on Laplace syntheses
        whose k̂ was above 0.7 too, so the k̂ is recorded, not gated; every other check stands."""
        if self.face_noise_ is None:
            return result
        out = self.face_noise_.apply(result, labels)
        dom = held_out_domain(result, self.face_noise_.info)
        warn = [w for w in result.warnings if not is_sampler_warning(result.method, w)] + dom["warning"]
        return replace(out, warnings=warn, diagnostics={**out.diagnostics, "face_noise": {"domain": dom}})
