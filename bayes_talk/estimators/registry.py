"""The one registry of what ``evaluate`` and ``synth`` can run.

:data:`ESTIMATORS`: method *families*, name -> estimator class and the constructor
arguments the family fixes: the papers' switching SGPDMs, the default model, deena2009's
SGPLVM, every baseline, the floor and ceiling (``zero``, ``oracle``) and ``sparse-sgpdm``.
A family is what is trained (``train --model``, :func:`bayes_talk.pipeline.new_model`; one
training per family and split in ``evaluate``).

:data:`METHODS`: the *methods* ``evaluate --methods`` compares, each a family with the
keyword arguments of its estimator's ``predict_dist`` (e.g. deena2010's Algorithm 1 or 2,
or the Laplace posterior, of one trained switching model). Every family that names no
method of its own is a method too, with no options, so adding a method is one estimator
class and one line in :data:`ESTIMATORS`.

A family's settings are its estimator's constructor arguments (``get_params``): an
evaluation protocol sets them by name for the family's *model* (:func:`model_name`: the
family, or the name the families of one class share, :data:`MODEL_NAMES`), so a new family
declares nothing in the evaluation layer (:class:`bayes_talk.evaluation.systems.SystemConfig`
``models``).

:func:`load_estimator`: any saved estimator, registered or wrapping one (the band-calibrated
wrapper), read back from the directory :meth:`Estimator.save
<bayes_talk.estimators.base.Estimator.save>` wrote; its descriptor names the class, so no
class is passed in. It also reads the layouts of earlier versions.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bayes_talk.base.bundle import BUNDLE_MANIFEST
from bayes_talk.estimators.base import ESTIMATOR_FILE, Estimator
from bayes_talk.estimators.baselines import REGISTRY as BASELINES
from bayes_talk.estimators.calibrated import BandCalibrated
from bayes_talk.estimators.ceiling import OracleModel, ZeroModel
from bayes_talk.estimators.sgplvm import SGPLVM
from bayes_talk.estimators.sparse_sgpdm import CorpusSparseSGPDM
from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.models.sgpdm import SGPDM
from bayes_talk.models.sparse_sgpdm import SparseSGPDM

__all__ = ["AUDIO_CONTEXT", "DEFAULT_MODEL", "ESTIMATORS", "FAMILY_DEFAULTS", "LEGACY_READERS", "METHODS", "MODEL_NAMES",
           "WRAPPERS", "Method", "load_estimator", "make_estimator", "model_families", "model_name", "model_settings"]

#: family name -> (estimator class, constructor arguments the family fixes)
ESTIMATORS: dict[str, tuple[type[Estimator], dict[str, Any]]] = {
    "ssgpdm-vlmm": (SwitchingSGPDM, {"states": "vlmm"}),
    "ssgpdm-phone": (SwitchingSGPDM, {"states": "phone"}),
    "ssgpdm-vlmm-rc": (SwitchingSGPDM, {"states": "vlmm", "right_context": True}),
    "ssgpdm-phone-rc": (SwitchingSGPDM, {"states": "phone", "right_context": True}),
    "ssgpdm-phone-ctx": (SwitchingSGPDM, {"states": "phone", "right_context": True}),
    "ssgpdm-phone-ctx-mean": (SwitchingSGPDM, {"states": "phone", "right_context": True, "context_mean": True}),
    "sgplvm": (SGPLVM, {}),
    **{name: (cls, {}) for name, cls in BASELINES.items()},
    "zero": (ZeroModel, {}),
    "oracle": (OracleModel, {}),
    "sparse-sgpdm": (CorpusSparseSGPDM, {}),
}
#: estimators that wrap a fitted one of a family (``train --calibrate-bands`` saves the wrapper)
WRAPPERS: tuple[type[Estimator], ...] = (BandCalibrated,)
#: the family ``train`` fits unless told otherwise: right-context phone states with an audio
#: context of ±2 frames whose visual GPs have the phonetic-context view as their mean function
#: (:data:`FAMILY_DEFAULTS`; docs/switching.md), the best model on our development sentences
#: (docs/results.md); "ssgpdm-vlmm" is deena2010's
DEFAULT_MODEL = "ssgpdm-phone-ctx-mean"
#: the audio context window (±frames, SwitchingConfig.audio_context) of our families with
#: one, its one setting: with ±2 frames and its band calibration, ``ssgpdm-phone-rc``
#: predicted better on every metric on our held-out sentences than with per-frame MFCCs and
#: put its 90 % band in range (docs/results.md); deena2010's families keep the per-frame
#: MFCCs (0, the SwitchingConfig default)
AUDIO_CONTEXT = 2
#: family name -> constructor arguments the family sets unless given (overridable, unlike the
#: fixed ones)
FAMILY_DEFAULTS: dict[str, dict[str, Any]] = {
    "ssgpdm-phone-rc": {"audio_context": AUDIO_CONTEXT},
    # the default's states and audio, with the phonetic-context view of labels ±8 frames
    # (SwitchingConfig.context_view; docs/switching.md)
    "ssgpdm-phone-ctx": {"audio_context": AUDIO_CONTEXT, "context_view": 8},
    # the same view as the explicit mean function of the visual mapping: the state models
    # explain the residual face (SwitchingConfig.context_mean; docs/switching.md); states with
    # fewer than 60 frames back off to their suffix (their visual noise, fitted on 12-25
    # frames, was the smallest of all states and their bands the most over-confident:
    # docs/results.md)
    "ssgpdm-phone-ctx-mean": {"audio_context": AUDIO_CONTEXT, "context_view": 8, "min_frames_per_state": 60},
}


#: estimator class -> the *model* name its families share: the key under which an evaluation
#: protocol sets the class's constructor arguments and synthesis options
#: (:class:`~bayes_talk.evaluation.systems.SystemConfig` ``models`` and ``synthesis``); a class
#: not listed is its family's own model. A family's settings are thus declared by its
#: registration alone: they are its estimator's constructor arguments (``get_params``).
MODEL_NAMES: dict[type[Estimator], str] = {SwitchingSGPDM: "ssgpdm"}


def model_name(family: str) -> str:
    """The model of ``family`` (:data:`MODEL_NAMES`; the family's own name by default)."""
    if family not in ESTIMATORS:
        raise ValueError(f"unknown method family {family!r}; choose one of {', '.join(ESTIMATORS)}")
    return MODEL_NAMES.get(ESTIMATORS[family][0], family)


def model_families(model: str) -> list[str]:
    """The families of ``model`` (ValueError listing the models when there is none)."""
    fams = [fam for fam in ESTIMATORS if model_name(fam) == model]
    if not fams:
        valid = sorted({model_name(f) for f in ESTIMATORS})
        raise ValueError(f"unknown model {model!r}; valid models: {', '.join(valid)}")
    return fams


def model_settings(model: str) -> tuple[str, ...]:
    """The constructor arguments a protocol may set for ``model``: those of its estimator
    (``get_params``) that none of its families fixes (:data:`ESTIMATORS`)."""
    fams = model_families(model)
    params = set(make_estimator(fams[0]).get_params(deep=False))
    return tuple(sorted(params.difference(*(ESTIMATORS[f][1] for f in fams))))


def make_estimator(name: str, **params: Any) -> Estimator:
    """An unfitted estimator of family ``name`` with ``params`` (others: the family's
    :data:`FAMILY_DEFAULTS`, then the class defaults)."""
    if name not in ESTIMATORS:
        raise ValueError(f"unknown method family {name!r}; choose one of {', '.join(ESTIMATORS)}")
    cls, fixed = ESTIMATORS[name]
    clash = sorted(set(fixed) & set(params))
    if clash:
        raise ValueError(f"{name}: {clash} are fixed by the family name")
    return cls(**fixed, **{**FAMILY_DEFAULTS.get(name, {}), **params})


@dataclass(frozen=True)
class Method:
    """One evaluated method: ``name`` (``evaluate --methods``), ``family`` (the trained
    estimator it uses, a key of :data:`ESTIMATORS`), ``label`` (how the papers call it),
    ``has_variance`` (its predictive variance is scored), ``options`` (keyword arguments
    of the estimator's ``predict_dist``), ``settings`` (``predict_dist`` keyword -> the
    evaluation setting shared by every model that supplies it, a field of
    :class:`bayes_talk.evaluation.systems.SystemConfig`; a model's own synthesis options
    are its ``SystemConfig.synthesis`` entry)."""

    name: str
    family: str
    label: str
    has_variance: bool
    options: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)


