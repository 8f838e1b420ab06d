"""How an evaluation protocol builds, trains and runs the systems it compares
(docs/evaluation.md), every one through the estimator protocol and the registry.

Every *method* is a way of producing visual features for a test utterance; every method
belongs to a *family*, the model that must be trained for it. Both are declared once, in
:mod:`bayes_talk.estimators.registry` (``ESTIMATORS``, ``METHODS``); this module adds the
protocol's settings (:class:`SystemConfig`) and runs every method the same way: build,
``fit``, ``predict_dist(utt, **options)`` (``predict`` for a point method). Methods of one
family share one trained model, so the harness trains each family once per split:

==========================  ==================  ==========================================
method                      family              what it is
==========================  ==================  ==========================================
ssgpdm-vlmm-optimise        ssgpdm-vlmm         deena2010 Algorithm 1, VLMM states
ssgpdm-vlmm-predict         ssgpdm-vlmm         deena2010 Algorithm 2, VLMM states
ssgpdm-phone-optimise       ssgpdm-phone        Algorithm 1, phone states (SSGPDM-phoneme)
ssgpdm-phone-predict        ssgpdm-phone        Algorithm 2, phone states
ssgpdm-vlmm-posterior       ssgpdm-vlmm         ours: mean and variance of the whole-utterance
                                                synthesis posterior (Laplace), VLMM states
ssgpdm-phone-posterior      ssgpdm-phone        the same with phone states
ssgpdm-vlmm-rc-posterior    ssgpdm-vlmm-rc      the posterior with right-context (anticipatory)
ssgpdm-phone-rc-posterior   ssgpdm-phone-rc     states, bayes_talk.models.right_context (the
                                                phone-rc family, the default model, also sees
                                                ±2 frames of audio: registry.FAMILY_DEFAULTS)
ssgpdm-vlmm-rc-optimise     ssgpdm-vlmm-rc      Algorithm 1 with right-context states
ssgpdm-phone-rc-optimise    ssgpdm-phone-rc
sgplvm-a                    sgplvm              deena2009, back-constraint initialiser
sgplvm-b                    sgplvm              deena2009, HMM/Viterbi initialiser
voice-puppetry              voice-puppetry      Brand (1999)
slds                        slds                switching LDS with known labels
dpds                        dpds                englebienne2008
hmm-mean                    hmm-mean            per-phone mean face
context-ridge               context-ridge       ridge on label/MFCC context windows
context-mlp                 context-mlp         one-hidden-layer MLP on the same windows
zero                        zero                each utterance's mean (0 after mean removal)
oracle                      oracle              generator average given the true timing
                                                (built corpora only; the ceiling)
sparse-sgpdm                sparse-sgpdm        ours: one sparse SGPDM on every
                                                training frame, sequence optimisation
==========================  ==================  ==========================================

``zero`` and ``oracle`` bracket every method: see :mod:`bayes_talk.evaluation.ceiling`
(the oracle's finite-sample bias correction, the achievable-gain fraction).

The ``*-posterior`` methods (our addition, docs/uncertainty.md) replace Algorithm 1's path by the
posterior over the whole utterance's latents (:mod:`bayes_talk.synthesis.joint`; Laplace
approximation at the joint MAP, :func:`~bayes_talk.posterior.sampling.sample_synthesis`,
``posterior_draws`` draws) and report the mean and variance of the resulting visual
mixture, i.e. the Bayes estimate under squared error rather than the mode.

Our GP methods return a predictive variance with the mean (``Prediction.var``); so do the
context regressions (their cross-validated / held-out residual variance, ``predict_var``);
the other baselines return a mean only. ``log_likelihood`` gives a per-utterance test
log-likelihood where the method defines one: the baselines' own
``log_likelihood(seq)``, and for our methods the Gaussian predictive density
Σ_t Σ_d ln N(z_td; μ_td, σ²_td) (frame-wise marginals: not the joint density of the
trajectory, so it is comparable with the baselines only loosely).
"""
from __future__ import annotations

import copy
import inspect
import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bayes_talk.calibration.bands import CALIBRATED_MODELS, CALIBRATIONS, HOLDOUT_FRACTION
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.base import Estimator
from bayes_talk.estimators.calibrated import BandCalibrated
from bayes_talk.estimators.ceiling import MSE_BIAS
from bayes_talk.estimators.registry import (
    ESTIMATORS,
    Method,
    make_estimator,
    methods,
    model_families,
    model_name,
    model_settings,
)
from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.evaluation.scoring import SAMPLE_DRAWS
from bayes_talk.posterior.methods import DEFAULT_DRAWS
from bayes_talk.synthesis.face_noise import FaceNoise
from bayes_talk.synthesis.result import SynthesisResult
from bayes_talk.synthesis.segment_objective import SEGMENT_MAX_ITER

