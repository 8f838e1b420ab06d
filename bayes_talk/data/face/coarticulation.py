"""Articulator tracks from a phone segmentation: per-phone targets, Cohen-Massaro
dominance blending, per-token variability, low-pass noise, the visual lead, blinks and
head pose (the first half of :func:`bayes_talk.data.face.face_landmarks`; the model and
its parameters are described in the :mod:`bayes_talk.data.face` docstring and
docs/face.md)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from bayes_talk.data.phones import (
    BILABIALS,
    LABIODENTALS,
    PHONE_TO_VISEME,
    PHONES,
    SILENCE,
    VOWELS,
    check_phone,
)

__all__ = [
    "ARTICULATORS",
    "N_ARTICULATORS",
    "FaceTrack",
    "articulator_targets",
    "dominance_parameters",
    "face_trajectories",
    "random_phone_intervals",
]

ARTICULATORS: tuple[str, ...] = ("jaw", "aperture", "spread", "protrusion", "raise", "tuck")
N_ARTICULATORS = len(ARTICULATORS)
_J, _A, _S, _P, _R, _K = range(N_ARTICULATORS)

# --------------------------------------------------------------------------------------
# Per-phone targets
# --------------------------------------------------------------------------------------
#: Per-viseme articulator targets (jaw, aperture, spread, protrusion, raise, tuck).
_VISEME_TARGETS: dict[int, tuple[float, ...]] = {
    0: (0.5, -0.5, 0.0, 0.0, 0.0, 0.0),    # sil: rest, mouth closed
    1: (1.0, -1.0, 0.0, 0.05, 0.0, 0.0),   # p b m: lips pressed together
    2: (1.0, 2.2, 0.0, 0.0, 2.0, 1.0),     # f v: lower lip under the upper teeth
    3: (2.0, 2.5, 0.1, 0.0, 0.5, 0.0),     # th dh
    4: (2.0, 2.5, 0.1, 0.0, 0.3, 0.0),     # t d
    5: (2.5, 3.0, 0.0, 0.0, 0.0, 0.0),     # k g ng hh
    6: (1.5, 2.0, -0.2, 0.8, 0.8, 0.0),    # ch jh sh zh: protruded
    7: (1.0, 1.5, 0.35, 0.0, 0.6, 0.0),    # s z: teeth together, slightly spread
    8: (2.0, 2.5, 0.1, 0.0, 0.2, 0.0),     # n l
    9: (1.5, 2.5, -0.4, 0.5, 0.3, 0.0),    # r er
    10: (6.0, 8.5, 0.15, 0.0, 0.5, 0.0),   # A: jaw wide open
    11: (4.5, 6.0, 0.35, 0.0, 0.4, 0.0),   # E
    12: (2.5, 3.5, 0.8, 0.0, 0.4, 0.0),    # I: spread
    13: (5.0, 6.0, -0.6, 0.5, 0.0, 0.0),   # O: open rounded
    14: (2.5, 2.5, -1.0, 0.9, 0.0, 0.0),   # U: narrow rounded
}
#: Phone-level refinements of the viseme table.
_PHONE_OVERRIDES: dict[str, tuple[float, ...]] = {
    "aa": (6.5, 9.0, 0.1, 0.0, 0.5, 0.0),
    "ae": (5.5, 8.0, 0.4, 0.0, 0.6, 0.0),
    "ah": (5.0, 7.0, 0.15, 0.0, 0.4, 0.0),
    "iy": (2.0, 3.0, 1.0, 0.0, 0.5, 0.0),
    "ih": (3.0, 4.0, 0.6, 0.0, 0.4, 0.0),
    "uh": (3.0, 3.5, -0.6, 0.5, 0.0, 0.0),
    "w": (1.5, 1.5, -1.0, 1.0, 0.0, 0.0),
}

_ROUNDED = frozenset(("uw", "uh", "ow", "ao", "oy", "w"))
_PROTRUDED = frozenset(("ch", "jh", "sh", "zh"))


@dataclass(frozen=True)
class _Dominance:
    alpha: tuple[float, ...]  # per articulator
    theta_ant: float          # 1/s, before the segment centre
    theta_car: float          # 1/s, after the segment centre


#: Dominance classes (alpha per articulator: jaw, aperture, spread, protrusion, raise, tuck).
_DOMINANCE: dict[str, _Dominance] = {
    "sil": _Dominance((1.0, 1.0, 1.0, 1.0, 1.0, 1.0), 5.0, 5.0),
    "bilabial": _Dominance((0.5, 2000.0, 0.3, 0.3, 1.0, 5.0), 100.0, 100.0),
    "labiodental": _Dominance((0.8, 1000.0, 0.5, 0.5, 500.0, 1000.0), 100.0, 100.0),
    "rounded": _Dominance((1.0, 1.5, 3.0, 3.0, 1.0, 1.0), 8.0, 14.0),
    "vowel": _Dominance((1.5, 1.5, 1.0, 1.0, 1.0, 1.0), 11.0, 14.0),
    "protruded": _Dominance((0.8, 1.0, 1.5, 2.0, 1.0, 1.0), 16.0, 16.0),
    "sibilant": _Dominance((1.5, 1.0, 0.8, 0.3, 0.8, 1.0), 16.0, 16.0),
    "aspirate": _Dominance((0.05,) * 6, 16.0, 16.0),
    "consonant": _Dominance((1.0, 0.8, 0.3, 0.3, 0.5, 1.0), 16.0, 16.0),
}
_DOMINANCE_EXPONENT = 1.0

#: Per-token target standard deviations (truncated at 2.5 sd), design units.
_TARGET_SD = np.array([0.6, 0.8, 0.08, 0.08, 0.3, 0.05])
#: Smooth articulatory noise: standard deviations and Gaussian low-pass width.
_NOISE_SD = np.array([0.3, 0.3, 0.04, 0.03, 0.15, 0.0])
_NOISE_SIGMA_S = 0.08        # Gaussian kernel sd in seconds (-3 dB near 2.3 Hz)
_BROW_NOISE_SD = 0.6         # eyebrow raise, design units
#: Physical ranges the articulators are clipped to.
_LOWER = np.array([0.0, 0.0, -1.2, 0.0, -0.5, 0.0])
_UPPER = np.array([10.0, 12.0, 1.2, 1.2, 3.0, 1.0])
#: Visual lead over audio, seconds (uniform per utterance).
_LEAD_RANGE_S = (0.020, 0.040)
#: Blinks: Poisson rate per second; closing / opening half-widths in seconds.
_BLINK_RATE = 0.3
_BLINK_CLOSE_S, _BLINK_OPEN_S = 0.04, 0.07
#: Head pose: per-utterance offsets and within-utterance smooth motion (sd), truncated at
#: 3 sd. Order: (tx, ty) design units, rotation rad, log scale.
_POSE_OFFSET_SD = np.array([1.5, 1.5, np.deg2rad(1.0), 0.02])
_POSE_MOTION_SD = np.array([0.8, 0.8, np.deg2rad(0.6), 0.01])
_POSE_SIGMA_S = 0.32


def _dominance_class(phone: str) -> str:
    if phone == SILENCE:
        return "sil"
    if phone in BILABIALS:
        return "bilabial"
    if phone in LABIODENTALS:
        return "labiodental"
    if phone in _ROUNDED:
        return "rounded"
    if phone in VOWELS:
        return "vowel"
    if phone in _PROTRUDED:
        return "protruded"
    if phone in ("s", "z"):
        return "sibilant"
    if phone == "hh":
        return "aspirate"
    return "consonant"


def articulator_targets(phone: str) -> np.ndarray:
    """Mean articulator target (6,) of a phone: its viseme's row, refined per phone.

    Order of :data:`ARTICULATORS`. Closures use a negative aperture ("lip compression")
    so the blended aperture reaches 0 despite neighbouring open vowels.
    """
    check_phone(phone, "articulator_targets")
    row = _PHONE_OVERRIDES.get(phone, _VISEME_TARGETS[PHONE_TO_VISEME[phone]])
    return np.array(row, dtype=np.float64)


def dominance_parameters(phone: str) -> tuple[np.ndarray, float, float]:
    """``(alpha (6,), theta_ant, theta_car)`` of a phone's dominance function (1/s)."""
    check_phone(phone, "dominance_parameters")
    d = _DOMINANCE[_dominance_class(phone)]
    return np.array(d.alpha, dtype=np.float64), d.theta_ant, d.theta_car


