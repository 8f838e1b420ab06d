"""Published baselines (englebienne2008; deena2009 §4.3): Voice Puppetry, SLDS, DPDS,
per-phone mean; and the context-window regressions a practitioner tries first (ridge and MLP).

``REGISTRY`` maps each model's ``name`` to its class::

    from bayes_talk.estimators.baselines import REGISTRY
    model = REGISTRY["dpds"]().fit(train)
    z_hat = model.predict(test_seq)
"""
from __future__ import annotations

from bayes_talk.estimators.baselines.base import Baseline
from bayes_talk.estimators.baselines.context import ContextRidge
from bayes_talk.estimators.baselines.context_mlp import ContextMLP
from bayes_talk.estimators.baselines.dpds import DPDS
from bayes_talk.estimators.baselines.hmm_mean import HMMMean
from bayes_talk.estimators.baselines.slds import SLDS
from bayes_talk.estimators.baselines.voice_puppetry import VoicePuppetry

REGISTRY: dict[str, type[Baseline]] = {
    cls.name: cls for cls in (VoicePuppetry, SLDS, DPDS, HMMMean, ContextRidge, ContextMLP)
}

__all__ = ["DPDS", "REGISTRY", "SLDS", "Baseline", "ContextMLP", "ContextRidge", "HMMMean", "VoicePuppetry"]
