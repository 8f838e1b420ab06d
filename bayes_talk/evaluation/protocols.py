"""The three published evaluation protocols (issue #5; DESIGN.md §9).

==================  ====================================  =====  ==========================
protocol            split                                 d      headline metrics
==================  ====================================  =====  ==========================
deena2009           10 repeats, random 50 train / 20 test  8      RMS (deena2009 §4.4)
deena2010           one split, 250 train / 28 test         6      AMSE, ACC (deena2010 §5)
englebienne2008     10-fold cross-validation               6      L1, RMS, L∞, test log-lik.
==================  ====================================  =====  ==========================

Splits are drawn from ``numpy.random.default_rng([seed, k])`` (k = repeat index; k = 0 for
the single split and for the fold permutation), so the same seed and the same list of
utterances (in the same order) give the same split. With more utterances than a protocol
uses, a seeded subset is taken first (``[seed, 2**16]`` stream); with fewer, ValueError.
For k-fold CV the seeded permutation is cut into k near-equal folds (``np.array_split``):
every utterance is tested exactly once.

``quick=True`` gives a labelled *quick* variant of each protocol (fewer utterances,
repeats and folds, smaller per-state caps and iteration counts; see ``_QUICK``) meant to
finish ``deena2010`` within 10 minutes on a 2-core machine. Its numbers are not the
protocol's numbers: the JSON says ``"quick": true``.

With a separate test set (``test_sequences``) the protocol trains once on *all* the given
training utterances and tests on *all* the test utterances; the test set must have the
same feature dimensions and phone set (:func:`check_test_set`).

Reported per method (over all test utterances of all splits pooled; ``n`` = number of
test utterances scored): ``mse`` (its mean is AMSE), ``rms``, ``l1``, ``linf``, ``nmse``
(MSE over the ground-truth variance of the split's test frames), ``corr`` (its mean is
ACC), ``log_likelihood_per_frame`` where defined, and for methods with a predictive
variance ``coverage_50``, ``coverage_90`` (fraction of entries inside the central 50 / 90 %
band of the method's predictive: the exact mixture interval of its
:class:`~bayes_talk.synthesis.result.SynthesisResult`, the bands ``synth`` writes; a
Gaussian one for a baseline's variance), ``crps`` and ``nlpd`` (per entry, Gaussian); each as
:func:`~bayes_talk.evaluation.metrics.summarise` gives it ({"mean", "std", "ci95", "n"}).
Also ``train_seconds`` (total over splits; methods sharing a family report the shared
training time and name each other in ``train_shared_with``) and
``synth_frames_per_second``.
"""
from __future__ import annotations

import logging
import math
import os
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from bayes_talk.data.sequence import Sequence as Utterance
from bayes_talk.evaluation import metrics as M
from bayes_talk.evaluation.ceiling import add_gain_fractions
from bayes_talk.evaluation.systems import (
    METHODS,
    SystemConfig,
    fit_family,
    group_by_family,
    log_likelihood,
    predict,
    resolve_methods,
)

__all__ = [
    "PROTOCOLS",
    "Protocol",
    "Split",
    "check_test_set",
    "check_writable",
    "evaluate",
    "get_protocol",
    "make_splits",
    "run_protocol",
]

log = logging.getLogger(__name__)

SCHEMES = ("repeats", "holdout", "kfold")
VAR_FLOOR = 1e-10


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

#: what ``quick=True`` changes: protocol fields and SystemConfig fields
_QUICK: dict[str, tuple[dict, dict]] = {
    "deena2009": (
        {"n_train": 20, "n_test": 8, "n_repeats": 3},
        {"sgplvm_max_frames": 400, "sgplvm_max_iter": 40, "sgplvm_synth_max_iter": 30,
         "vp_n_states": 12, "vp_n_iter": 20}),
    "deena2010": (
        {"n_train": 100, "n_test": 20},
        {"ssgpdm_max_frames_per_state": 150, "ssgpdm_min_frames_per_state": 30, "ssgpdm_min_count": 10,
         "ssgpdm_max_iter": 40, "ssgpdm_fallback_frames": 300,
         "vp_n_states": 12, "vp_n_iter": 20}),
    "englebienne2008": (
        {"n_folds": 4, "n_use": 40},
        {"ssgpdm_max_frames_per_state": 150, "ssgpdm_min_frames_per_state": 30, "ssgpdm_min_count": 10,
         "ssgpdm_max_iter": 40, "ssgpdm_fallback_frames": 300,
         "sgplvm_max_frames": 400, "sgplvm_max_iter": 40, "sgplvm_synth_max_iter": 30,
         "vp_n_states": 12, "vp_n_iter": 20, "slds_n_iter": 30, "dpds_max_iter": 100}),
}


