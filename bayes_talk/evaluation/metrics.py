"""Error, correlation and calibration metrics (docs/evaluation.md).

Inputs are per-utterance arrays: ``truth`` and ``pred`` are lists of (T_i, D) arrays
(a single 2-D array is one utterance, a 3-D array (n, T, D) is n utterances of equal
length). Shapes must agree utterance by utterance and contain no NaN/inf; otherwise a
ValueError names the problem.

Per-utterance errors, with e_td = ẑ_td − z_td over T frames and D dimensions:

    MSE   = (1 / TD) Σ_t Σ_d e_td²                        (deena2010 §5, "mean squared error")
    RMS   = √MSE                                          (deena2009 §4.4)
    L1    = (1 / T) Σ_t Σ_d |e_td|                        (englebienne2008 Fig. 4a: mean L1 distance
                                                           between generated and real frames)
    L∞    = (1 / T) Σ_t max_d |e_td|                      (englebienne2008 Fig. 4c: mean L∞ distance)
    NMSE  = (1 / D) Σ_d [ (1/T) Σ_t e_td² ] / v_d         (MSE normalised by the ground-truth variance
                                                           v_d; corpora differ in scale)
    CORR  = (1 / |D'|) Σ_{d ∈ D'} Pearson(ẑ_·d, z_·d)     (D' = dimensions where both series vary)

Corpus figures (deena2010 §5): AMSE = mean over utterances of MSE; ACC = mean over
utterances of CORR. A dimension that is constant in the truth or in the prediction has an
undefined Pearson correlation: it is skipped (not counted as 0); an utterance with no
usable dimension has CORR = nan and is skipped by ACC (with a warning).

Calibration of Gaussian predictive bands (docs/uncertainty.md), pooled over every scalar entry of
every utterance: :func:`coverage`, :func:`crps_gaussian` (closed form),
:func:`crps_ensemble` (samples), :func:`nlpd_gaussian`. Entry-wise forms
(:func:`crps_gaussian_entries`, :func:`crps_sample_entries`) feed the per-parameter
calibration report of :mod:`bayes_talk.evaluation.calibration` (mixture predictives:
coverage of the exact bands, PIT, mixture NLPD, sample CRPS).

The field's landmark metrics (FaceFormer's LVE, CodeTalker's FDD, ProbTalk3D's sample metrics),
on 2-D landmarks: ``truth`` and ``pred`` are lists of (T_i, P, 2) landmark tracks (pixels),
``samples`` lists of (N, T_i, P, 2) draws. With x̂_tv, x_tv the predicted and true position of landmark v at frame t:

    LVE   = (1/T) Σ_t max_{v ∈ L} ‖x̂_tv − x_tv‖²            lips L; squared distance, as FaceFormer's
                                                           lip vertex error (:func:`lip_vertex_error`)
    MOE   = (1/T) Σ_t | ‖x̂_ta − x̂_tb‖ − ‖x_ta − x_tb‖ |    mouth opening (a, b) = upper and lower lip
                                                           midpoints (:func:`mouth_opening_error`)
    FDD   = (1/|U|) Σ_{v ∈ U} | sd_t(‖x̂_tv − r_v‖²) − sd_t(‖x_tv − r_v‖²) |
                                                           upper face U, reference face r, sd the
                                                           population std over frames
                                                           (:func:`upper_face_dynamics_deviation`)
    DIV   = 2 / (N(N−1)) Σ_{i<j} (1/(TP)) Σ_t Σ_v ‖x^i_tv − x^j_tv‖
                                                           diversity of N draws (:func:`sample_diversity`)
    MEE   = LVE of the draws' average (1/N) Σ_i x^i        (:func:`mean_of_samples_error`)
    CE    = min_i LVE(x^i)                                 best of N (:func:`best_of_n_error`)

Each is per utterance (an (n,) array); the corpus figure is its mean over utterances, as AMSE.
"""
from __future__ import annotations

import warnings
from collections.abc import Sequence as Seq

import numpy as np
import scipy.stats