#: deena2010's sequential path (Algorithm 1 "optimise" or 2 "predict")
_ALGORITHM = {"max_iter": "synth_max_iter"}
#: the whole-utterance posterior (docs/uncertainty.md)
_POSTERIOR = {"n_draws": "posterior_draws", "seed": "seed"}


def _switching(name: str, family: str, label: str, how: str) -> Method:
    if how in ("optimise", "predict"):
        return Method(name, family, label, True, {"algorithm": how}, _ALGORITHM)
    return Method(name, family, label, True, {"posterior": how}, _POSTERIOR)


#: the methods with a name of their own (a family with options for its ``predict_dist``); a new
#: one is a line here (or, for a family with no options, nothing: :func:`methods`)
NAMED_METHODS: tuple[Method, ...] = (
    _switching("ssgpdm-vlmm-optimise", "ssgpdm-vlmm", "SSGPDM-VLMM seq. optimisation", "optimise"),
    _switching("ssgpdm-vlmm-predict", "ssgpdm-vlmm", "SSGPDM-VLMM seq. prediction", "predict"),
    _switching("ssgpdm-phone-optimise", "ssgpdm-phone", "SSGPDM-phoneme seq. optimisation", "optimise"),
    _switching("ssgpdm-phone-predict", "ssgpdm-phone", "SSGPDM-phoneme seq. prediction", "predict"),
    _switching("ssgpdm-vlmm-posterior", "ssgpdm-vlmm", "SSGPDM-VLMM utterance posterior (Laplace, ours)", "laplace"),
    _switching("ssgpdm-phone-posterior", "ssgpdm-phone", "SSGPDM-phoneme utterance posterior (Laplace, ours)",
               "laplace"),
    _switching("ssgpdm-vlmm-rc-posterior", "ssgpdm-vlmm-rc", "SSGPDM-VLMM + right context, posterior (ours)",
               "laplace"),
    _switching("ssgpdm-phone-rc-posterior", "ssgpdm-phone-rc",
               "SSGPDM-phoneme + right context + audio ±2, posterior (ours)", "laplace"),
    _switching("ssgpdm-phone-ctx-posterior", "ssgpdm-phone-ctx",
               "SSGPDM-phoneme + right context + audio ±2 + phonetic-context view ±8, posterior (ours)", "laplace"),
    _switching("ssgpdm-phone-ctx-mean-posterior", "ssgpdm-phone-ctx-mean",
               "SSGPDM-phoneme + right context + audio ±2, phonetic-context view ±8 as the visual mean "
               "function, posterior (ours)", "laplace"),
    _switching("ssgpdm-vlmm-rc-optimise", "ssgpdm-vlmm-rc", "SSGPDM-VLMM + right context, seq. optimisation",
               "optimise"),
    _switching("ssgpdm-phone-rc-optimise", "ssgpdm-phone-rc",
               "SSGPDM-phoneme + right context + audio ±2, seq. optimisation", "optimise"),
    Method("sgplvm-a", "sgplvm", "SGPLVM A (back-constraint init.)", True, {"init": "back-constraint"}),
    Method("sgplvm-b", "sgplvm", "SGPLVM B (HMM init.)", True, {"init": "hmm"}),
    Method("voice-puppetry", "voice-puppetry", "Voice Puppetry (Brand)", False),
    Method("slds", "slds", "SLDS", False),
    Method("dpds", "dpds", "DPDS", False),
    Method("hmm-mean", "hmm-mean", "HMM (per-phone mean)", True),
    Method("context-ridge", "context-ridge", "ridge on label/MFCC context windows", True),
    Method("context-mlp", "context-mlp", "MLP on label/MFCC context windows", True),
    Method("zero", "zero", "zero (utterance mean, still face)", True),
    Method("oracle", "oracle", "oracle (generator mean given the true timing)", True),
    Method("sparse-sgpdm", "sparse-sgpdm", "one sparse SGPDM on the whole corpus (ours)", True),
)


