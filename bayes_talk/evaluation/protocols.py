"""The three published evaluation protocols (docs/evaluation.md).

==================  ====================================  =====  ==========================
protocol            split                                 d      headline metrics
==================  ====================================  =====  ==========================
deena2009           10 repeats, random 50 train / 20 test  8      RMS (deena2009 §4.4)
deena2010           one split, 250 train / 28 test         6      AMSE, ACC (deena2010 §5)
englebienne2008     10-fold cross-validation               6      L1, RMS, L∞, test log-lik.
==================  ====================================  =====  ==========================

``quick=True`` gives a labelled *quick* variant of each protocol (fewer utterances,
repeats and folds, smaller per-state caps and iteration counts of the models it runs by
default; see ``_QUICK``) meant to
finish ``deena2010`` within 10 minutes on a 2-core machine. Its numbers are not the
protocol's numbers: the JSON says ``"quick": true``.

The train/test splits are drawn by :mod:`bayes_talk.evaluation.splits`; the protocols are run
(train, predict, score, report) by :mod:`bayes_talk.evaluation.harness`.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from bayes_talk.evaluation.systems import SystemConfig, resolve_methods

__all__ = ["PROTOCOLS", "Protocol", "get_protocol", "scale_protocol"]

SCHEMES = ("repeats", "holdout", "kfold")


@dataclass(frozen=True)
class Protocol:
    """An evaluation protocol.

    scheme: "repeats" (``n_repeats`` random ``n_train``/``n_test`` subsets), "holdout"
    (one ``n_train``/``n_test`` split) or "kfold" (``n_folds``-fold CV over ``n_use``
    utterances, all of them if None). headline: the paper's metrics, as
    (label, metric key) pairs. system: settings of every model.
    """

    name: str
    paper: str
    scheme: str
    headline: tuple[tuple[str, str], ...]
    default_methods: tuple[str, ...]
    system: SystemConfig
    n_train: int | None = None
    n_test: int | None = None
    n_repeats: int = 1
    n_folds: int | None = None
    n_use: int | None = None
    seed: int = 0
    quick: bool = False

    def __post_init__(self) -> None:
        if self.scheme not in SCHEMES:
            raise ValueError(f"scheme must be one of {SCHEMES}, got {self.scheme!r}")
        if self.scheme in ("repeats", "holdout"):
            if not (isinstance(self.n_train, int) and self.n_train >= 1
                    and isinstance(self.n_test, int) and self.n_test >= 1):
                raise ValueError(f"{self.name}: n_train and n_test must be positive integers")
            if self.n_repeats < 1:
                raise ValueError(f"{self.name}: n_repeats must be >= 1, got {self.n_repeats}")
        else:
            if not (isinstance(self.n_folds, int) and self.n_folds >= 2):
                raise ValueError(f"{self.name}: n_folds must be an integer >= 2, got {self.n_folds!r}")
            if self.n_use is not None and self.n_use < self.n_folds:
                raise ValueError(f"{self.name}: n_use ({self.n_use}) < n_folds ({self.n_folds})")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        resolve_methods(self.default_methods)

    @property
    def n_needed(self) -> int:
        """Minimum number of utterances the protocol needs."""
        if self.scheme == "kfold":
            return self.n_use or self.n_folds
        return self.n_train + self.n_test

    def describe(self) -> str:
        """One sentence: the split scheme, the numbers of utterances and the paper."""
        q = "quick variant of " if self.quick else ""
        if self.scheme == "repeats":
            s = f"{self.n_repeats} repeats of random {self.n_train} train / {self.n_test} test"
        elif self.scheme == "holdout":
            s = f"one split, {self.n_train} train / {self.n_test} test"
        else:
            s = f"{self.n_folds}-fold cross-validation" + (f" over {self.n_use} utterances" if self.n_use else "")
        return f"{q}{self.name}: {s}, d = {self.system.latent_dim}, seed {self.seed}"


_BASELINES = ("voice-puppetry",)
PROTOCOLS: dict[str, Protocol] = {
    "deena2009": Protocol(
        "deena2009", "deena2009 §4.3-4.4", "repeats", (("RMS", "rms"),),
        ("sgplvm-a", "sgplvm-b", "voice-puppetry"), SystemConfig(latent_dim=8),
        n_train=50, n_test=20, n_repeats=10),
    "deena2010": Protocol(
        "deena2010", "deena2010 §5, Table 1", "holdout", (("AMSE", "mse"), ("ACC", "corr")),
        ("ssgpdm-vlmm-optimise", "ssgpdm-vlmm-predict", "ssgpdm-phone-optimise", "ssgpdm-phone-predict",
         "ssgpdm-vlmm-posterior", "voice-puppetry", "context-ridge", "context-mlp"), SystemConfig(latent_dim=6),
        n_train=250, n_test=28),
    "englebienne2008": Protocol(
        "englebienne2008", "englebienne2008 §4, Fig. 4", "kfold",
        (("L1", "l1"), ("RMS", "rms"), ("Linf", "linf"), ("test log-lik./frame", "log_likelihood_per_frame")),
        ("dpds", "voice-puppetry", "hmm-mean", "slds"), SystemConfig(latent_dim=6),
        n_folds=10),
}

# the quick variants' settings of the models (SystemConfig.models / .synthesis)
_SSGPDM_QUICK = {"max_frames_per_state": 150, "min_frames_per_state": 30, "min_count": 10, "max_iter": 40,
                 "fallback_frames": 300}
_SGPLVM_QUICK = {"max_frames": 400, "max_iter": 40}
_VP_QUICK = {"n_states": 12, "n_iter": 20}

#: what ``quick=True`` changes: protocol fields and SystemConfig fields (``models`` and
#: ``synthesis`` merged per model into the protocol's)
_QUICK: dict[str, tuple[dict, dict]] = {
    "deena2009": (
        {"n_train": 20, "n_test": 8, "n_repeats": 3},
        {"models": {"sgplvm": _SGPLVM_QUICK, "voice-puppetry": _VP_QUICK},
         "synthesis": {"sgplvm": {"max_iter": 30}}}),
    "deena2010": (
        {"n_train": 100, "n_test": 20},
        {"models": {"ssgpdm": _SSGPDM_QUICK, "voice-puppetry": _VP_QUICK}}),
    "englebienne2008": (
        {"n_folds": 4, "n_use": 40},
        {"models": {"ssgpdm": _SSGPDM_QUICK, "sgplvm": _SGPLVM_QUICK, "voice-puppetry": _VP_QUICK,
                    "slds": {"n_iter": 30}, "dpds": {"max_iter": 100}},
         "synthesis": {"sgplvm": {"max_iter": 30}}}),
}
#: the SystemConfig fields merged per model rather than replaced
_PER_MODEL = ("models", "synthesis")


def _merge(system: SystemConfig, overrides: dict[str, Any]) -> dict[str, Any]:
    """``overrides`` of ``system``'s fields, with ``models`` and ``synthesis`` merged per model
    (a model's settings not overridden are kept)."""
    out = dict(overrides)
    for k in _PER_MODEL:
        if k in overrides:
            merged = {m: dict(v) for m, v in getattr(system, k).items()}
            for model, params in overrides[k].items():
                merged[model] = {**merged.get(model, {}), **params}
            out[k] = merged
    return out


def get_protocol(name: str, quick: bool = False, seed: int | None = None, **system_overrides: Any) -> Protocol:
    """The protocol ``name`` (its quick variant if ``quick``); ``seed`` replaces the fixed
    seed (0) of the split and of every model; ``system_overrides`` replace SystemConfig fields,
    except ``models`` and ``synthesis``, merged per model (e.g. ``models={"voice-puppetry":
    {"n_states": 4}}`` changes that one constructor argument of the protocol's Voice Puppetry)."""
    if name not in PROTOCOLS:
        raise ValueError(f"unknown protocol {name!r}; valid protocols: {', '.join(PROTOCOLS)}")
    p = PROTOCOLS[name]
    valid = {f.name for f in fields(SystemConfig)}
    unknown = set(system_overrides) - valid
    if unknown:
        raise ValueError(f"unknown system setting(s) {sorted(unknown)}; valid: {sorted(valid)}")
    system = p.system
    if quick:
        pk, sk = _QUICK[name]
        p = replace(p, quick=True, **pk)
        system = replace(system, **_merge(system, sk))
    if seed is not None:
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        p = replace(p, seed=int(seed))
        system = replace(system, seed=int(seed))
    if system_overrides:
        system = replace(system, **_merge(system, system_overrides))
    return p if system is p.system else replace(p, system=system)


def scale_protocol(protocol: Protocol, n_items: int, min_utterances: int) -> tuple[Protocol, str | None]:
    """``protocol`` for a corpus of ``n_items`` utterances: unchanged (note None) if it has
    enough; else, if ``n_items >= min_utterances``, its split scaled down in proportion
    (repeats/holdout: train and test shares kept, at least 1 test and 2 training
    utterances; k-fold: ``n_use`` = all, folds capped at ``n_items``) and a note saying so
    for the report; else ValueError naming both numbers."""
    p = protocol
    if n_items >= p.n_needed:
        return p, None
    if n_items < max(int(min_utterances), 3):
        raise ValueError(f"protocol {p.name} needs {p.n_needed} utterances; the corpus has {n_items}, "
                         f"fewer than --min-utterances {min_utterances} (and at least 3 are needed)")
    if p.scheme == "kfold":
        q = replace(p, n_use=None, n_folds=min(p.n_folds, n_items))
    else:
        n_test = min(max(1, round(n_items * p.n_test / p.n_needed)), n_items - 2)
        q = replace(p, n_train=n_items - n_test, n_test=n_test)
    note = (f"SMALL CORPUS: {p.name} needs {p.n_needed} utterances, the corpus has {n_items}; the split was "
            f"scaled to it (--min-utterances {min_utterances}): {q.describe()}. Not the paper's protocol; "
            "numbers from so few utterances are noisy and not comparable with the full protocol's")
    return q, note