__all__ = [
    "acc",
    "amse",
    "best_of_n_error",
    "correlation",
    "coverage",
    "crps_ensemble",
    "crps_gaussian",
    "crps_gaussian_entries",
    "crps_sample_entries",
    "l1",
    "linf",
    "lip_vertex_error",
    "mean_of_samples_error",
    "mouth_opening",
    "mouth_opening_error",
    "mse",
    "nlpd_gaussian",
    "normalised_mse",
    "rms",
    "sample_diversity",
    "summarise",
    "upper_face_dynamics_deviation",
]

ArrayList = Seq[np.ndarray] | np.ndarray


def _as_list(x: ArrayList, what: str, ndim: int = 2) -> list[np.ndarray]:
    if isinstance(x, np.ndarray):
        if x.ndim == ndim:
            items = [x]
        elif x.ndim == ndim + 1:
            items = list(x)
        else:
            raise ValueError(f"{what}: expected a list of {ndim}-D arrays, got an array of shape {x.shape}")
    else:
        items = list(x)
    if not items:
        raise ValueError(f"{what}: no utterances")
    out = []
    for i, a in enumerate(items):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != ndim:
            raise ValueError(f"{what}[{i}]: expected a {ndim}-D array, got shape {a.shape}")
        if a.size == 0:
            raise ValueError(f"{what}[{i}]: empty array of shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what}[{i}]: contains NaN or inf")
        out.append(a)
    return out


def _pairs(truth: ArrayList, other: ArrayList, name: str = "pred") -> list[tuple[np.ndarray, np.ndarray]]:
    t = _as_list(truth, "truth")
    o = _as_list(other, name)
    if len(t) != len(o):
        raise ValueError(f"{len(t)} truth utterances but {len(o)} {name} utterances")
    for i, (a, b) in enumerate(zip(t, o)):
        if a.shape != b.shape:
            raise ValueError(f"utterance {i}: {name} has shape {b.shape}, expected {a.shape} (truth)")
    return list(zip(t, o))


def mse(truth: ArrayList, pred: ArrayList) -> np.ndarray:
    """Per-utterance mean squared error (n,)."""
    return np.array([np.mean((p - t) ** 2) for t, p in _pairs(truth, pred)])


def rms(truth: ArrayList, pred: ArrayList) -> np.ndarray:
    """Per-utterance root mean squared error √MSE (n,)."""
    return np.sqrt(mse(truth, pred))


def l1(truth: ArrayList, pred: ArrayList) -> np.ndarray:
    """Per-utterance mean over frames of the L1 distance Σ_d |e_td| (n,)."""
    return np.array([np.mean(np.sum(np.abs(p - t), axis=1)) for t, p in _pairs(truth, pred)])


def linf(truth: ArrayList, pred: ArrayList) -> np.ndarray:
    """Per-utterance mean over frames of the L∞ distance max_d |e_td| (n,)."""
    return np.array([np.mean(np.max(np.abs(p - t), axis=1)) for t, p in _pairs(truth, pred)])


def normalised_mse(truth: ArrayList, pred: ArrayList, variance: np.ndarray | None = None) -> np.ndarray:
    """Per-utterance variance-normalised MSE (n,): mean over d of MSE_d / v_d.

    ``variance`` (D,) is the ground-truth variance per dimension; by default the variance
    of the pooled truth frames of all given utterances (stable for short utterances and
    the same normaliser for every model). Dimensions with v_d = 0 are skipped.
    """
    pairs = _pairs(truth, pred)
    D = pairs[0][0].shape[1]
    if any(t.shape[1] != D for t, _ in pairs):
        raise ValueError("normalised_mse: utterances have different numbers of dimensions")
    if variance is None:
        v = np.concatenate([t for t, _ in pairs]).var(axis=0)
    else:
        v = np.asarray(variance, dtype=np.float64)
        if v.shape != (D,):
            raise ValueError(f"variance has shape {v.shape}, expected ({D},)")
        if np.any(~np.isfinite(v)) or np.any(v < 0):
            raise ValueError("variance must be finite and non-negative")
    keep = v > 0
    if not keep.any():
        raise ValueError("normalised_mse: the ground truth is constant in every dimension")
    return np.array([np.mean(np.mean((p - t) ** 2, axis=0)[keep] / v[keep]) for t, p in pairs])