__all__ = [
    "DEFAULT_MODELS",
    "FAMILIES",
    "METHODS",
    "SHARED_ARGUMENTS",
    "Method",
    "Prediction",
    "SystemConfig",
    "build_family",
    "calibrated_method",
    "fit_calibrated_family",
    "fit_family",
    "get_method",
    "group_by_family",
    "log_likelihood",
    "predict",
    "resolve_methods",
]

log = logging.getLogger(__name__)

#: variance floor applied to predictive variances before calibration metrics
VAR_FLOOR = 1e-10


def _default(fn: Any, param: str) -> Any:
    """The default of ``fn``'s argument ``param``: the family's own default is the one source."""
    return inspect.signature(fn).parameters[param].default


#: constructor argument -> the :class:`SystemConfig` field shared by every model that sets it,
#: in every estimator whose constructor takes the argument (``random_state``: scikit-learn's
#: name of a seed)
SHARED_ARGUMENTS: dict[str, str] = {"latent_dim": "latent_dim", "seed": "seed", "random_state": "seed"}

#: the evaluation's settings of a model where they are not its estimator's defaults
#: (:attr:`SystemConfig.models`): the sparse SGPDM with fewer inducing inputs and iterations
DEFAULT_MODELS: dict[str, dict[str, Any]] = {"sparse-sgpdm": {"n_inducing": 150, "max_iter": 200}}


