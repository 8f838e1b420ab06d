"""bayes_talk: speech-driven talking faces with switching shared GP dynamical models.

The public API, imported lazily on first use (``import bayes_talk`` stays fast and
pulls in neither torch nor pyro)::

    import bayes_talk as bt
    corpus = bt.load_corpus("corpus_dir")
    model = bt.make_estimator("ssgpdm-vlmm").fit(corpus.sequences)
    dist = model.predict_dist(utterance)          # mean and variance (T, D_z)

The layers and what each may import: docs/architecture.md.
"""
from __future__ import annotations

from bayes_talk.base.lazy import lazy_exports

__version__ = "0.1.0"

#: public name -> module that defines it
_EXPORTS: dict[str, str] = {
    # data
    "Utterance": "bayes_talk.data.utterance",
    "load_corpus": "bayes_talk.corpus",
    # features
    "AAM": "bayes_talk.features.aam",
    # models
    "SGPDM": "bayes_talk.models.sgpdm",
    "VLMM": "bayes_talk.models.vlmm",
    "SwitchingModel": "bayes_talk.models.switching",
    # synthesis
    "sample_synthesis": "bayes_talk.posterior.sampling",
    # estimators
    "ESTIMATORS": "bayes_talk.estimators.registry",
    "make_estimator": "bayes_talk.estimators.registry",
    "SwitchingSGPDM": "bayes_talk.estimators.switching",
    "SGPLVM": "bayes_talk.estimators.sgplvm",
    "VoicePuppetry": "bayes_talk.estimators.baselines",
    "SLDS": "bayes_talk.estimators.baselines",
    "DPDS": "bayes_talk.estimators.baselines",
    "HMMMean": "bayes_talk.estimators.baselines",
    "ContextRidge": "bayes_talk.estimators.baselines",
    "ContextMLP": "bayes_talk.estimators.baselines",
    "NotFittedError": "bayes_talk.base.errors",
    # command-line workflow
    "train": "bayes_talk.pipeline",
    "synth": "bayes_talk.pipeline",
    "load_trained": "bayes_talk.pipeline",
    "read_utterance": "bayes_talk.pipeline",
}

__all__ = [  # noqa: RUF022 - grouped by layer, as _EXPORTS
    "__version__", "Utterance", "load_corpus", "AAM", "SGPDM", "VLMM", "SwitchingModel", "sample_synthesis",
    "ESTIMATORS", "make_estimator", "SwitchingSGPDM", "SGPLVM", "VoicePuppetry", "SLDS", "DPDS", "HMMMean",
    "ContextRidge", "ContextMLP", "NotFittedError", "train", "synth", "load_trained", "read_utterance",
]


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals(), __all__)
