"""Synthetic 2-D landmark face driven by coarticulated articulatory parameters.

This is the face side of the built-in talking-head corpus (DESIGN.md §8; parameter choices
and their reasons are collected in ``docs/face.md``). One call,
:func:`face_landmarks`, turns a phone segmentation into per-frame landmarks::

    intervals (start_s, end_s, phone) --Cohen-Massaro blend--> articulators (T, 6)
        + per-token target variability + low-pass noise + visual lead
    articulators, blinks, head pose --geometry--> landmarks (T, 57, 2) in pixels

Articulators (:data:`ARTICULATORS`), in *design units* (1 unit = 1 pixel of a 136-pixel
frame, i.e. ``image_size / 136`` pixels):

==========  =====================================================================
jaw         vertical jaw drop (chin and jaw line move down), units
aperture    inner-lip opening at the midline, units; clipped at 0 (lips touch)
spread      lip spreading (> 0, wide, /iy/) or rounding (< 0, narrow, /uw/), ~[-1, 1]
protrusion  lip protrusion in [0, 1]; frontal view: narrowing + vertical thickening
raise       upper-lip raise, units (shows the upper teeth, /f v/)
tuck        lower lip tucked under the upper teeth in [0, 1] (thins the lower lip)
==========  =====================================================================

Coarticulation (Cohen & Massaro 1993). Segment ``s`` with centre ``c_s`` exerts, for each
articulator ``j``, its target ``T_sj`` with dominance::

    D_sj(t) = alpha_sj * exp(-theta_s^{ant|car} * |t - c_s|**c),   c = 1

(``theta_ant`` for ``t < c_s``: the segment's influence on what comes before it;
``theta_car`` for ``t >= c_s``), and the articulator track is
``x_j(t) = sum_s D_sj T_sj / sum_s D_sj`` (computed as a softmax of ``log D`` for
numerical range). Bilabials and labiodentals are strongly but locally dominant on lip
aperture (alpha 2000 / 1000 with theta 100/s: they win inside their segment and fall
below a vowel's alpha 1.5 about 70 ms from their centre) with a negative "compression"
aperture target, so after clipping at 0 the lips really close; vowels are weakly
dominant on lip shape (alpha ~1) except the rounded ones, whose rounding spreads into
neighbouring consonants (alpha 3, slower anticipatory decay 8/s); ``hh`` is transparent
(alpha 0.05). The face leads the audio by 20-40 ms, except lip contact of /p b m f v/,
which stays synchronous with the acoustic closure.

All randomness comes from the ``rng`` argument, drawn in a fixed order, so the same seed
gives bit-identical landmarks.
"""
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
    "DESIGN_SIZE",
    "LANDMARK_GROUPS",
    "N_ARTICULATORS",
    "N_LANDMARKS",
    "FaceTrack",
    "articulator_targets",
    "dominance_parameters",
    "face_landmarks",
    "face_trajectories",
    "inner_lip_aperture",
    "reference_shape",
    "rest_shape",
    "shape_from_articulators",
]

ARTICULATORS: tuple[str, ...] = ("jaw", "aperture", "spread", "protrusion", "raise", "tuck")
N_ARTICULATORS = len(ARTICULATORS)
_J, _A, _S, _P, _R, _K = range(N_ARTICULATORS)

#: The face is designed in a 136-unit frame and scaled to ``image_size`` pixels, which
#: leaves a margin of >= 4 px at 128 px for the largest jaw drop and head motion.
DESIGN_SIZE = 136.0

# --------------------------------------------------------------------------------------
# Landmark layout (57 points). Index ranges are fixed; docs/face.md has a figure-free table.
# --------------------------------------------------------------------------------------
_GROUP_SIZES = (
    ("jaw", 9),          # left temple -> chin -> right temple
    ("forehead", 5),     # right -> top -> left (closes the face outline)
    ("brow_left", 3),
    ("brow_right", 3),
    ("eye_left", 6),     # outer corner, upper x2, inner corner, lower x2 (clockwise)
    ("eye_right", 6),    # inner corner, upper x2, outer corner, lower x2
    ("nose", 5),         # bridge, tip, left ala, right ala, subnasale
    ("outer_lip", 12),   # left corner, upper x5 (left->right), right corner, lower x5
    ("inner_lip", 8),    # left corner, upper x3 (left->right), right corner, lower x3
)
LANDMARK_GROUPS: dict[str, np.ndarray] = {}
_start = 0
for _name, _n in _GROUP_SIZES:
    LANDMARK_GROUPS[_name] = np.arange(_start, _start + _n)
    _start += _n