_TARGET_TABLE = np.stack([articulator_targets(p) for p in PHONES])
_DOM_TABLE = {p: dominance_parameters(p) for p in PHONES}


@dataclass(frozen=True)
class FaceTrack:
    """Per-frame control signals of one utterance.

    articulators : (T, 6) in :data:`ARTICULATORS` order, design units, clipped.
    blink : (T,) eyelid closure in [0, 1].
    pose : (T, 4) head pose (tx, ty, rotation rad, log scale) about the frame centre.
    brow : (T,) eyebrow raise, design units.
    lead_s : visual lead over the audio, seconds.
    """

    articulators: np.ndarray
    blink: np.ndarray
    pose: np.ndarray
    brow: np.ndarray
    lead_s: float


def _validate_intervals(intervals, n_frames: int, fps: float) -> tuple[np.ndarray, np.ndarray, list[str]]:
    if not isinstance(n_frames, (int, np.integer)) or isinstance(n_frames, bool) or n_frames < 1:
        raise ValueError(f"n_frames: expected a positive int, found {n_frames!r}")
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps: expected a positive finite number, found {fps!r}")
    if len(intervals) == 0:
        raise ValueError("intervals: expected at least one (start_s, end_s, phone), found none")
    starts, ends, phones = [], [], []
    for i, item in enumerate(intervals):
        if len(item) != 3:
            raise ValueError(f"intervals[{i}]: expected (start_s, end_s, phone), found {item!r}")
        s, e, p = float(item[0]), float(item[1]), str(item[2])
        check_phone(p, f"intervals[{i}]")
        if not (np.isfinite(s) and np.isfinite(e)) or s < 0 or e <= s:
            raise ValueError(f"intervals[{i}]: expected 0 <= start < end, found ({s}, {e})")
        if starts and s < ends[-1] - 1e-6:
            raise ValueError(
                f"intervals[{i}]: expected sorted, non-overlapping intervals; starts at {s} "
                f"before the previous end {ends[-1]}"
            )
        starts.append(s)
        ends.append(e)
        phones.append(p)
    return np.array(starts), np.array(ends), phones