def methods() -> dict[str, Method]:
    """Every method: the named ones above, then one per registered family without a method
    of its own (its estimator's ``predict_dist`` with no options; labelled by its class)."""
    out = {m.name: m for m in NAMED_METHODS}
    covered = {m.family for m in NAMED_METHODS}
    for fam, (cls, _) in ESTIMATORS.items():
        if fam not in covered and fam not in out:
            out[fam] = Method(fam, fam, f"{fam} ({cls.__name__})", cls.has_distribution())
    return out


#: method name -> :class:`Method` (see :func:`methods`; a family registered later in
#: :data:`ESTIMATORS` is picked up by :func:`methods`, which ``evaluate`` reads)
METHODS: dict[str, Method] = methods()


#: ``format`` of a ``<path>.json`` in the per-family layout of earlier versions -> its reader
#: (deena2009's SGPLVM and the sparse SGPDM saved to a base name; a trained-model directory
#: held them as ``sgpdm.*`` and ``sparse_sgpdm.*``)
LEGACY_READERS = {SGPDM.format_name: SGPLVM.read_legacy, SparseSGPDM.format_name: CorpusSparseSGPDM.read_legacy}


def load_estimator(path: str | os.PathLike) -> Estimator:
    """The estimator saved in the directory ``path`` by :meth:`Estimator.save
    <bayes_talk.estimators.base.Estimator.save>`, of the class its descriptor names
    (:meth:`Estimator.load <bayes_talk.estimators.base.Estimator.load>`; every class of
    :data:`ESTIMATORS` and :data:`WRAPPERS` is imported here).

    Layouts of earlier versions (before ``estimator.json``), as trained-model directories held them,
    are read too: ``path/model.json`` + ``arrays.npz`` (a switching SGPDM) and ``<path>.json``
    + ``<path>.npz`` of a format in :data:`LEGACY_READERS`. Any other ``<path>.json`` (the
    context regressions' own format) is refused, naming the file and its format;
    FileNotFoundError when ``path`` holds no saved estimator."""
    p = Path(path)
    if (p / "model.json").is_file() and not (p / ESTIMATOR_FILE).is_file():
        return SwitchingSGPDM.read_legacy(p)
    if (p / ESTIMATOR_FILE).is_file() or (p / BUNDLE_MANIFEST).is_file():
        return Estimator.load(p)
    legacy = p.with_name(p.name + ".json")
    if legacy.is_file():
        try:
            fmt = json.loads(legacy.read_text(encoding="utf-8")).get("format")
        except (OSError, ValueError, AttributeError) as exc:
            raise ValueError(f"model file {legacy} is truncated or not a saved model ({exc})") from None
        if fmt not in LEGACY_READERS:
            raise ValueError(f"model file {legacy}: a model of format {fmt!r} saved by an earlier bayes_talk, "
                             f"which this version does not read (it reads {', '.join(map(repr, LEGACY_READERS))} "
                             "and the directories Estimator.save writes); train the model again")
        return LEGACY_READERS[fmt](p)
    raise FileNotFoundError(f"{p} holds no saved estimator (no {ESTIMATOR_FILE})")
