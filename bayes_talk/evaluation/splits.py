"""Train/test splits of an evaluation protocol, and the checks of a separate test set.

Splits are drawn from ``numpy.random.default_rng([seed, k])`` (k = repeat index; k = 0 for
the single split and for the fold permutation), so the same seed and the same list of
utterances (in the same order) give the same split. With more utterances than a protocol
uses, a seeded subset is taken first (``[seed, 2**16]`` stream); with fewer, ValueError.
For k-fold CV the seeded permutation is cut into k near-equal folds (``np.array_split``):
every utterance is tested exactly once.

With a separate test set (``test_sequences``) the protocol trains once on *all* the given
training utterances and tests on *all* the test utterances; the test set must have the
same feature dimensions and phone set (:func:`check_test_set`).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from bayes_talk.data.utterance import Utterance

if TYPE_CHECKING:
    from bayes_talk.evaluation.protocols import Protocol

__all__ = ["Split", "check_test_set", "make_splits"]


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
def feature_dims(seqs: Sequence[Utterance], what: str) -> tuple[int, int]:
    """(D_y, D_z), the audio and visual feature dimensions shared by ``seqs`` (ValueError naming ``what`` otherwise)."""
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
    dy, dz = feature_dims(train, "training corpus")
    ty, tz = feature_dims(test, "test corpus")
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