def _truncated_normal(rng: np.random.Generator, sd: np.ndarray, size: tuple[int, ...], k: float) -> np.ndarray:
    return np.clip(rng.standard_normal(size), -k, k) * sd


def _smooth_noise(rng: np.random.Generator, n: int, sd: np.ndarray, sigma_frames: float) -> np.ndarray:
    """Gaussian-low-passed white noise (n, len(sd)) with stationary standard deviation sd.

    White noise of unit variance through a normalised Gaussian kernel of sd ``s`` frames
    has variance ``1 / (2 sqrt(pi) s)``; we rescale by its square root. Generated with a
    pad of 4 s on each side so the ends are not attenuated by the boundary.
    """
    pad = int(np.ceil(4 * sigma_frames))
    w = rng.standard_normal((n + 2 * pad, len(sd)))
    if sigma_frames > 0:
        w = gaussian_filter1d(w, sigma_frames, axis=0, mode="nearest")
        w *= np.sqrt(2.0 * np.sqrt(np.pi) * sigma_frames)
    return w[pad:pad + n] * sd


def _blink_track(rng: np.random.Generator, t: np.ndarray, duration: float) -> np.ndarray:
    """Eyelid closure from a Poisson process of blinks with asymmetric Gaussian profiles."""
    n_max = int(np.ceil(_BLINK_RATE * duration * 3 + 10))
    gaps = rng.exponential(1.0 / _BLINK_RATE, size=n_max)
    times = np.cumsum(gaps) - rng.uniform(0.0, 1.0 / _BLINK_RATE)
    times = times[(times > -0.3) & (times < duration + 0.3)]
    closure = np.zeros_like(t)
    for t0 in times:
        dt = t - t0
        w = np.where(dt < 0, _BLINK_CLOSE_S, _BLINK_OPEN_S)
        closure = np.maximum(closure, np.exp(-0.5 * (dt / w) ** 2))
    return closure