def correlation(truth: ArrayList, pred: ArrayList) -> np.ndarray:
    """Per-utterance mean over dimensions of the Pearson correlation (n,).

    Dimensions where the truth is constant are skipped (nan if none remain); a dimension
    where the truth varies but the prediction is constant counts as correlation 0 (a still
    prediction follows nothing), so a method cannot raise its ACC by predicting some
    dimensions as constants (e.g. a mean shrunk to zero there).
    """
    out = []
    for t, p in _pairs(truth, pred):
        tc, pc = t - t.mean(axis=0), p - p.mean(axis=0)
        st, sp_ = np.sqrt(np.sum(tc * tc, axis=0)), np.sqrt(np.sum(pc * pc, axis=0))
        scale = np.maximum(np.abs(t).max(axis=0), np.abs(p).max(axis=0)) * np.sqrt(t.shape[0])
        ok_t = st > 1e-12 * scale
        if not ok_t.any():
            out.append(np.nan)
            continue
        ok = ok_t & (sp_ > 1e-12 * scale)
        r = np.zeros(int(ok_t.sum()))
        r[ok[ok_t]] = np.sum(tc[:, ok] * pc[:, ok], axis=0) / (st[ok] * sp_[ok])
        out.append(float(np.mean(np.clip(r, -1.0, 1.0))))
    return np.array(out)


def amse(truth: ArrayList, pred: ArrayList) -> float:
    """AMSE: mean over utterances of the per-utterance MSE (deena2010 §5)."""
    return float(np.mean(mse(truth, pred)))


def acc(truth: ArrayList, pred: ArrayList) -> float:
    """ACC: mean over utterances of :func:`correlation` (utterances with nan skipped)."""
    c = correlation(truth, pred)
    bad = np.isnan(c)
    if bad.all():
        warnings.warn("acc: no utterance has a usable (non-constant) dimension", RuntimeWarning, stacklevel=2)
        return float("nan")
    if bad.any():
        warnings.warn(f"acc: {int(bad.sum())} utterance(s) without a usable dimension skipped",
                      RuntimeWarning, stacklevel=2)
    return float(np.mean(c[~bad]))


def summarise(values: Seq[float] | np.ndarray, level: float = 0.95) -> dict[str, object]:
    """Mean, sample std (ddof=1), t confidence interval of the mean and n.

        ci = mean ± t_{(1+level)/2, n−1} · std / √n

    Non-finite values (e.g. an undefined correlation) are dropped with a warning and not
    counted in n. With n = 1 the std and the interval are nan. The key is ``"ci95"``
    whatever ``level`` is.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        raise ValueError("summarise: no values")
    fin = np.isfinite(v)
    if not fin.all():
        warnings.warn(f"summarise: {int((~fin).sum())} non-finite value(s) dropped", RuntimeWarning,
                      stacklevel=2)
        v = v[fin]
    n = int(v.size)
    if n == 0:
        raise ValueError("summarise: all values are NaN or inf")
    mean = float(v.mean())
    if n < 2:
        return {"mean": mean, "std": float("nan"), "ci95": [float("nan"), float("nan")], "n": n}
    std = float(v.std(ddof=1))
    half = float(scipy.stats.t.ppf(0.5 + level / 2, n - 1)) * std / np.sqrt(n)
    return {"mean": mean, "std": std, "ci95": [mean - half, mean + half], "n": n}


def coverage(truth: ArrayList, lower: ArrayList, upper: ArrayList) -> float:
    """Fraction of truth entries with lower ≤ z ≤ upper, pooled over all utterances."""
    lo = _pairs(truth, lower, "lower")
    up = _pairs(truth, upper, "upper")
    inside = total = 0
    for (t, l), (_, u) in zip(lo, up):
        if np.any(l > u):
            raise ValueError("coverage: lower bound above upper bound")
        inside += int(np.sum((t >= l) & (t <= u)))
        total += t.size
    return inside / total


def crps_gaussian_entries(z: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Entry-wise CRPS of N(μ, σ²) at z, closed form (Gneiting & Raftery 2007, eq. 21):

        CRPS = σ [ w (2Φ(w) − 1) + 2 φ(w) − 1/√π ],   w = (z − μ) / σ   (σ > 0).
    """
    z, mean, std = (np.asarray(a, dtype=np.float64) for a in (z, mean, std))
    if np.any(std <= 0):
        raise ValueError("crps_gaussian: std must be > 0")
    w = (z - mean) / std
    return std * (w * (2 * scipy.stats.norm.cdf(w) - 1) + 2 * scipy.stats.norm.pdf(w) - 1 / np.sqrt(np.pi))


