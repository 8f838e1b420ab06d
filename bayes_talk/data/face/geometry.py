"""Face geometry: the 57-landmark layout and the map from articulators, blinks, brow and
head pose to landmarks in pixels (the second half of
:func:`bayes_talk.data.face.face_landmarks`; design in the :mod:`bayes_talk.data.face`
docstring and docs/face.md)."""
from __future__ import annotations

import numpy as np

from bayes_talk.data.face.coarticulation import N_ARTICULATORS, articulator_targets
from bayes_talk.data.phones import SILENCE

__all__ = [
    "DESIGN_SIZE",
    "LANDMARK_GROUPS",
    "LIP_LANDMARKS",
    "LOWER_TEETH_BELOW_CHIN",
    "MOUTH_OPENING_PAIR",
    "N_LANDMARKS",
    "UPPER_FACE_LANDMARKS",
    "UPPER_TEETH_Y",
    "check_image_size",
    "inner_lip_aperture",
    "reference_shape",
    "rest_shape",
    "shape_from_articulators",
]

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

#: The regions of the field's landmark metrics (bayes_talk.evaluation.metrics, docs/evaluation.md).
#: Lips: the 12 outer- and 8 inner-lip points (indices 37-56), the region of the lip error.
LIP_LANDMARKS = np.concatenate([LANDMARK_GROUPS["outer_lip"], LANDMARK_GROUPS["inner_lip"]])
#: Mouth opening: the inner-lip midline pair (upper midpoint 51, lower midpoint 55), which share x
#: and coincide when the lips touch; their distance is the inner-lip aperture at the midline.
MOUTH_OPENING_PAIR = (int(LANDMARK_GROUPS["inner_lip"][2]), int(LANDMARK_GROUPS["inner_lip"][6]))
#: Upper face: forehead, brows, eyes and nose (indices 9-36): every point that neither the lips nor
#: the jaw move (the jaw line drops with the jaw, so it belongs to the mouth region).
UPPER_FACE_LANDMARKS = np.concatenate([LANDMARK_GROUPS[g] for g in
                                       ("forehead", "brow_left", "brow_right", "eye_left", "eye_right", "nose")])

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


def check_image_size(image_size: int) -> None:
    """ValueError unless ``image_size`` is an int >= 32."""
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
    check_image_size(image_size)
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