def face_trajectories(
    intervals: list[tuple[float, float, str]],
    n_frames: int,
    *,
    fps: float = 25.0,
    rng: np.random.Generator,
    given: dict[str, np.ndarray] | None = None,
) -> FaceTrack:
    """Articulator, blink, brow and head-pose tracks sampled at the frame centres.

    Frame ``k`` covers ``[k/fps, (k+1)/fps)`` and is sampled at ``(k + 0.5)/fps``; the
    face runs ``lead_s`` ahead of the audio (``lead_s ~ U(20, 40) ms`` per utterance), so
    articulation is evaluated at ``(k + 0.5)/fps + lead_s``. Random draws, in order:
    lead, per-token targets, articulatory noise, brow noise, blinks, pose offset, pose
    motion.

    ``given``: articulator name -> (n_frames,) track in design units, e.g. from a vocal
    tract (:mod:`bayes_talk.data.articulatory`); such a column replaces the blend and gets
    no face noise (but is clipped to the physical ranges). The random draws are the same
    with or without it, so every other component (brows, blinks, pose, the remaining
    articulators) is identical for the same ``rng``.
    """
    if not isinstance(rng, np.random.Generator):
        # ValueError, not TypeError: the project convention for every bad input.
        raise ValueError(f"rng: expected a numpy.random.Generator, found {type(rng).__name__}")  # noqa: TRY004
    starts, ends, phones = _validate_intervals(intervals, n_frames, fps)
    n_seg = len(phones)
    t_frame = (np.arange(n_frames) + 0.5) / fps
    lead = float(rng.uniform(*_LEAD_RANGE_S))
    t = t_frame + lead

    # Per-token targets and dominance parameters.
    base = np.stack([_TARGET_TABLE[PHONES.index(p)] for p in phones])
    targets = base + _truncated_normal(rng, _TARGET_SD, (n_seg, N_ARTICULATORS), 2.5)
    # Closures stay closures: a token of a closed-lip target varies only towards more
    # compression (lip contact is a hard constraint, not a noisy target).
    closed = base[:, _A] <= 0
    targets[closed, _A] = base[closed, _A] - np.abs(targets[closed, _A] - base[closed, _A])
    log_alpha = np.log(np.stack([_DOM_TABLE[p][0] for p in phones]))        # (S, 6)
    theta_ant = np.array([_DOM_TABLE[p][1] for p in phones])
    theta_car = np.array([_DOM_TABLE[p][2] for p in phones])
    # The face leads the audio by ``lead`` (anticipatory movement), except lip contact:
    # the acoustic closure of /p b m f v/ starts when the lips meet, so the closure
    # segments are shifted with the lead and stay synchronous with the audio.
    contact = np.array([p in BILABIALS or p in LABIODENTALS for p in phones])
    centres = 0.5 * (starts + ends) + np.where(contact, lead, 0.0)

    # Cohen-Massaro blend as a softmax over segments of log D (T, S, 6).
    tau = t[:, None] - centres[None, :]
    theta = np.where(tau < 0, theta_ant[None, :], theta_car[None, :])
    log_d = log_alpha[None, :, :] - (theta * np.abs(tau) ** _DOMINANCE_EXPONENT)[:, :, None]
    log_d -= log_d.max(axis=1, keepdims=True)
    d = np.exp(log_d)
    art = np.einsum("tsj,sj->tj", d, targets) / d.sum(axis=1)

    sigma_frames = _NOISE_SIGMA_S * fps
    noise = _smooth_noise(rng, n_frames, _NOISE_SD, sigma_frames)
    # Aperture noise fades out as the lips close (full above 1 unit, none at contact).
    noise[:, _A] *= np.clip(art[:, _A], 0.0, 1.0)
    for name, track in (given or {}).items():
        if name not in ARTICULATORS:
            raise ValueError(f"given: unknown articulator {name!r}; expected one of {ARTICULATORS}")
        track = np.asarray(track, dtype=np.float64)
        if track.shape != (n_frames,) or not np.all(np.isfinite(track)):
            raise ValueError(f"given[{name!r}]: expected {n_frames} finite values, found shape {track.shape}")
        j = ARTICULATORS.index(name)
        art[:, j] = track
        noise[:, j] = 0.0
    art = art + noise
    art = np.clip(art, _LOWER, _UPPER)
    brow = _smooth_noise(rng, n_frames, np.array([_BROW_NOISE_SD]), sigma_frames)[:, 0]

    duration = max(float(ends[-1]), n_frames / fps)
    blink = _blink_track(rng, t_frame, duration)

    offset = _truncated_normal(rng, _POSE_OFFSET_SD, (4,), 3.0)
    motion = _smooth_noise(rng, n_frames, _POSE_MOTION_SD, _POSE_SIGMA_S * fps)
    motion = np.clip(motion, -3 * _POSE_MOTION_SD, 3 * _POSE_MOTION_SD)
    pose = offset[None, :] + motion
    return FaceTrack(articulators=art, blink=blink, pose=pose, brow=brow, lead_s=lead)


_CV_CONSONANTS = tuple(p for p in PHONES if p != "sil" and p not in VOWELS)
_CV_VOWELS = tuple(sorted(VOWELS))


def random_phone_intervals(rng: np.random.Generator, n_frames: int,
                           fps: float = 25.0) -> list[tuple[float, float, str]]:
    """Random phone intervals for face-only experiments (no speech needed): silence, then
    consonant–vowel syllables with random phones (consonants 60–120 ms, vowels 90–200 ms),
    then silence to the end of ``n_frames`` frames."""
    dur = n_frames / fps
    t = float(rng.uniform(0.1, 0.3))
    out = [(0.0, t, "sil")]
    k = 0
    while t < dur - 0.3:
        if k % 2 == 0:
            p, d = _CV_CONSONANTS[rng.integers(len(_CV_CONSONANTS))], rng.uniform(0.06, 0.12)
        else:
            p, d = _CV_VOWELS[rng.integers(len(_CV_VOWELS))], rng.uniform(0.09, 0.2)
        out.append((t, t + float(d), p))
        t += float(d)
        k += 1
    out.append((t, dur, "sil"))
    return out