@dataclass
class SystemConfig:
    """Settings of every method, fixed by a protocol (see :mod:`bayes_talk.evaluation.protocols`).

    Shared by every model (each default is read from the models' own defaults: one source):

    latent_dim: d of our GP models (8 in deena2009, 6 in deena2010), given to every estimator
        whose constructor takes ``latent_dim``.
    seed: seeds every model (the constructor argument ``seed``, or ``random_state``), the
        posterior draws and the band calibration.
    synth_max_iter: optimiser iterations per segment / utterance of deena2010's Algorithms 1-2.
    posterior_draws: posterior draws of the ``*-posterior`` methods.
    lowpass_hz: optional zero-phase low-pass (Hz) applied to every method's predicted mean,
        the post-filter of deena2010 §4.2.3 (None: off); variances are left as predicted.
        Not to ``zero`` and ``oracle``: the ceiling is the generator's mean with its
        finite-draw bias removed, and a filter would both change that bias and cut the
        generator's own motion above the cut-off (4 Hz took the oracle's AMSE on our
        held-out sentences from 3.28 to 4.30: a filtered "ceiling" is no ceiling).
    torch_threads: torch intra-op threads while fitting and synthesising (1: the GP
        problems here are small, and extra threads oversubscribe a shared machine; see
        :mod:`bayes_talk.gp.threads`).
    band_calibration, calibrated_model: the band calibration of the ``*-posterior`` methods.
    sample_draws: predictive draws (N >= 2, seeded by ``seed``) of the sample-based landmark
        metrics of a method whose predictive mixes over draws of the path (diversity, mean-of-samples and
        best-of-N lip error; :func:`bayes_talk.evaluation.scoring.landmark_metrics`).

    Per model (a family, or the families of one estimator class sharing its settings:
    :func:`bayes_talk.estimators.registry.model_name`, e.g. "ssgpdm" for every switching
    SGPDM), so that a family's settings are declared by its registration alone:

    models: model -> constructor arguments of its estimator (``get_params`` names; those a
        family fixes and the shared ones above are refused). An argument not given keeps the
        family's default (registry ``FAMILY_DEFAULTS``), then the class's. Default
        :data:`DEFAULT_MODELS`; a given mapping replaces it (``get_protocol`` merges).
    synthesis: model -> keyword arguments of its estimator's ``predict_dist`` given to every
        method of the model (e.g. ``{"sgplvm": {"max_iter": 30}}``, the SGPLVM's
        sequence-optimisation iterations).
    """

    latent_dim: int = _default(SwitchingSGPDM, "latent_dim")
    seed: int = 0
    synth_max_iter: int = SEGMENT_MAX_ITER
    lowpass_hz: float | None = None
    posterior_draws: int = DEFAULT_DRAWS["laplace"]
    torch_threads: int = 1
    #: fraction of the training utterances held out to fit the band calibration of the
    #: ``*-posterior`` methods (bayes_talk.calibration.bands); None: raw bands only
    band_calibration: float | None = HOLDOUT_FRACTION
    #: which model the calibration is scored with (CALIBRATED_MODELS, as ``train --calibrated-model``)
    calibrated_model: str = "refit"
    #: what is fitted on the held-out utterances (CALIBRATIONS, as ``train --calibration``)
    calibration: str = "noise"
    sample_draws: int = SAMPLE_DRAWS
    models: dict[str, dict[str, Any]] = field(default_factory=lambda: copy.deepcopy(DEFAULT_MODELS))
    synthesis: dict[str, dict[str, Any]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.band_calibration is not None and not 0 < self.band_calibration < 1:
            raise ValueError(f"band_calibration must be a fraction in (0, 1) or None, got {self.band_calibration!r}")
        if self.calibrated_model not in CALIBRATED_MODELS:
            raise ValueError(f"calibrated_model must be one of {CALIBRATED_MODELS}, got {self.calibrated_model!r}")
        if self.calibration not in CALIBRATIONS:
            raise ValueError(f"calibration must be one of {CALIBRATIONS}, got {self.calibration!r}")
        if self.lowpass_hz is not None and not self.lowpass_hz > 0:
            raise ValueError(f"lowpass_hz must be > 0 or None, got {self.lowpass_hz!r}")
        if not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")
        for k in ("latent_dim", "synth_max_iter", "posterior_draws", "torch_threads"):
            v = getattr(self, k)
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{k} must be a positive integer, got {v!r}")
        if not isinstance(self.sample_draws, (int, np.integer)) or self.sample_draws < 2:
            raise ValueError(f"sample_draws must be an integer >= 2 (the diversity compares pairs of draws), "
                             f"got {self.sample_draws!r}")
        self._check_models()
        self._check_synthesis()

    def _check_models(self) -> None:
        """Every ``models`` entry names a model and constructor arguments of its estimator,
        and its families build with them (the estimator's own validation)."""
        for model, params in _mapping(self.models, "models").items():
            families = model_families(model)
            given = set(_mapping(params, f"models[{model!r}]"))
            shared = sorted(given & set(SHARED_ARGUMENTS))
            if shared:
                raise ValueError(f"models[{model!r}]: {shared} are shared by every model: set "
                                 f"{sorted({SHARED_ARGUMENTS[k] for k in shared})} of SystemConfig instead")
            allowed = model_settings(model)
            unknown = sorted(given - set(allowed))
            if unknown:
                raise ValueError(f"models[{model!r}]: unknown setting(s) {unknown}; the constructor arguments "
                                 f"{model} takes: {', '.join(allowed)}")
            for family in families:
                build_family(family, self)

    def _check_synthesis(self) -> None:
        """Every ``synthesis`` entry names a model and ``predict_dist`` keywords its methods
        leave open."""
        valid = methods()
        for model, opts in _mapping(self.synthesis, "synthesis").items():
            families = model_families(model)
            given = set(_mapping(opts, f"synthesis[{model!r}]"))
            taken = {k for m in valid.values() if m.family in families for k in (*m.options, *m.settings)}
            if given & taken:
                raise ValueError(f"synthesis[{model!r}]: {sorted(given & taken)} are set by the methods of "
                                 f"{model} (their options, or a shared setting of SystemConfig)")
            params = inspect.signature(ESTIMATORS[families[0]][0].predict_dist).parameters
            if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
                unknown = sorted(given - set(params))
                if unknown:
                    raise ValueError(f"synthesis[{model!r}]: {unknown} are not keyword arguments of "
                                     f"{ESTIMATORS[families[0]][0].__name__}.predict_dist")


def _mapping(value: Any, what: str) -> Mapping:
    if not isinstance(value, Mapping):
        raise TypeError(f"{what} must be a mapping, got {value!r}")
    return value


#: every method ``evaluate`` can run when this module was imported (the registry's
#: :func:`~bayes_talk.estimators.registry.methods`; :func:`resolve_methods` reads it afresh)
METHODS: dict[str, Method] = methods()

FAMILIES: tuple[str, ...] = tuple(ESTIMATORS)


@dataclass
class Prediction:
    """mean: (T, D_z); var: (T, D_z) predictive variance, or None for a point predictor;
    mse_bias: (T, D_z) known finite-sample excess of the squared error (``oracle``'s
    s^2 / K), subtracted in the ``*_corrected`` metrics; None for every other method;
    result: the method's :class:`~bayes_talk.synthesis.result.SynthesisResult` (its bands,
    :meth:`interval`, are the ones scored, as ``synth`` writes them), or None; raw: when a
    band calibration was applied to ``result``, the uncalibrated one; control: the
    constant-band control fitted with that calibration (the calibrated mean with a constant
    per-parameter band, calibrated the same way), or None."""

    mean: np.ndarray
    var: np.ndarray | None = None
    mse_bias: np.ndarray | None = None
    result: Any = None
    #: the predictive before the band calibration, where one was applied
    raw: Any = None
    #: the constant-band control of a band-calibrated predictive
    control: Any = None
    #: the observation term's ablations (name -> predictive), where the model has them
    ablations: dict = field(default_factory=dict)

    def band(self, level: float) -> tuple[np.ndarray, np.ndarray]:
        """The central ``level`` band (lower, upper) of the predictive: the result's exact
        :meth:`~bayes_talk.synthesis.result.SynthesisResult.interval`, or the Gaussian
        N(mean, var) one for a prediction without a result."""
        from bayes_talk.synthesis.result import SynthesisResult

        if self.var is None:
            raise ValueError("a point prediction has no bands")
        res = self.result if self.result is not None else SynthesisResult.gaussian(self.mean, self.var,
                                                                                   method="gaussian")
        return res.interval(level)


def get_method(name: str) -> Method:
    """The method ``name`` of the registry (ValueError listing the valid names)."""
    return methods()[resolve_methods([name])[0]]


def resolve_methods(names: str | Iterable[str] | None, default: Sequence[str] = ()) -> list[str]:
    """Method names from a comma-separated string or an iterable (None: ``default``).

    Duplicates are dropped (first occurrence kept). An unknown name raises ValueError
    listing the valid ones.
    """
    valid = methods()
    if names is None:
        items = list(default)
    elif isinstance(names, str):
        items = [s.strip() for s in names.split(",") if s.strip()]
    else:
        items = [str(s).strip() for s in names]
    if not items:
        raise ValueError(f"no methods given; valid methods: {', '.join(valid)}")
    unknown = [s for s in items if s not in valid]
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(map(repr, unknown))}; "
                         f"valid methods: {', '.join(valid)}")
    return list(dict.fromkeys(items))