def crps_gaussian(truth: ArrayList, mean: ArrayList, std: ArrayList) -> float:
    """Mean CRPS of Gaussian predictives N(μ, σ²), closed form (:func:`crps_gaussian_entries`),
    pooled over every entry of every utterance."""
    pm, ps = _pairs(truth, mean, "mean"), _pairs(truth, std, "std")
    tot = n = 0.0
    for (t, m), (_, s) in zip(pm, ps):
        c = crps_gaussian_entries(t, m, s)
        tot += c.sum()
        n += c.size
    return float(tot / n)


def crps_sample_entries(z: np.ndarray, samples: np.ndarray, fair: bool = False) -> np.ndarray:
    """Entry-wise CRPS of a predictive given by m samples (m, *z.shape), energy form
    (Gneiting & Raftery 2007, eq. 20):

        CRPS = (1/m) Σ_i |x_i − z| − (1 / 2m²) Σ_i Σ_j |x_i − x_j|

    (``fair=False``: the exact CRPS of the sample distribution; ``fair=True``: the second
    term over m(m − 1) instead of m², unbiased for the CRPS of the distribution sampled;
    Ferro 2014). The double sum uses the sorted-sample identity
    Σ_i Σ_j |x_i − x_j| = 2 Σ_k (2k − m − 1) x_(k), k = 1..m, so the cost is O(m log m).
    """
    z = np.asarray(z, dtype=np.float64)
    s = np.asarray(samples, dtype=np.float64)
    if s.shape[1:] != z.shape:
        raise ValueError(f"samples have shape {s.shape}, expected (m, *{z.shape})")
    m = s.shape[0]
    if m < (2 if fair else 1):
        raise ValueError(f"crps_sample_entries: need at least {2 if fair else 1} samples, got {m}")
    term1 = np.mean(np.abs(s - z[None]), axis=0)
    xs = np.sort(s, axis=0)
    k = np.arange(1, m + 1, dtype=np.float64).reshape(-1, *([1] * z.ndim))
    pair_sum = 2.0 * np.sum((2 * k - m - 1) * xs, axis=0)          # Σ_i Σ_j |x_i − x_j|
    return term1 - pair_sum / (2.0 * m * (m - 1 if fair else m))


def crps_ensemble(truth: ArrayList, samples: ArrayList) -> float:
    """Mean CRPS of the empirical distribution of m samples per entry
    (:func:`crps_sample_entries`, the plain estimator), pooled over every entry of every
    utterance. ``samples`` is a list of (m, T_i, D) arrays.
    """
    t_list = _as_list(truth, "truth")
    s_list = _as_list(samples, "samples", ndim=3)
    if len(t_list) != len(s_list):
        raise ValueError(f"{len(t_list)} truth utterances but {len(s_list)} sample sets")
    tot = n = 0.0
    for i, (t, s) in enumerate(zip(t_list, s_list)):
        if s.shape[1:] != t.shape:
            raise ValueError(f"utterance {i}: samples have shape {s.shape}, expected (m, *{t.shape})")
        c = crps_sample_entries(t, s)
        tot += c.sum()
        n += c.size
    return float(tot / n)


def nlpd_gaussian(truth: ArrayList, mean: ArrayList, var: ArrayList) -> float:
    """Mean negative log predictive density per entry: ½ log(2π σ²) + (z − μ)² / (2σ²)."""
    pm, pv = _pairs(truth, mean, "mean"), _pairs(truth, var, "var")
    tot = n = 0.0
    for (t, m), (_, v) in zip(pm, pv):
        if np.any(v <= 0):
            raise ValueError("nlpd_gaussian: var must be > 0")
        tot += np.sum(0.5 * np.log(2 * np.pi * v) + (t - m) ** 2 / (2 * v))
        n += t.size
    return float(tot / n)


