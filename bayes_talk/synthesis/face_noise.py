"""What the latent path cannot explain: the face's observation model (docs/uncertainty.md).

The visual GP of a state model predicts the face from a latent point, N(μ_Z(x), σ²_Z(x))
(deena2010 eq. 10), around the explicit mean function c_t where the model has one
(``SwitchingConfig.context_mean``). Its noise level is fitted to *training* frames, whose
latents are free: they absorb face variation that the audio does not determine, so on new
speech the GP predictive alone is too narrow and its mean varies more than the truth does
with it. The face model therefore ends in an observation term, per AAM parameter d, for
frame t with phone class g(t) and latent draw x^k:

    z_td = c_td + a_d (μ_Z,d(x^k_t) − c_td) + √β_d σ_Z,d(x^k_t) ξ + ε_td,   ξ ~ N(0, 1),
    ε_td ~ Student-t(ν_d, 0, τ_{g(t),d}),   τ_{g,d} = τ_d exp(δ_{g,d})                   (N1)

* a_d: how much of the latent path's deviation from c_t predicts the face (1: all of it,
  0: the mean function alone);
* β_d: a scale of the GP's own predictive variance;
* τ_d, ν_d: scale and degrees of freedom of the part nothing in the model explains,
  heavy-tailed (ν_d small) where the errors are; δ_{g,d} its log-offset for the phone class
  g (the MPEG-4 viseme of the frame's label, :data:`~bayes_talk.data.phones.PHONE_TO_VISEME`:
  silence, bilabials, ... 15 classes), shrunk towards 0 where few frames support it.

All of them are fitted by ``train`` on held-out *training* utterances under the held-out
log score (:mod:`bayes_talk.calibration.face_noise`), never on the frames the GPs saw.

**As a mixture.** A Student-t is a scale mixture of Gaussians: ε = τ √λ η with
λ ~ InvGamma(ν/2, ν/2), η ~ N(0, 1). Given λ every term of (N1) is Gaussian, so the
predictive of a synthesis with K latent draws (the mixture (1) of
:mod:`bayes_talk.synthesis.result`) becomes

    p(z_td) = (1/K) Σ_k N(z_td; c_td + a_d (μ^k_td − c_td), β_d v^k_td + τ²_{g(t),d} λ_ktd)   (N2)

with λ_ktd = F⁻¹((π_td(k) + ½)/K), F the InvGamma(ν_d/2, ν_d/2) distribution function and
π_td a seeded random permutation of the K components per entry: stratified quantiles, so
the K components of every entry carry the whole Student-t, each component a different
part of its tails (for ν_d = ∞, λ = 1 and ε is Gaussian). A point synthesis (K = 1:
deena2010's Algorithms 1–2, the MAP) is first repeated to :data:`MIN_COMPONENTS`
components. The result is again a :class:`~bayes_talk.synthesis.result.SynthesisResult`,
so its mean, bands, density, CDF and draws follow exactly, for every inference method
alike (:meth:`FaceNoise.apply`).

The same term is the ``face`` site of the Pyro synthesis program
(:func:`bayes_talk.synthesis.joint.face_model`). At synthesis the face is not observed, so
the term leaves the posterior of the latent path unchanged: it adds to what is predicted
from every draw, not to what is inferred.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import stats

from bayes_talk.data.phones import PHONE_TO_VISEME, SILENCE, VISEME_NAMES
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["FACE_NOISE_FORMAT", "MIN_COMPONENTS", "N_CLASSES", "FaceNoise", "frame_classes", "mixing_scales"]

#: components a point synthesis is repeated to before the Student-t term is added
MIN_COMPONENTS = 64
#: phone classes of the scale τ_{g,d}: the MPEG-4 visemes
N_CLASSES = len(VISEME_NAMES)
FACE_NOISE_FORMAT = "bayes_talk.face_noise"
_VERSION = 1
#: ν at or above this is Gaussian (λ = 1)
GAUSSIAN_NU = 1e6


def frame_classes(labels: Sequence[str]) -> np.ndarray:
    """(T,) the phone class g(t) of each frame: the MPEG-4 viseme of its label (a label
    outside the phone set, e.g. a right-context suffix, by its first phone; silence
    otherwise)."""
    out = np.empty(len(labels), dtype=np.int64)
    for t, lab in enumerate(labels):
        p = str(lab).split("+", 1)[0].split("-", 1)[0].strip().lower()
        out[t] = PHONE_TO_VISEME.get(p, PHONE_TO_VISEME[SILENCE])
    return out


def mixing_scales(nu: np.ndarray, shape: tuple[int, int, int], seed: int) -> np.ndarray:
    """(K, T, D) the λ_ktd of (N2): for parameter d, the K stratified quantiles
    ((j + ½)/K, j = 0..K−1) of InvGamma(ν_d/2, ν_d/2) in a seeded random order per entry
    (t, d); 1 where ν_d ≥ :data:`GAUSSIAN_NU`. Deterministic in ``seed``."""
    K, T, D = shape
    nu = np.asarray(nu, dtype=np.float64)
    u = (np.arange(K) + 0.5) / K
    out = np.ones(shape)
    rng = np.random.default_rng([int(seed), 2**19])
    # one permutation of the K strata per entry: argsort of uniforms along the component axis
    order = np.argsort(rng.random((K, T, D)), axis=0)
    for d in range(D):
        if nu[d] < GAUSSIAN_NU:
            q = stats.invgamma.ppf(u, nu[d] / 2.0, scale=nu[d] / 2.0)
            out[:, :, d] = q[order[:, :, d]]
    return out


@dataclass
class FaceNoise:
    """The fitted observation term (N1) of the module docstring, per AAM parameter d.

    shrink: (D,) a_d; gp_scale: (D,) β_d; scale: (D,) τ_d; dof: (D,) ν_d (≥
        :data:`GAUSSIAN_NU`: Gaussian); class_offset: (N_CLASSES, D) δ_{g,d};
    control_var: (D,) the held-out mean squared error of this model's mean, the variance of
        the plain constant band N(mean, v_d) that ``evaluate`` holds the bands against;
    info: what it was fitted on (held-out utterances, frames, log score, coverage).
    """

    shrink: np.ndarray
    gp_scale: np.ndarray
    scale: np.ndarray
    dof: np.ndarray
    class_offset: np.ndarray
    control_var: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("shrink", "gp_scale", "scale", "dof", "control_var", "class_offset"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if not np.all(np.isfinite(v)):
                raise ValueError(f"face noise {name}: expected finite values, found {v}")
            setattr(self, name, v)
        D = self.shrink.shape
        if self.shrink.ndim != 1:
            raise ValueError(f"face noise shrink: expected shape (D,), found {self.shrink.shape}")
        for name in ("gp_scale", "scale", "dof", "control_var"):
            if getattr(self, name).shape != D:
                raise ValueError(f"face noise {name}: expected shape {D}, found {getattr(self, name).shape}")
        if self.class_offset.shape != (N_CLASSES, *D):
            raise ValueError(f"face noise class_offset: expected shape ({N_CLASSES}, {D[0]}), "
                             f"found {self.class_offset.shape}")
        if np.any(self.gp_scale < 0) or np.any(self.scale <= 0) or np.any(self.dof <= 0) or np.any(self.control_var <= 0):
            raise ValueError("face noise: expected gp_scale >= 0 and scale, dof, control_var > 0")

    @property
    def n_dims(self) -> int:
        """D, the AAM parameters the term is fitted for."""
        return int(self.shrink.shape[0])

    def describe(self) -> str:
        """One line: what the term is and how it covered the utterances it was fitted on."""
        cov = self.info.get("coverage", {})
        return ("face noise: fitted on {} held-out utterances; 90 % coverage there {:.3f}; shrinkage a {:.2f}-{:.2f}, "
                "dof {}".format(self.info.get("n_utterances", "?"), cov.get("0.9", float("nan")), self.shrink.min(),
                                self.shrink.max(), sorted({float(v) for v in np.minimum(self.dof, GAUSSIAN_NU)})))

    def class_scale(self, labels: Sequence[str]) -> np.ndarray:
        """(T, D) τ_{g(t),d} for the frames' labels."""
        return self.scale[None, :] * np.exp(self.class_offset[frame_classes(labels)])

    def apply(self, result: SynthesisResult, labels: Sequence[str]) -> SynthesisResult:
        """The predictive (N2) of ``result`` (the model's synthesis without this term, any
        inference method) for frames labelled ``labels``; seeded by ``result.seed``."""
        T, D = result.n_frames, result.n_dims
        if D != self.n_dims:
            raise ValueError(f"face noise fitted for {self.n_dims} AAM parameters; the synthesis has {D}")
        if len(labels) != T:
            raise ValueError(f"face noise: {len(labels)} labels for a synthesis of {T} frames")
        if result.diagnostics.get("face_noise"):
            raise ValueError("face noise: this synthesis already carries the observation term")
        res = result if result.n_draws >= MIN_COMPONENTS else _repeated(result, -(-MIN_COMPONENTS // result.n_draws))
        C, S = res.draw_mean.shape[:2]
        c = 0.0 if res.mean_function is None else res.mean_function[None, None]
        mean = c + self.shrink * (res.draw_mean - c)
        lam = mixing_scales(self.dof, (C * S, T, D), res.seed).reshape(C, S, T, D)
        var = self.gp_scale * res.draw_var + self.class_scale(labels)[None, None] ** 2 * lam
        return replace(res, draw_mean=mean, draw_var=var,
                       diagnostics={**res.diagnostics, "face_noise": True})

    def constant_band(self, result: SynthesisResult) -> SynthesisResult:
        """The plain constant band N(m_td, v_d) around ``result``'s mean (``control_var``):
        the control the bands are held against."""
        return SynthesisResult.gaussian(result.mean, np.broadcast_to(self.control_var, result.mean.shape).copy(),
                                        method=f"{result.method}-constant-band", seed=result.seed)

    # ------------------------------------------------------------------ saving
    def to_dict(self) -> dict[str, Any]:
        """The JSON form (saved in the switching model's ``estimator.json``)."""
        return {"format": FACE_NOISE_FORMAT, "version": _VERSION, "shrink": self.shrink.tolist(),
                "gp_scale": self.gp_scale.tolist(), "scale": self.scale.tolist(),
                "dof": [min(float(v), GAUSSIAN_NU) for v in self.dof],
                "class_offset": self.class_offset.tolist(), "classes": list(VISEME_NAMES),
                "control_var": self.control_var.tolist(), "info": self.info}

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "face noise") -> FaceNoise:
        """Read :meth:`to_dict`'s form; ValueError naming ``where`` and the problem."""
        if not isinstance(d, dict) or d.get("format") != FACE_NOISE_FORMAT:
            raise ValueError(f"{where}: expected a {FACE_NOISE_FORMAT} object, found "
                             f"{d.get('format') if isinstance(d, dict) else type(d).__name__!r}")
        if d.get("version") != _VERSION:
            raise ValueError(f"{where}: format version {d.get('version')!r}; this version reads {_VERSION}")
        if d.get("classes") != list(VISEME_NAMES):
            raise ValueError(f"{where}: phone classes {d.get('classes')!r}; expected {list(VISEME_NAMES)}")
        try:
            return cls(**{k: np.asarray(d[k], dtype=np.float64) for k in
                          ("shrink", "gp_scale", "scale", "dof", "class_offset", "control_var")},
                       info=dict(d.get("info") or {}))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{where}: missing or malformed field ({exc})") from exc


def _repeated(result: SynthesisResult, r: int) -> SynthesisResult:
    """``result`` with each component repeated ``r`` times along the draw axis (the same
    mixture, more components to carry (N2)'s scales)."""
    def rep(a):
        return None if a is None else np.repeat(a, r, axis=1)
    stats_ = {k: np.repeat(v, r, axis=1) for k, v in result.sample_stats.items()}
    return replace(result, draw_mean=rep(result.draw_mean), draw_var=rep(result.draw_var),
                   latent_draws=rep(result.latent_draws), sample_stats=stats_)