N_LANDMARKS = _start
del _start, _name, _n

# Fractions of the half-widths at which lip points sit.
_OUTER_U = np.array([-0.6, -0.25, 0.0, 0.25, 0.6])
_INNER_U = np.array([-0.5, 0.0, 0.5])
_EYE_U = np.array([-0.4, 0.4])

# Neutral geometry (design units, origin at the frame centre, y down).
_FACE_CY = -2.0          # face ellipse centre
_FACE_A = 44.0           # half width
_FACE_B_TOP = 50.0       # forehead height above the centre
_FACE_B_BOT = 48.0       # chin depth below the centre (chin at y = 46)
_EYE_CX, _EYE_CY, _EYE_HW = 19.0, -11.0, 8.5
_EYE_UP, _EYE_LO = 4.0, 2.8
_LIP_Y0 = 25.0           # lip line at rest
_LIP_HW = 15.0           # outer half width at rest
_LIP_INNER_INSET = 2.5   # inner corner inset from the outer corner
_UPPER_THICK, _LOWER_THICK = 5.0, 6.0
_NOSE = np.array([[0.0, -10.0], [0.0, 8.0], [-6.0, 11.0], [6.0, 11.0], [0.0, 13.5]])
_BROW = np.array([[-30.0, -20.0], [-20.0, -24.0], [-9.0, -21.0]])