def group_by_family(names: Iterable[str]) -> dict[str, list[str]]:
    """family -> its requested methods, in first-appearance order (one training per family)."""
    out: dict[str, list[str]] = {}
    valid = methods()
    for name in resolve_methods(list(names)):
        out.setdefault(valid[name].family, []).append(name)
    return out


def build_family(family: str, cfg: SystemConfig) -> Estimator:
    """The unfitted estimator of ``family`` with the protocol's settings: the shared ones its
    constructor takes (:data:`SHARED_ARGUMENTS`) and its model's ``cfg.models`` entry; every
    other argument keeps the family's default (registry ``FAMILY_DEFAULTS``), then the class's."""
    if family not in ESTIMATORS:
        raise ValueError(f"unknown family {family!r}; valid families: {', '.join(ESTIMATORS)}")
    takes = set(make_estimator(family).get_params(deep=False)).difference(ESTIMATORS[family][1])
    shared = {arg: getattr(cfg, f) for arg, f in SHARED_ARGUMENTS.items() if arg in takes}
    return make_estimator(family, **shared, **cfg.models.get(model_name(family), {}))


def fit_family(family: str, train: Sequence[Utterance], cfg: SystemConfig, executor=None) -> Any:
    """Build and train the model of ``family`` on ``train`` (seeded by ``cfg.seed``).

    ``executor`` (anything with ``map``) is passed to an estimator whose ``fit`` takes one
    (the switching models' states); the others train in this process.
    """
    from bayes_talk.gp.threads import torch_threads

    if not train:
        raise ValueError("no training sequences")
    model = build_family(family, cfg)
    with torch_threads(cfg.torch_threads):
        if "executor" in inspect.signature(model.fit).parameters:
            return model.fit(list(train), executor=executor)
        return model.fit(list(train))


def predict(method: str, model: Any, seq: Utterance, cfg: SystemConfig) -> Prediction:
    """Visual features of ``seq`` (from its mfcc and labels only) by ``method``."""
    from bayes_talk.gp.threads import torch_threads

    m = get_method(method)
    with torch_threads(cfg.torch_threads):
        pred = _predict(m, model, seq, cfg)
    if cfg.lowpass_hz is not None and not getattr(model, "reference", False):
        from bayes_talk.synthesis.sequential import lowpass

        def filtered(r):   # every predictive of the method moves with its own filtered mean
            return None if r is None else r.shift(lowpass(r.mean, cfg.lowpass_hz) - r.mean)
        smooth = lowpass(pred.mean, cfg.lowpass_hz)
        res = None if pred.result is None else pred.result.shift(smooth - pred.mean)
        pred = Prediction(smooth, pred.var, result=res, raw=filtered(pred.raw), control=filtered(pred.control),
                          ablations={k: filtered(v) for k, v in pred.ablations.items()})
    return pred


