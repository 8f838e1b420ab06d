"""Small synthetic audio-visual utterances with known structure, for model tests.

Each phone has a target in a 3-D articulatory space; the trajectory relaxes towards the
current phone's target (a first-order coarticulation), the 'visual' features are a fixed
nonlinear map of it and the 'audio' features another one plus a phone-specific offset.
"""
from __future__ import annotations

import numpy as np

from bayes_talk.data.utterance import Utterance

PHONES = ("sil", "aa", "m", "iy", "uw", "s")


def make_utterances(n: int, seed: int = 0, Dy: int = 8, Dz: int = 5, mean_len: int = 40) -> list[Utterance]:
    rng = np.random.default_rng(seed)
    top = np.random.default_rng(1234)  # the world: same maps and targets for every seed
    targets = {p: top.normal(size=3) for p in PHONES}
    targets["sil"] = np.zeros(3)
    offsets = {p: top.normal(size=Dy) * 0.5 for p in PHONES}
    Wy, Wz = top.normal(size=(3, Dy)), top.normal(size=(3, Dz))
    out = []
    for k in range(n):
        labels: list[str] = ["sil"] * 3
        while len(labels) < mean_len - 3:
            labels += [str(rng.choice(PHONES[1:]))] * int(rng.integers(2, 7))
        labels += ["sil"] * 3
        T = len(labels)
        a = np.zeros((T, 3))
        for t in range(1, T):
            a[t] = a[t - 1] + 0.45 * (targets[labels[t]] - a[t - 1]) + 0.02 * rng.normal(size=3)
        z = np.tanh(a @ Wz) + 0.01 * rng.normal(size=(T, Dz))
        y = np.sin(a @ Wy) + np.array([offsets[lab] for lab in labels]) + 0.05 * rng.normal(size=(T, Dy))
        out.append(Utterance(f"utt{k:03d}", y, z, labels))
    return out