# ------------------------------------------------------------------------------ landmarks
def _tracks(x: ArrayList, what: str, ndim: int = 3) -> list[np.ndarray]:
    """Landmark tracks (.., T, P, 2) of every utterance, checked (finite, last axis 2)."""
    items = _as_list(x, what, ndim=ndim)
    for i, a in enumerate(items):
        if a.shape[-1] != 2:
            raise ValueError(f"{what}[{i}]: expected 2-D landmarks (..., P, 2), got shape {a.shape}")
    return items


def _track_pairs(truth: ArrayList, pred: ArrayList, name: str = "pred") -> list[tuple[np.ndarray, np.ndarray]]:
    t, p = _tracks(truth, "truth"), _tracks(pred, name)
    if len(t) != len(p):
        raise ValueError(f"{len(t)} truth utterances but {len(p)} {name} utterances")
    for i, (a, b) in enumerate(zip(t, p)):
        if a.shape != b.shape:
            raise ValueError(f"utterance {i}: {name} has shape {b.shape}, expected {a.shape} (truth)")
    return list(zip(t, p))


def _indices(idx, n_points: int, what: str) -> np.ndarray:
    ix = np.asarray(idx)
    if ix.ndim != 1 or ix.size == 0 or not np.issubdtype(ix.dtype, np.integer):
        raise ValueError(f"{what}: expected a non-empty 1-D array of landmark indices, got {idx!r}")
    if ix.min() < 0 or ix.max() >= n_points:
        raise ValueError(f"{what}: landmark indices must lie in [0, {n_points}), got {ix.min()}..{ix.max()}")
    return ix


def _lve_frames(truth: np.ndarray, pred: np.ndarray, lips) -> np.ndarray:
    """Per frame (.., T): the largest squared distance over the lip landmarks."""
    ix = _indices(lips, truth.shape[-2], "lips")
    d2 = np.sum((pred[..., ix, :] - truth[..., ix, :]) ** 2, axis=-1)
    return d2.max(axis=-1)


def lip_vertex_error(truth: ArrayList, pred: ArrayList, lips) -> np.ndarray:
    """Per-utterance lip error in FaceFormer's LVE form (n,):

        LVE = (1/T) Σ_t max_{v ∈ L} ‖x̂_tv − x_tv‖²

    the largest *squared* Euclidean error over the lip landmarks ``lips`` (indices L) in each
    frame, averaged over the frames (units: pixels²).
    """
    return np.array([float(np.mean(_lve_frames(t, p, lips))) for t, p in _track_pairs(truth, pred)])


def mouth_opening(landmarks: np.ndarray, pair: tuple[int, int]) -> np.ndarray:
    """Mouth opening (T,) of a track (T, P, 2): the distance ‖x_ta − x_tb‖ between the two
    landmarks of ``pair`` = (a, b), the upper and lower lip midpoints."""
    lm = np.asarray(landmarks, dtype=np.float64)
    if lm.ndim != 3:
        raise ValueError(f"landmarks: expected one track of shape (T, P, 2), got shape {lm.shape}")
    lm = _tracks(lm, "landmarks")[0]
    if len(pair) != 2 or pair[0] == pair[1]:
        raise ValueError(f"pair: expected two different landmark indices, got {pair!r}")
    a, b = _indices(list(pair), lm.shape[1], "pair")
    return np.linalg.norm(lm[:, a] - lm[:, b], axis=-1)


def mouth_opening_error(truth: ArrayList, pred: ArrayList, pair: tuple[int, int]) -> np.ndarray:
    """Per-utterance mean absolute error of the mouth opening (n,):

        MOE = (1/T) Σ_t | o(x̂)_t − o(x)_t |,   o(x)_t = ‖x_ta − x_tb‖   (:func:`mouth_opening`)
    """
    return np.array([float(np.mean(np.abs(mouth_opening(p, pair) - mouth_opening(t, pair))))
                     for t, p in _track_pairs(truth, pred)])


