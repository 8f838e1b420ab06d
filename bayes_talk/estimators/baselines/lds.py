"""Label-switched linear dynamical systems: what SLDS and DPDS share (englebienne2008 §3, App. A).

The models are :class:`bayes_talk.estimators.baselines.slds.SLDS` and :class:`bayes_talk.estimators.baselines.dpds.DPDS`;
this module holds their common model definition, batching, generation and initialisation.

Both models are driven by the known frame labels π_{1:T} (no audio) and use the
observation = state convention B = I of englebienne2008 §3:

    x_1 = μ_{π_1} (+ noise),   x_t = A_{π_t} x_{t−1} + ν_{π_t} (+ w_t),   y_t = x_t + v_t,

where y_t is the visual feature vector z_t (``Utterance.aam``), A_π is diagonal and all
covariances are diagonal. With diagonal A and covariances every visual dimension is an
independent scalar system, which is how both models are computed (vectorised over the
dimensions and over sequences, which are padded to a common length and masked).

Labels: ``μ_π`` is the mean of the *first* frame of the sequences that start with phone π;
a new phone segment does NOT restart the state: the paper's recursion
x_t = A_{π_t} x_{t−1} + ν_{π_t} runs for every t ≥ 2 across phone boundaries (eq. 1; in
App. A, Algorithm 1 accumulates the μ_n coefficients only over sequences whose first
label is n, and the ν coefficients through all t ≥ 2). For a phone that never starts a
training sequence μ_π is not identifiable; it is set to the mean of that phone's training
frames (used only if a test sequence starts with it). Unseen phones: see
:class:`bayes_talk.estimators.baselines.base.LabelEncoder`.

Generation (englebienne2008 §3, "Utterance generation"), both models:

    ŷ_1 = μ_{π_1},   ŷ_t = A_{π_t} ŷ_{t−1} + ν_{π_t}                       (GEN)

i.e. the mean (= most likely) observation sequence for the labels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayes_talk.data.utterance import Utterance, check_test
from bayes_talk.estimators.baselines.base import Baseline, check_train
from bayes_talk.features.phone_encoding import LabelEncoder

__all__ = [
    "LOG2PI",
    "Batch",
    "LabelSwitchedLDS",
    "first_frame_means",
    "init_ar",
    "label_batch",
    "label_means",
    "make_batch",
    "mean_trajectory",
    "prepare_fit",
]

LOG2PI = float(np.log(2.0 * np.pi))


# --------------------------------------------------------------------------- batching
@dataclass(frozen=True)
class Batch:
    """Sequences padded to a common length (time-major).

    Y : (T_max, S, D) observations (0 where padded); L : (T_max, S) label indices
    (0 where padded); M : (T_max, S) bool validity mask.
    """

    Y: np.ndarray
    L: np.ndarray
    M: np.ndarray

    @property
    def n_frames(self) -> int:
        """Total frames in the batch."""
        return int(self.M.sum())


def make_batch(labels: list[np.ndarray], Y: list[np.ndarray] | None = None,
               n_dims: int | None = None) -> Batch:
    """Pad per-sequence label indices (T_s,) and observations (T_s, D) into a :class:`Batch`."""
    S = len(labels)
    if S == 0:
        raise ValueError("no sequences")
    T = max(len(l) for l in labels)
    D = Y[0].shape[1] if Y is not None else int(n_dims or 0)
    Yb = np.zeros((T, S, D))
    Lb = np.zeros((T, S), dtype=np.int64)
    Mb = np.zeros((T, S), dtype=bool)
    for s, l in enumerate(labels):
        n = len(l)
        Lb[:n, s] = l
        Mb[:n, s] = True
        if Y is not None:
            if Y[s].shape != (n, D):
                raise ValueError(f"sequence {s}: observations have shape {Y[s].shape}, expected {(n, D)}")
            Yb[:n, s] = Y[s]
    return Batch(Yb, Lb, Mb)


def mean_trajectory(A: np.ndarray, nu: np.ndarray, mu: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(GEN): ŷ_1 = μ_{π_1}, ŷ_t = A_{π_t} ŷ_{t−1} + ν_{π_t}; A, ν, μ are (Π, D) diagonals."""
    out = np.empty((len(idx), A.shape[1]))
    out[0] = mu[idx[0]]
    for t in range(1, len(idx)):
        out[t] = A[idx[t]] * out[t - 1] + nu[idx[t]]
    return out