def calibrated_method(names: Iterable[str]) -> str | None:
    """The posterior method (e.g. "laplace") a band calibration is fitted for among the
    methods ``names`` of one family, or None when none of them is a posterior method."""
    valid = methods()
    posterior = {valid[n].options["posterior"] for n in names if "posterior" in valid[n].options}
    return min(posterior) if posterior else None


def fit_calibrated_family(family: str, train: Sequence[Utterance], cfg: SystemConfig, method: str,
                          executor=None, progress=None) -> Any:
    """The model of ``family`` as ``train`` ships it, trained on ``train`` with
    ``cfg.calibration`` fitted on held-out training utterances (a ``cfg.band_calibration``
    fraction; by the scheme ``cfg.calibrated_model``; the held-out syntheses by the posterior
    ``method``): :func:`bayes_talk.estimators.calibrated.calibrate_model`, the observation
    term's ablations fitted too (scored beside it)."""
    from bayes_talk.estimators.calibrated import calibrate_model
    from bayes_talk.gp.threads import torch_threads

    if cfg.band_calibration is None:
        raise ValueError("band_calibration is off: nothing to fit")
    with torch_threads(cfg.torch_threads):
        return calibrate_model(build_family(family, cfg), list(train), cfg.calibrated_model, cfg.calibration,
                               holdout=cfg.band_calibration, n_draws=cfg.posterior_draws, seed=cfg.seed,
                               method=method, executor=executor, progress=progress, ablations=True)


def _predict(m: Method, model: Any, seq: Utterance, cfg: SystemConfig) -> Prediction:
    """The method's predictive: ``model.predict_dist`` with the method's options, its model's
    synthesis options (``cfg.synthesis``) and the shared settings it reads, band-calibrated
    where the model holds a calibration of that inference method; a point method's ``predict``."""
    if not m.has_variance:
        return Prediction(np.asarray(model.predict(seq), np.float64), None)
    options = {**m.options, **cfg.synthesis.get(model_name(m.family), {}),
               **{k: getattr(cfg, f) for k, f in m.settings.items()}}
    raw = control = None
    ablations: dict[str, SynthesisResult] = {}
    noise = getattr(model, "face_noise_", None)
    if isinstance(model, BandCalibrated):   # the raw predictive, and the control, scored beside it
        cal = model.calibration_
        raw = model.estimator_.predict_dist(seq, **options)
        r = model.calibrate(raw)
        control = cal.control_result(raw) if cal.control is not None else None
    elif noise is not None and "face_noise" in inspect.signature(model.predict_dist).parameters:
        # the predictive with the model's observation term, the GP predictive alone, the plain
        # constant band around the mean and the term's ablations, from one synthesis
        raw = model.predict_dist(seq, face_noise=False, **options)
        r = model.observe(raw, seq.labels)
        control = noise.constant_band(r)
        ablations = {k: FaceNoise.from_dict(d, where=f"face noise ablation {k}").apply(raw, seq.labels)
                     for k, d in noise.info.get("ablations", {}).items()}
    else:
        r = model.predict_dist(seq, **options)
    for w in r.warnings:   # those of the predictive reported (calibrated: BandCalibration.domain)
        log.warning("%s: %s", seq.name, w)
    bias = r.diagnostics.get(MSE_BIAS) if isinstance(r.diagnostics, dict) else None
    return Prediction(np.asarray(r.mean, np.float64), np.asarray(r.var, np.float64), mse_bias=bias, result=r,
                      raw=raw, control=control, ablations=ablations)


def log_likelihood(method: str, model: Any, seq: Utterance, pred: Prediction) -> float | None:
    """Test log-likelihood of ``seq.aam`` (total over the utterance), or None if undefined.

    Baselines: their own ``log_likelihood`` (where ``has_log_likelihood``). Our methods:
    Σ_t Σ_d ln N(z_td; μ_td, σ²_td) of the frame-wise Gaussian predictive.
    """
    m = get_method(method)
    if m.has_variance:
        if pred.var is None:
            return None
        v = np.maximum(pred.var, VAR_FLOOR)
        return float(-0.5 * np.sum(np.log(2 * np.pi * v) + (seq.aam - pred.mean) ** 2 / v))
    if getattr(model, "has_log_likelihood", False):
        return float(model.log_likelihood(seq))
    return None