def get_protocol(name: str, quick: bool = False, seed: int | None = None, **system_overrides: Any) -> Protocol:
    """The protocol ``name`` (its quick variant if ``quick``); ``seed`` replaces the fixed
    seed (0) of the split and of every model; ``system_overrides`` replace SystemConfig fields."""
    if name not in PROTOCOLS:
        raise ValueError(f"unknown protocol {name!r}; valid protocols: {', '.join(PROTOCOLS)}")
    p = PROTOCOLS[name]
    sys_kw: dict[str, Any] = {}
    if quick:
        pk, sk = _QUICK[name]
        p = replace(p, quick=True, **pk)
        sys_kw.update(sk)
    if seed is not None:
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        p = replace(p, seed=int(seed))
        sys_kw["seed"] = int(seed)
    unknown = set(system_overrides) - set(asdict(p.system))
    if unknown:
        raise ValueError(f"unknown system setting(s) {sorted(unknown)}; valid: {sorted(asdict(p.system))}")
    sys_kw.update(system_overrides)
    if sys_kw:
        p = replace(p, system=replace(p.system, **sys_kw))
    return p


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


@dataclass(frozen=True)
class Split:
    """Indices into the utterance list: ``train`` and ``test`` (disjoint)."""

    index: int
    train: tuple[int, ...]
    test: tuple[int, ...]


def make_splits(protocol: Protocol, n_items: int) -> list[Split]:
    """The protocol's train/test splits of ``n_items`` utterances (deterministic in the seed)."""
    p = protocol
    if not isinstance(n_items, (int, np.integer)) or n_items < 0:
        raise ValueError(f"n_items must be a non-negative integer, got {n_items!r}")
    if n_items < p.n_needed:
        raise ValueError(f"protocol {p.name}{' (quick)' if p.quick else ''} needs at least {p.n_needed} "
                         f"utterances, the corpus has {n_items}")
    if p.scheme == "kfold":
        pool = np.arange(n_items)
        if p.n_use is not None and p.n_use < n_items:
            pool = np.sort(np.random.default_rng([p.seed, 2**16]).choice(n_items, p.n_use, replace=False))
        perm = pool[np.random.default_rng([p.seed, 0]).permutation(len(pool))]
        folds = np.array_split(perm, p.n_folds)
        out = []
        for k, f in enumerate(folds):
            test = set(f.tolist())
            out.append(Split(k, tuple(int(i) for i in pool if i not in test), tuple(sorted(int(i) for i in f))))
        return out
    out = []
    for r in range(p.n_repeats):
        perm = np.random.default_rng([p.seed, r]).permutation(n_items)
        out.append(Split(r, tuple(sorted(int(i) for i in perm[:p.n_train])),
                         tuple(sorted(int(i) for i in perm[p.n_train:p.n_train + p.n_test]))))
    return out


# ---------------------------------------------------------------------------- test-set checks
def _dims(seqs: Sequence[Utterance], what: str) -> tuple[int, int]:
    if not seqs:
        raise ValueError(f"{what}: no utterances")
    dims = {(s.mfcc.shape[1], None if s.aam is None else s.aam.shape[1]) for s in seqs}
    if any(dz is None for _, dz in dims):
        missing = [s.name for s in seqs if s.aam is None][:5]
        raise ValueError(f"{what}: utterances without visual features (aam): {missing}")
    if len(dims) != 1:
        raise ValueError(f"{what}: utterances have different feature dimensions (D_y, D_z): {sorted(dims)}")
    return next(iter(dims))


def check_test_set(train: Sequence[Utterance], test: Sequence[Utterance],
                   train_phone_set: Sequence[str] | None = None,
                   test_phone_set: Sequence[str] | None = None) -> None:
    """Refuse (ValueError naming the difference) a test set that does not match training.

    Feature dimensions (audio D_y and visual D_z) must be equal. Phone sets: if both are
    declared (a built corpus's manifest ``phone_set``) they must be equal; in any case every
    label used by the test set must be in the training phone set (declared, else the
    labels seen in training).
    """
    dy, dz = _dims(train, "training corpus")
    ty, tz = _dims(test, "test corpus")
    if dy != ty:
        raise ValueError(f"test corpus differs in audio feature dimension: training has D_y = {dy}, test has {ty}")
    if dz != tz:
        raise ValueError(f"test corpus differs in visual feature dimension: training has D_z = {dz} "
                         f"AAM parameters, test has {tz}")
    if train_phone_set is not None and test_phone_set is not None:
        a, b = set(train_phone_set), set(test_phone_set)
        if a != b:
            raise ValueError(f"test corpus has a different phone set: only in training {sorted(a - b)}, "
                             f"only in test {sorted(b - a)}")
    known = set(train_phone_set) if train_phone_set is not None else {lab for s in train for lab in s.labels}
    extra = sorted({lab for s in test for lab in s.labels} - known)
    if extra:
        raise ValueError(f"test corpus has a different phone set: labels {extra} are not in the training "
                         "corpus's phone set")


