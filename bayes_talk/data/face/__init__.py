"""Synthetic 2-D landmark face driven by coarticulated articulatory parameters.

This is the face side of the built-in talking-head corpus (docs/data.md; parameter choices
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

The package: :mod:`~bayes_talk.data.face.coarticulation` (phones to articulator tracks)
and :mod:`~bayes_talk.data.face.geometry` (articulators to landmarks); rendering the
landmarks as grey-level frames is :mod:`bayes_talk.corpus.render`. Their public names are
re-exported here.
"""
from __future__ import annotations

import numpy as np

from bayes_talk.data.face.coarticulation import (
    ARTICULATORS,
    N_ARTICULATORS,
    FaceTrack,
    articulator_targets,
    dominance_parameters,
    face_trajectories,
    random_phone_intervals,
)
from bayes_talk.data.face.geometry import (
    DESIGN_SIZE,
    LANDMARK_GROUPS,
    LIP_LANDMARKS,
    LOWER_TEETH_BELOW_CHIN,
    MOUTH_OPENING_PAIR,
    N_LANDMARKS,
    UPPER_FACE_LANDMARKS,
    UPPER_TEETH_Y,
    check_image_size,
    inner_lip_aperture,
    reference_shape,
    rest_shape,
    shape_from_articulators,
)

__all__ = [
    "ARTICULATORS",
    "DESIGN_SIZE",
    "LANDMARK_GROUPS",
    "LIP_LANDMARKS",
    "LOWER_TEETH_BELOW_CHIN",
    "MOUTH_OPENING_PAIR",
    "N_ARTICULATORS",
    "N_LANDMARKS",
    "UPPER_FACE_LANDMARKS",
    "UPPER_TEETH_Y",
    "FaceTrack",
    "articulator_targets",
    "check_image_size",
    "dominance_parameters",
    "face_landmarks",
    "face_trajectories",
    "inner_lip_aperture",
    "random_phone_intervals",
    "reference_shape",
    "rest_shape",
    "shape_from_articulators",
]


def face_landmarks(
    intervals: list[tuple[float, float, str]],
    n_frames: int,
    *,
    fps: float = 25.0,
    image_size: int = 128,
    rng: np.random.Generator,
    given: dict[str, np.ndarray] | None = None,
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
    given : articulator tracks that replace the phone-driven ones (see
        :func:`face_trajectories`).

    See :func:`face_trajectories` for the control signals and
    :func:`shape_from_articulators` for the geometry.
    """
    check_image_size(image_size)
    track = face_trajectories(intervals, n_frames, fps=fps, rng=rng, given=given)
    return shape_from_articulators(
        track.articulators, track.blink, track.pose, track.brow, image_size=image_size
    )