def label_means(batch: Batch, n_labels: int) -> np.ndarray:
    """Mean visual vector (n_labels, D) of the frames of each label (0 for a label without frames)."""
    sums = np.zeros((n_labels, batch.Y.shape[2]))
    np.add.at(sums, batch.L[batch.M], batch.Y[batch.M])
    cnt = np.bincount(batch.L[batch.M], minlength=n_labels)
    return sums / np.maximum(cnt, 1)[:, None]


def init_ar(batch: Batch, n_labels: int, a_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-label least-squares fit of y_t ≈ a y_{t−1} + ν on the observations (initialisation).

    Returns a (clipped to [0, a_max]), ν and the residual variance, each (Π, D).
    """
    D = batch.Y.shape[2]
    v = batch.M[1:]
    lab = batch.L[1:][v]
    yp, yc = batch.Y[:-1][v], batch.Y[1:][v]
    st = {k: np.zeros((n_labels, D)) for k in ("pp", "p", "c", "x", "xx")}
    for k, val in (("pp", yp * yp), ("p", yp), ("c", yc * yp), ("x", yc), ("xx", yc * yc)):
        np.add.at(st[k], lab, val)
    n = np.bincount(lab, minlength=n_labels).astype(np.float64)[:, None]
    det = st["pp"] * n - st["p"] ** 2
    ok = (n > 1) & (det > 1e-12 * np.maximum(st["pp"] * n, 1e-300))
    a = np.where(ok, (st["c"] * n - st["p"] * st["x"]) / np.where(ok, det, 1.0), 0.5)
    a = np.clip(a, 0.0, a_max)
    mean_x = st["x"] / np.maximum(n, 1)
    mean_p = st["p"] / np.maximum(n, 1)
    nu = np.where(n > 0, mean_x - a * mean_p, 0.0)
    res = st["xx"] - 2 * a * st["c"] - 2 * nu * st["x"] + a * a * st["pp"] + 2 * a * nu * st["p"] + nu * nu * n
    var = np.where(n > 0, res / np.maximum(n, 1), np.nan)
    return a, nu, var


def first_frame_means(batch: Batch, n_labels: int, values: np.ndarray,
                       fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` (S, D) over sequences grouped by first label; fallback elsewhere."""
    sums = np.zeros((n_labels, values.shape[1]))
    np.add.at(sums, batch.L[0], values)
    cnt = np.bincount(batch.L[0], minlength=n_labels)
    out = np.where(cnt[:, None] > 0, sums / np.maximum(cnt, 1)[:, None], fallback)
    return out, cnt > 0


def label_batch(encoder: LabelEncoder, seqs: list[Utterance]) -> Batch:
    """:func:`make_batch` of the sequences' encoded frame labels and visual features."""
    return make_batch([encoder.encode(s.labels, where=f"sequence {s.name!r}") for s in seqs],
                      [s.aam for s in seqs])


def prepare_fit(model, train: list[Utterance]) -> tuple[int, int, int, Batch, np.ndarray]:
    """Shared start of SLDS/DPDS ``fit``: check the data, fit the label encoder on
    ``model``, batch the sequences, and the per-dimension data variance (1 where zero).
    Returns (D_y, D_z, number of labels, batch, data variance)."""
    d_y, d_z = check_train(train)
    model.encoder_ = LabelEncoder().fit(train)
    b = label_batch(model.encoder_, train)
    data_var = b.Y[b.M].var(axis=0)
    data_var[data_var <= 0] = 1.0
    return d_y, d_z, model.encoder_.n_classes, b, data_var


class LabelSwitchedLDS(Baseline):
    """What the SLDS and DPDS estimators share: the label encoder fitted by
    :func:`prepare_fit` and the batching of test sequences with it."""

    encoder_: LabelEncoder

    def _batch(self, seqs: list[Utterance]) -> Batch:
        return label_batch(self.encoder_, seqs)

    def _start_means(self) -> np.ndarray:
        """μ_π of the first frame, per label (fitted)."""
        raise NotImplementedError

    def predict(self, seq: Utterance) -> np.ndarray:
        """(GEN) the mean trajectory for ``seq.labels`` (module docstring)."""
        self._check_fitted()
        check_test(seq)
        idx = self.encoder_.encode(seq.labels, where=f"sequence {seq.name!r}")
        return mean_trajectory(self.A_, self.nu_, self._start_means(), idx)