def check_writable(path: str | Path) -> Path:
    """Fail fast (ValueError) unless a file can be created at ``path`` (and beside it)."""
    p = Path(path)
    if p.suffix.lower() != ".json":
        raise ValueError(f"--json path must end in .json, got {str(p)!r}")
    if p.is_dir():
        raise ValueError(f"cannot write {p}: it is a directory")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"cannot write {p}: directory {parent} does not exist")
    if p.exists() and not os.access(p, os.W_OK):
        raise ValueError(f"cannot write {p}: file is not writable")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".probe", dir=parent)
    except OSError as exc:
        raise ValueError(f"cannot write {p}: {exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(tmp)
    return p


# ---------------------------------------------------------------------------- metrics
def _utterance_metrics(z: np.ndarray, pred, variance: np.ndarray, ll: float | None) -> dict[str, float]:
    mean = pred.mean
    out = {
        "mse": float(M.mse([z], [mean])[0]),
        "rms": float(M.rms([z], [mean])[0]),
        "l1": float(M.l1([z], [mean])[0]),
        "linf": float(M.linf([z], [mean])[0]),
        "nmse": float(M.normalised_mse([z], [mean], variance=variance)[0]),
        "corr": float(M.correlation([z], [mean])[0]),
    }
    if ll is not None:
        out["log_likelihood_per_frame"] = ll / z.shape[0]
    if pred.var is not None:
        sd = np.sqrt(np.maximum(pred.var, VAR_FLOOR))
        for level in (50, 90):  # the bands synth writes (the result's exact interval)
            lo, hi = pred.band(level / 100)
            out[f"coverage_{level}"] = M.coverage([z], [lo], [hi])
        out["crps"] = M.crps_gaussian([z], [mean], [sd])
        out["nlpd"] = M.nlpd_gaussian([z], [mean], [sd * sd])
    if getattr(pred, "mse_bias", None) is not None:  # oracle: remove its finite-sample bias
        b = np.asarray(pred.mse_bias, np.float64).mean(axis=0)
        keep = variance > 0
        out["mse_corrected"] = out["mse"] - float(b.mean())
        out["nmse_corrected"] = out["nmse"] - float(np.mean(b[keep] / variance[keep]))
    return out


def _summary(values: list[float]) -> dict[str, Any]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        v = np.asarray(values, dtype=np.float64)
        if not np.isfinite(v).any():
            return {"mean": None, "std": None, "ci95": [None, None], "n": 0}
        s = M.summarise(v)
    return s


def _clean(obj: Any) -> Any:
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python, tuples -> lists."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    return obj


# ---------------------------------------------------------------------------- the harness
@dataclass
class Trajectory:
    """Material of the trajectory figure: one test utterance, first split."""

    utterance: str
    truth: np.ndarray
    predictions: dict[str, Any] = field(default_factory=dict)


def run_protocol(
    protocol: Protocol,
    sequences: Sequence[Utterance],
    methods: str | Sequence[str] | None = None,
    test_sequences: Sequence[Utterance] | None = None,
    train_phone_set: Sequence[str] | None = None,
    test_phone_set: Sequence[str] | None = None,
    executor=None,
    progress: Callable[[str], None] | None = None,
    model_cache: dict | None = None,
) -> tuple[dict[str, Any], Trajectory]:
    """Run ``protocol`` on ``sequences`` (or train on them and test on ``test_sequences``).

    Returns (result, trajectory): ``result`` is the JSON-ready dict (see the module
    docstring); ``trajectory`` holds the ground truth and every method's prediction for
    the first test utterance of the first split (for :mod:`bayes_talk.evaluation.report`).
    ``model_cache``: a dict reused across calls with the same training utterances: the
    fitted model of each (family, split) is taken from it or stored in it (label sources).
    """
    names = resolve_methods(methods, protocol.default_methods)
    seqs = list(sequences)
    say = progress or (lambda msg: log.info("%s", msg))
    if test_sequences is not None:
        tests = list(test_sequences)
        check_test_set(seqs, tests, train_phone_set, test_phone_set)
        pool = seqs + tests
        splits = [Split(0, tuple(range(len(seqs))), tuple(range(len(seqs), len(pool))))]
    else:
        _dims(seqs, "corpus")
        pool = seqs
        splits = make_splits(protocol, len(seqs))
    families = group_by_family(names)
    cfg = protocol.system
    per_utt: dict[str, list[dict[str, float]]] = {n: [] for n in names}
    per_split: dict[str, list[dict[str, Any]]] = {n: [] for n in names}
    train_s = {f: 0.0 for f in families}
    synth_s = {n: 0.0 for n in names}
    synth_frames = {n: 0 for n in names}
    traj: Trajectory | None = None
    t_start = time.perf_counter()
    for split in splits:
        train = [pool[i] for i in split.train]
        test = [pool[i] for i in split.test]
        variance = np.concatenate([s.aam for s in test]).var(axis=0)
        if traj is None:
            traj = Trajectory(test[0].name, test[0].aam.copy())
        for fam, fam_methods in families.items():
            say(f"split {split.index + 1}/{len(splits)}: training {fam} on {len(train)} utterances")
            t0 = time.perf_counter()
            if model_cache is not None and (fam, split.index) in model_cache:
                model = model_cache[(fam, split.index)]
            else:
                model = fit_family(fam, train, cfg, executor=executor)
            if model_cache is not None:
                model_cache[(fam, split.index)] = model
            train_s[fam] += time.perf_counter() - t0
            for name in fam_methods:
                rows = []
                for j, seq in enumerate(test):
                    t0 = time.perf_counter()
                    pred = predict(name, model, seq, cfg)
                    synth_s[name] += time.perf_counter() - t0
                    synth_frames[name] += seq.n_frames
                    if pred.mean.shape != seq.aam.shape:
                        raise RuntimeError(f"{name} predicted shape {pred.mean.shape} for {seq.name}, "
                                           f"expected {seq.aam.shape}")
                    ll = log_likelihood(name, model, seq, pred)
                    rows.append(_utterance_metrics(seq.aam, pred, variance, ll))
                    if split.index == splits[0].index and j == 0:
                        traj.predictions[name] = pred
                per_utt[name].extend(rows)
                keys = rows[0].keys()
                per_split[name].append({"split": split.index, "n_test": len(rows),
                                        **{k: float(np.nanmean([r[k] for r in rows])) for k in keys}})
                say(f"split {split.index + 1}/{len(splits)}: {name} " + ", ".join(
                    f"{k}={per_split[name][-1][k]:.4g}" for k in ("mse", "corr")))
    result_methods: dict[str, Any] = {}
    for name in names:
        m = METHODS[name]
        rows = per_utt[name]
        entry: dict[str, Any] = {"label": m.label, "family": m.family, "has_variance": m.has_variance}
        for k in rows[0]:
            entry[k] = _summary([r[k] for r in rows])
        entry["headline"] = {lab: (entry[k]["mean"] if k in entry else None) for lab, k in protocol.headline}
        entry["train_seconds"] = train_s[m.family]
        entry["train_shared_with"] = [n for n in families[m.family] if n != name]
        entry["synth_seconds"] = synth_s[name]
        entry["synth_frames_per_second"] = synth_frames[name] / synth_s[name] if synth_s[name] > 0 else None
        entry["n_test_frames"] = synth_frames[name]
        entry["per_split"] = per_split[name]
        result_methods[name] = entry
    add_gain_fractions(result_methods)
    n_train = [len(s.train) for s in splits]
    n_test = [len(s.test) for s in splits]
    result = {
        "protocol": protocol.name,
        "quick": bool(protocol.quick),
        "description": protocol.describe() if test_sequences is None else
        f"{'quick variant of ' if protocol.quick else ''}{protocol.name} settings, trained on all "
        f"{len(seqs)} utterances of the training corpus, tested on all {len(pool) - len(seqs)} of the test corpus",
        "paper": protocol.paper,
        "scheme": "test-corpus" if test_sequences is not None else protocol.scheme,
        "seed": protocol.seed,
        "n_train": int(min(n_train)),
        "n_test": int(min(n_test)),
        "n_splits": len(splits),
        "n_scored": int(sum(n_test)),
        "headline_metrics": [{"label": lab, "key": k} for lab, k in protocol.headline],
        "settings": asdict(cfg),
        "splits": [{"index": s.index, "train": [pool[i].name for i in s.train],
                    "test": [pool[i].name for i in s.test]} for s in splits],
        "methods": result_methods,
        "elapsed_seconds": time.perf_counter() - t_start,
    }
    return _clean(result), traj


def evaluate(
    protocol: str,
    corpus: str | Path,
    json_path: str | Path,
    test_corpus: str | Path | None = None,
    methods: str | Sequence[str] | None = None,
    quick: bool = False,
    seed: int | None = None,
    figures: bool = True,
    lowpass_hz: float | None = None,
    oracle_draws: int | None = None,
    min_utterances: int | None = None,
    cmvn: str = "mean",
    labels: str | Sequence[str] | None = None,
) -> dict[str, Any]:
    """The ``bayes-talk evaluate`` job: load corpora, run, write JSON + Markdown + figure.

    lowpass_hz: apply deena2010's zero-phase low-pass to every method's predicted mean
    (recorded in the JSON under ``settings``); None: off, the protocols' default.
    min_utterances: let a corpus smaller than the protocol needs (but with at least this
    many utterances) be evaluated with the split scaled down (:func:`scale_protocol`); the
    JSON and Markdown carry a warning saying so. cmvn: the per-utterance cepstral
    normalisation of both corpora's MFCCs (``load_corpus(cmvn=...)``; "mean" as ``train``).
    labels: test-label sources, e.g. ``"true,aligned,recognised"`` (default ``"true"``;
    :mod:`bayes_talk.evaluation.label_sources`).

    Checks the protocol, the methods and that ``json_path`` is writable *before* loading
    or training anything. Writes ``json_path``, ``json_path`` with suffix ``.md`` and
    ``<stem>_trajectories.png`` beside it (each atomically).
    """
    from bayes_talk.data.corpus import load_corpus
    from bayes_talk.data.phones import PHONES
    from bayes_talk.evaluation import report

    proto = get_protocol(protocol, quick=quick, seed=seed,
                         **({"lowpass_hz": float(lowpass_hz)} if lowpass_hz is not None else {}),
                         **({"oracle_draws": oracle_draws} if oracle_draws is not None else {}))
    names = resolve_methods(methods, proto.default_methods)
    from bayes_talk.evaluation.label_sources import parse_label_sources, run_label_sources

    sources = parse_label_sources(labels)
    out = check_writable(json_path)
    t0 = time.perf_counter()
    train_c = load_corpus(corpus, cmvn=cmvn)
    test_c = None
    if test_corpus is not None:
        # score the test frames in the training corpus's AAM space: project them through it
        try:
            test_c = load_corpus(test_corpus, aam=train_c.aam_path, cmvn=cmvn)
        except ValueError as exc:
            raise ValueError(f"test corpus {test_corpus} cannot be scored against training corpus "
                             f"{corpus}: {exc}") from exc
    load_s = time.perf_counter() - t0
    small_note = None
    if min_utterances is not None and test_c is None:
        proto, small_note = scale_protocol(proto, len(train_c.sequences), min_utterances)

    def phone_set(c):
        return list(c.manifest.get("phone_set", PHONES))

    if sources != ("true",):  # test labels from the aligner / recogniser (issue 13)
        result, traj = run_label_sources(
            run_protocol, proto, train_c.sequences, test_c.sequences if test_c is not None else None, names,
            sources, train_phone_set=phone_set(train_c),
            test_phone_set=phone_set(test_c) if test_c is not None else None)
    else:
        result, traj = run_protocol(
            proto, train_c.sequences, names,
            test_sequences=test_c.sequences if test_c is not None else None,
            train_phone_set=phone_set(train_c),
            test_phone_set=phone_set(test_c) if test_c is not None else None)
    result["corpus"] = str(Path(corpus).resolve())
    result["test_corpus"] = str(Path(test_corpus).resolve()) if test_corpus is not None else None
    result["test_features"] = (None if test_c is None else "projected through the training corpus's AAM"
                               if train_c.aam_path is not None else "the test corpus's precomputed features")
    result["load_seconds"] = load_s
    result["cmvn"] = cmvn
    if small_note:
        result["warnings"] = [*(result.get("warnings") or []), small_note]
        result["scaled_for_small_corpus"] = True
    md_path = out.with_suffix(".md")
    png_path = out.with_name(out.stem + "_trajectories.png")
    result["outputs"] = {"json": out.name, "markdown": md_path.name, "figure": png_path.name if figures else None}
    if figures:
        report.plot_trajectories(traj, png_path, title=f"{result['description']} — first AAM parameter, "
                                 f"utterance {traj.utterance}")
    report.write_markdown(result, md_path)
    report.write_json(result, out)
    return result