#: Upper-teeth edge (fixed to the skull) and lower-teeth top (fixed to the jaw), design
#: units; used by the renderer to paint teeth in the mouth cavity.
UPPER_TEETH_Y = _LIP_Y0 + 2.5
LOWER_TEETH_BELOW_CHIN = (_FACE_CY + _FACE_B_BOT) - (_LIP_Y0 + 3.0)

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
) -> FaceTrack:
    """Articulator, blink, brow and head-pose tracks sampled at the frame centres.

    Frame ``k`` covers ``[k/fps, (k+1)/fps)`` and is sampled at ``(k + 0.5)/fps``; the
    face runs ``lead_s`` ahead of the audio (``lead_s ~ U(20, 40) ms`` per utterance), so
    articulation is evaluated at ``(k + 0.5)/fps + lead_s``. Random draws, in order:
    lead, per-token targets, articulatory noise, brow noise, blinks, pose offset, pose
    motion.
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


def _check_image_size(image_size: int) -> None:
    if not isinstance(image_size, (int, np.integer)) or isinstance(image_size, bool) or image_size < 32:
        raise ValueError(f"image_size: expected an int >= 32, found {image_size!r}")


def shape_from_articulators(
    articulators: np.ndarray,
    blink: np.ndarray | None = None,
    pose: np.ndarray | None = None,
    brow: np.ndarray | None = None,
    image_size: int = 128,
) -> np.ndarray:
    """Landmarks (T, 57, 2) in pixels (x = column, y = row) from control signals.

    Geometry (design units, y down, origin at the frame centre; see docs/face.md):
    jaw line points drop by ``jaw * sin(phi)**2`` (phi = 0 at the temples, pi/2 at the
    chin); the inner lips form a half-ellipse opening of height ``aperture`` whose upper
    midpoint sits at ``25 - raise - 0.2 * aperture``; the outer lips add a thickness
    profile ``t (1 - u^2)^0.7`` with a cupid's bow, ``t`` grown by protrusion (x1.35),
    thinned by spreading and (lower lip) by tuck; widths scale by
    ``1 + 0.18 spread - 0.12 protrusion``. Blink moves the upper-lid points onto the lower
    lid. The head pose is a similarity ``p -> exp(log_s) R(rot) p + t`` about the centre,
    and the design frame is scaled by ``image_size / 136``.
    """
    _check_image_size(image_size)
    art = np.asarray(articulators, dtype=np.float64)
    if art.ndim != 2 or art.shape[1] != N_ARTICULATORS:
        raise ValueError(f"articulators: expected shape (T, {N_ARTICULATORS}), found {art.shape}")
    T = art.shape[0]
    blink = np.zeros(T) if blink is None else np.asarray(blink, dtype=np.float64)
    brow = np.zeros(T) if brow is None else np.asarray(brow, dtype=np.float64)
    pose = np.zeros((T, 4)) if pose is None else np.asarray(pose, dtype=np.float64)
    if blink.shape != (T,) or brow.shape != (T,) or pose.shape != (T, 4):
        raise ValueError(
            f"blink/brow/pose: expected shapes ({T},), ({T},), ({T}, 4); found "
            f"{blink.shape}, {brow.shape}, {pose.shape}"
        )
    jaw, ap, spread, prot, rais, tuck = (art[:, j][:, None] for j in range(N_ARTICULATORS))
    ap = np.maximum(ap, 0.0)
    out = np.zeros((T, N_LANDMARKS, 2))
    G = LANDMARK_GROUPS

    # Face outline.
    phi = np.linspace(np.pi, 0.0, 9)  # left temple -> chin -> right temple
    jx = _FACE_A * np.cos(phi) * (1.0 - 0.25 * np.sin(phi) ** 2)
    jy = _FACE_CY + _FACE_B_BOT * np.sin(phi)
    out[:, G["jaw"], 0] = jx
    out[:, G["jaw"], 1] = jy + jaw * np.sin(phi) ** 2
    psi = np.deg2rad([340.0, 305.0, 270.0, 235.0, 200.0])  # right -> top -> left
    out[:, G["forehead"], 0] = _FACE_A * 0.95 * np.cos(psi)
    out[:, G["forehead"], 1] = _FACE_CY + _FACE_B_TOP * np.sin(psi)

    # Brows.
    out[:, G["brow_left"], 0] = _BROW[:, 0]
    out[:, G["brow_left"], 1] = _BROW[:, 1] - brow[:, None]
    out[:, G["brow_right"], 0] = -_BROW[::-1, 0]
    out[:, G["brow_right"], 1] = _BROW[::-1, 1] - brow[:, None]

    # Eyes: corner, upper, upper, corner, lower, lower (clockwise in image coordinates).
    open_ = 1.0 - np.clip(blink, 0.0, 1.0)[:, None]
    prof = np.sqrt(1.0 - _EYE_U**2)
    for name, cx in (("eye_left", -_EYE_CX), ("eye_right", _EYE_CX)):
        idx = G[name]
        lower_y = _EYE_CY + _EYE_LO * prof
        upper_y = lower_y - (_EYE_UP + _EYE_LO) * prof * open_
        out[:, idx[0]] = (cx - _EYE_HW, _EYE_CY)
        out[:, idx[1:3], 0] = cx + _EYE_U * _EYE_HW
        out[:, idx[1:3], 1] = upper_y
        out[:, idx[3]] = (cx + _EYE_HW, _EYE_CY)
        out[:, idx[4:6], 0] = cx - _EYE_U * _EYE_HW
        out[:, idx[4:6], 1] = lower_y[::-1]

    out[:, G["nose"]] = _NOSE

    # Lips.
    w_o = _LIP_HW * (1.0 + 0.18 * spread - 0.12 * prot)
    w_i = np.maximum(w_o - _LIP_INNER_INSET - 2.0 * np.maximum(-spread, 0.0), 3.0)
    y_ui = _LIP_Y0 - rais - 0.2 * ap
    y_li = y_ui + ap
    y_cn = y_ui + 0.45 * ap - 0.8 * np.maximum(spread, 0.0)
    thin = 1.0 - 0.15 * np.maximum(spread, 0.0)
    t_u = _UPPER_THICK * (1.0 + 0.35 * prot) * thin
    t_l = _LOWER_THICK * (1.0 + 0.35 * prot) * thin * (1.0 - 0.45 * tuck)

    def opening(x: np.ndarray, y_mid: np.ndarray) -> np.ndarray:
        u = np.clip(x / w_i, -1.0, 1.0)
        return y_cn + (y_mid - y_cn) * np.sqrt(1.0 - u**2)

    iu = G["inner_lip"]
    xi = _INNER_U[None, :] * w_i
    out[:, iu[0], 0], out[:, iu[0], 1] = -w_i[:, 0], y_cn[:, 0]
    out[:, iu[1:4], 0], out[:, iu[1:4], 1] = xi, opening(xi, y_ui)
    out[:, iu[4], 0], out[:, iu[4], 1] = w_i[:, 0], y_cn[:, 0]
    xl = xi[:, ::-1]
    out[:, iu[5:8], 0], out[:, iu[5:8], 1] = xl, opening(xl, y_li)

    ou = G["outer_lip"]
    xo = _OUTER_U[None, :] * w_o
    thick = (1.0 - _OUTER_U**2) ** 0.7
    bow = 1.0 + 0.12 * np.exp(-(((np.abs(_OUTER_U) - 0.25) / 0.12) ** 2)) - 0.1 * np.exp(-((_OUTER_U / 0.1) ** 2))
    out[:, ou[0], 0], out[:, ou[0], 1] = -w_o[:, 0], y_cn[:, 0] + 0.3
    out[:, ou[1:6], 0], out[:, ou[1:6], 1] = xo, opening(xo, y_ui) - t_u * thick * bow
    out[:, ou[6], 0], out[:, ou[6], 1] = w_o[:, 0], y_cn[:, 0] + 0.3
    xr = xo[:, ::-1]
    out[:, ou[7:12], 0], out[:, ou[7:12], 1] = xr, opening(xr, y_li) + t_l * thick[::-1]

    # Head pose (similarity about the frame centre), then design -> pixels.
    tx, ty, rot, log_s = (pose[:, j][:, None] for j in range(4))
    s = np.exp(log_s)
    c, sn = s * np.cos(rot), s * np.sin(rot)
    x, y = out[..., 0].copy(), out[..., 1].copy()
    out[..., 0] = c * x - sn * y + tx
    out[..., 1] = sn * x + c * y + ty
    k = image_size / DESIGN_SIZE
    return image_size / 2.0 + k * out


def face_landmarks(
    intervals: list[tuple[float, float, str]],
    n_frames: int,
    *,
    fps: float = 25.0,
    image_size: int = 128,
    rng: np.random.Generator,
) -> np.ndarray:
    """Per-frame face landmarks (n_frames, 57, 2) float64, pixels (x = column, y = row).

    Parameters
    ----------
    intervals : ``(start_s, end_s, phone)`` sorted, non-overlapping, covering the
        utterance; phones from :data:`bayes_talk.data.phones.PHONES`. Gaps get no target
        of their own (neighbouring segments coarticulate into them).
    n_frames : number of video frames; frame ``k`` describes ``[k/fps, (k+1)/fps)`` and
        is sampled at its centre (plus the visual lead).
    fps : frame rate (25 in the corpus).
    image_size : side of the square frame the landmarks live in (>= 32).
    rng : the only source of randomness (same seed -> identical output).

    See :func:`face_trajectories` for the control signals and
    :func:`shape_from_articulators` for the geometry.
    """
    _check_image_size(image_size)
    track = face_trajectories(intervals, n_frames, fps=fps, rng=rng)
    return shape_from_articulators(
        track.articulators, track.blink, track.pose, track.brow, image_size=image_size
    )


def rest_shape(image_size: int = 128) -> np.ndarray:
    """Landmarks (57, 2) of the rest face: sil targets, eyes open, frontal pose."""
    art = articulator_targets(SILENCE)[None, :]
    return shape_from_articulators(art, image_size=image_size)[0]


def reference_shape(image_size: int = 128) -> np.ndarray:
    """Landmarks (57, 2) the renderer's texture is painted in: mouth half open
    (jaw 4, aperture 6) so every lip and cavity triangle has a healthy area."""
    art = np.array([[4.0, 6.0, 0.0, 0.0, 0.0, 0.0]])
    return shape_from_articulators(art, image_size=image_size)[0]


def inner_lip_aperture(landmarks: np.ndarray) -> np.ndarray:
    """Mean distance (pixels) between the three facing upper/lower inner-lip points, (T,).

    0 when the lips touch (the paired points coincide).
    """
    lm = np.asarray(landmarks, dtype=np.float64)
    if lm.ndim != 3 or lm.shape[1:] != (N_LANDMARKS, 2):
        raise ValueError(f"landmarks: expected shape (T, {N_LANDMARKS}, 2), found {lm.shape}")
    iu = LANDMARK_GROUPS["inner_lip"]
    upper = lm[:, iu[1:4]]
    lower = lm[:, iu[5:8][::-1]]
    return np.linalg.norm(upper - lower, axis=-1).mean(axis=1)


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