def upper_face_dynamics_deviation(truth: ArrayList, pred: ArrayList, upper, reference: ArrayList) -> np.ndarray:
    """Per-utterance upper-face dynamics deviation in CodeTalker's FDD form (n,):

        m_tv = ‖x_tv − r_v‖²                                   motion of landmark v (squared
                                                               displacement from the reference r)
        FDD  = (1/|U|) Σ_{v ∈ U} | sd_t(m̂_tv) − sd_t(m_tv) |

    over the upper-face landmarks ``upper`` (indices U); sd_t is the population standard
    deviation over the T frames, ``reference`` one (P, 2) reference face per utterance (the
    template: the same for prediction and truth). Units: pixels². CodeTalker's code (and
    ProbTalk3D's) takes the signed difference of the two region means, sd of the truth minus sd
    of the prediction; here each landmark's difference counts in absolute value, so that a
    landmark moving too much cannot cancel one moving too little.
    """
    pairs = _track_pairs(truth, pred)
    refs = _as_list(reference, "reference", ndim=2)
    if len(refs) != len(pairs):
        raise ValueError(f"{len(pairs)} utterances but {len(refs)} reference faces")
    out = []
    for i, ((t, p), r) in enumerate(zip(pairs, refs)):
        if r.shape != t.shape[1:]:
            raise ValueError(f"reference[{i}]: expected shape {t.shape[1:]}, got {r.shape}")
        ix = _indices(upper, t.shape[1], "upper")
        sd_t = np.std(np.sum((t[:, ix] - r[ix]) ** 2, axis=-1), axis=0)
        sd_p = np.std(np.sum((p[:, ix] - r[ix]) ** 2, axis=-1), axis=0)
        out.append(float(np.mean(np.abs(sd_p - sd_t))))
    return np.array(out)


def _sample_sets(samples: ArrayList, min_draws: int) -> list[np.ndarray]:
    sets = _tracks(samples, "samples", ndim=4)
    for i, s in enumerate(sets):
        if s.shape[0] < min_draws:
            raise ValueError(f"samples[{i}]: need at least {min_draws} draws, got {s.shape[0]}")
    return sets


def sample_diversity(samples: ArrayList) -> np.ndarray:
    """Per-utterance diversity of N ≥ 2 draws (N, T, P, 2) (n,): the mean landmark distance
    between two different draws, over every pair of draws, frame and landmark,

        DIV = 2 / (N(N−1)) Σ_{i<j} (1/(TP)) Σ_t Σ_v ‖x^i_tv − x^j_tv‖   (pixels).

    ProbTalk3D averages the same distance over N/2 disjoint pairs of a shuffled set; every
    pair estimates the same expectation with less noise.
    """
    out = []
    for s in _sample_sets(samples, 2):
        n = s.shape[0]
        tot = 0.0
        for i in range(n - 1):
            tot += float(np.sum(np.mean(np.linalg.norm(s[i + 1:] - s[i], axis=-1), axis=(1, 2))))
        out.append(tot / (n * (n - 1) / 2))
    return np.array(out)


def _truth_and_samples(truth: ArrayList, samples: ArrayList) -> list[tuple[np.ndarray, np.ndarray]]:
    t, s = _tracks(truth, "truth"), _sample_sets(samples, 1)
    if len(t) != len(s):
        raise ValueError(f"{len(t)} truth utterances but {len(s)} sample sets")
    for i, (a, b) in enumerate(zip(t, s)):
        if b.shape[1:] != a.shape:
            raise ValueError(f"utterance {i}: samples have shape {b.shape}, expected (N, *{a.shape})")
    return list(zip(t, s))


def mean_of_samples_error(truth: ArrayList, samples: ArrayList, lips) -> np.ndarray:
    """Per-utterance lip error of the draws' average (ProbTalk3D's mean estimate error) (n,):
    :func:`lip_vertex_error` of (1/N) Σ_i x^i against the truth (pixels²)."""
    return np.array([float(np.mean(_lve_frames(t, s.mean(axis=0), lips))) for t, s in _truth_and_samples(truth, samples)])


def best_of_n_error(truth: ArrayList, samples: ArrayList, lips) -> np.ndarray:
    """Per-utterance best-of-N lip error (ProbTalk3D's closest error) (n,): the smallest
    :func:`lip_vertex_error` of a single draw, min_i LVE(x^i) (pixels²)."""
    return np.array([float(np.min(np.mean(_lve_frames(t[None], s, lips), axis=-1)))
                     for t, s in _truth_and_samples(truth, samples)])
