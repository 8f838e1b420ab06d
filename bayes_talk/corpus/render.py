"""Grayscale rendering of the synthetic landmark face (docs/data.md).

A frame is a piecewise-affine warp of one procedurally painted face texture from the
:func:`~bayes_talk.data.face.reference_shape` (mouth half open) to the frame's landmarks,
over a fixed Delaunay triangulation of the reference shape. Inside the inner-lip polygon
the texture is replaced by a mouth cavity painted per frame in head coordinates: upper
teeth whose edge is fixed to the skull, lower teeth fixed to the jaw, dark cavity
between. So appearance, not only shape, changes with speech: teeth show when the upper lip
rises (/f v/) or the lips part (/iy aa/), the cavity darkens as the jaw opens, the eyes
close in blinks (their triangles collapse and the eyelid skin stretches over them).

Warping is :func:`bayes_talk.features.warp.warp_triangles` (the piecewise-affine warp,
which also says which triangle each pixel came from: the cavity's pixels are repainted);
the camera (PSF blur, pixel area mean, rounding) is one compiled pass (:func:`render_frames`).
"""
from __future__ import annotations

import itertools
from functools import lru_cache

import numba
import numpy as np
from matplotlib.path import Path as MplPath
from scipy.ndimage import gaussian_filter
from scipy.spatial import Delaunay
from skimage.transform import downscale_local_mean

from bayes_talk.data import face as _face
from bayes_talk.features.warp import warp_triangles

__all__ = [
    "CAMERA_PSF_PX",
    "RENDER_SUPERSAMPLE",
    "background",
    "cavity_triangles",
    "face_texture",
    "face_triangles",
    "render_frames",
]

_SUPERSAMPLE = 4     # texture is painted at 4x and box-filtered (anti-aliasing)
_TEXTURE_BLUR_PX = 0.7
#: sub-pixel samples per pixel side of :func:`render_frames` (camera area integration);
#: 1 = point sampling at pixel centres (the corpus renderer of format version 1)
RENDER_SUPERSAMPLE = 2
#: camera optics: Gaussian point-spread function, sd in pixels, applied to the scene
#: before pixel integration (0 = ideal lens)
CAMERA_PSF_PX = 0.7
#: frames rasterised together, at 1x; divided by supersample**2 (memory per batch)
_RENDER_BATCH = 32


# ------------------------------------------------------------------------------------
# The face texture
# ------------------------------------------------------------------------------------
def _smoothstep(edge: float, x: np.ndarray, width: float) -> np.ndarray:
    return np.clip(0.5 + (edge - x) / width, 0.0, 1.0)


def _poly_mask(poly: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    pts = np.stack([px.ravel(), py.ravel()], axis=1)
    return MplPath(poly).contains_points(pts).reshape(px.shape).astype(np.float64)


def _polyline_distance(line: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    d = np.full(px.shape, np.inf)
    for a, b in itertools.pairwise(line):
        ab = b - a
        t = np.clip(((px - a[0]) * ab[0] + (py - a[1]) * ab[1]) / (ab @ ab), 0.0, 1.0)
        d = np.minimum(d, np.hypot(px - a[0] - t * ab[0], py - a[1] - t * ab[1]))
    return d


@lru_cache(maxsize=8)
def _texture_cached(image_size: int, fine: int = 1) -> np.ndarray:
    """Paint the face in design units over the reference shape (see module docstring).

    ``fine``: pixels per image pixel side of the returned texture, (image_size * fine)^2;
    pixel ``j`` of it has its centre at image coordinate ``(j + 0.5) / fine - 0.5``. It
    is painted at ``fine * m`` samples per pixel (``m = round(4 / fine)``, at least 1),
    box-filtered to ``fine`` and blurred by 0.7 image pixels (``0.7 fine`` texture
    pixels): the same continuous scene at every ``fine`` (``fine = 1`` is the version-1
    texture, bit for bit).
    """
    ss = int(fine) * max(1, round(_SUPERSAMPLE / int(fine)))
    k = image_size / _face.DESIGN_SIZE
    sub = (np.arange(image_size * ss) + 0.5) / ss - 0.5          # pixel coordinates
    gx, gy = np.meshgrid(sub, sub)
    x = (gx - image_size / 2.0) / k                                # design units
    y = (gy - image_size / 2.0) / k
    ref = (_face.reference_shape(image_size) - image_size / 2.0) / k
    G = _face.LANDMARK_GROUPS

    # Skin: darker towards the face outline, lit forehead and cheeks.
    cy = -2.0
    rho2 = (x / 44.0) ** 2 + ((y - cy) / np.where(y < cy, 50.0, 50.0)) ** 2
    img = 182.0 - 50.0 * rho2**2
    img += 8.0 * np.exp(-(x**2 + (y + 32.0) ** 2) / (2 * 14.0**2))
    for sx in (-22.0, 22.0):
        img += 6.0 * np.exp(-((x - sx) ** 2 + (y - 8.0) ** 2) / (2 * 8.0**2))
    # Nose: ridge highlight, side shadows, tip, nostrils, philtrum.
    ridge = np.exp(-(x**2) / (2 * 1.5**2)) * _smoothstep(8.0, y, 4.0) * _smoothstep(12.0, -y, 4.0)
    img += 12.0 * ridge
    sides = np.exp(-((np.abs(x) - 5.0) ** 2) / (2 * 1.6**2)) * np.exp(-((y - 5.0) ** 2) / (2 * 5.0**2))
    img -= 18.0 * sides
    img += 10.0 * np.exp(-(x**2 + (y - 7.0) ** 2) / (2 * 2.5**2))
    for nx_ in (-3.3, 3.3):
        r = np.sqrt(((x - nx_) / 2.0) ** 2 + ((y - 11.8) / 1.1) ** 2)
        img = img * (1 - _smoothstep(1.0, r, 0.3)) + 60.0 * _smoothstep(1.0, r, 0.3)
    img -= 7.0 * np.exp(-((np.abs(x) - 2.0) ** 2) / (2 * 0.8**2)) * np.exp(-((y - 17.0) ** 2) / (2 * 2.5**2))
    # Eye sockets, eyes, lash lines, creases.
    for name, ex in (("eye_left", -19.0), ("eye_right", 19.0)):
        pts = ref[G[name]]
        img -= 16.0 * np.exp(-((x - ex) ** 2 / (2 * 7.0**2) + (y + 12.5) ** 2 / (2 * 4.0**2)))
        inside = _poly_mask(pts, x, y)
        r = np.hypot(x - ex, y + 11.0)
        eye = 218.0 - 20.0 * (np.abs(x - ex) / 8.5) ** 2
        eye = eye * _smoothstep(3.6, r, 0.5) + 80.0 * (1 - _smoothstep(3.6, r, 0.5))
        eye = eye * _smoothstep(1.6, r, 0.4) + 25.0 * (1 - _smoothstep(1.6, r, 0.4))
        hl = np.hypot(x - ex - 1.0, y + 12.0)
        eye = eye * _smoothstep(0.7, hl, 0.3) + 235.0 * (1 - _smoothstep(0.7, hl, 0.3))
        img = img * (1 - inside) + eye * inside
        upper = pts[[0, 1, 2, 3]]
        lash = _smoothstep(0.7, _polyline_distance(upper, x, y), 0.5)
        img = img * (1 - lash) + 45.0 * lash
        crease = _smoothstep(0.5, _polyline_distance(upper + [0.0, -3.2], x, y), 0.6)
        img -= 22.0 * crease
    # Brows: tapered dark strokes.
    for name in ("brow_left", "brow_right"):
        pts = ref[G[name]]
        brow = _smoothstep(1.7, _polyline_distance(pts, x, y), 0.7)
        img = img * (1 - brow) + 68.0 * brow
    # Lips: darker than skin, upper lip darker, lower-lip highlight, chin crease.
    outer = ref[G["outer_lip"]]
    inner = ref[G["inner_lip"]]
    lips = _poly_mask(outer, x, y)
    lip_tone = np.where(y < inner[:, 1].mean(), 108.0, 124.0)
    lip_tone = lip_tone + 16.0 * np.exp(-(x**2 / (2 * 5.0**2) + (y - (inner[6, 1] + 3.0)) ** 2 / (2 * 1.5**2)))
    img = img * (1 - lips) + lip_tone * lips
    img -= 14.0 * np.exp(-(x**2 / (2 * 9.0**2) + (y - (outer[9, 1] + 4.0)) ** 2 / (2 * 1.8**2)))
    cavity = _poly_mask(inner, x, y)
    img = img * (1 - cavity) + 40.0 * cavity
    img = downscale_local_mean(img, (ss // fine, ss // fine))
    # A slight blur (sd 0.7 px) softens the painted edges (the scene, not the camera).
    img = gaussian_filter(img, _TEXTURE_BLUR_PX * fine)
    return np.clip(img, 0.0, 255.0)


def face_texture(image_size: int = 128) -> np.ndarray:
    """The face texture (image_size, image_size) float64 in [0, 255], painted on
    :func:`~bayes_talk.data.face.reference_shape`. Deterministic, cached; a copy."""
    _face.check_image_size(image_size)
    return _texture_cached(int(image_size)).copy()


@lru_cache(maxsize=4)
def _triangles_cached(image_size: int) -> np.ndarray:
    tri = Delaunay(_face.reference_shape(image_size)).simplices.astype(np.int64)
    return tri[np.lexsort(tri.T[::-1])]


def face_triangles(image_size: int = 128) -> np.ndarray:
    """(M, 3) Delaunay triangulation of the reference shape (sorted rows, a copy)."""
    return _triangles_cached(int(image_size)).copy()


def cavity_triangles(image_size: int = 128) -> np.ndarray:
    """Boolean (M,) mask of the triangles inside the inner-lip polygon (the mouth)."""
    tri = _triangles_cached(int(image_size))
    inner = _face.LANDMARK_GROUPS["inner_lip"]
    ref = _face.reference_shape(image_size)
    all_inner = np.isin(tri, inner).all(axis=1)
    centroids = ref[tri].mean(axis=1)
    inside = MplPath(ref[inner]).contains_points(centroids)
    return all_inner & inside


@lru_cache(maxsize=8)
def _background_cached(image_size: int, fine: int = 1) -> np.ndarray:
    """The backdrop at ``fine`` samples per pixel side (sub-pixel centres, see
    :func:`_to_fine`); linear in (row, column), so its pixel means are the
    ``fine = 1`` values."""
    idx = np.arange(image_size * fine, dtype=np.float64)
    if fine > 1:
        idx = (idx + 0.5) / fine - 0.5
    r = idx[:, None] / image_size
    c = idx[None, :] / image_size
    return 70.0 + 40.0 * r + 10.0 * c


def _to_fine(points: np.ndarray, fine: int) -> np.ndarray:
    """Image pixel coordinates -> coordinates on the ``fine`` x grid, whose pixel ``j``
    has its centre at image coordinate ``(j + 1/2) / fine - 1/2``."""
    return points if fine == 1 else (points + 0.5) * fine - 0.5


def background(image_size: int = 128) -> np.ndarray:
    """The static backdrop (image_size, image_size) float64: a soft vertical gradient."""
    return _background_cached(int(image_size)).copy()


def _cavity_colour(lm: np.ndarray, frame: np.ndarray, px: np.ndarray, py: np.ndarray, k: float) -> np.ndarray:
    """Teeth / dark cavity grey levels at pixel centres (px, py) of frames ``frame``.

    Head axes come from the (blink-invariant) eye corners; the upper-teeth edge is fixed
    to the subnasale (skull), the lower-teeth top to the chin (jaw). 1-pixel soft edges.
    """
    G = _face.LANDMARK_GROUPS
    el = lm[:, G["eye_left"][[0, 3]]].mean(axis=1)
    er = lm[:, G["eye_right"][[0, 3]]].mean(axis=1)
    d = er - el
    dist = np.linalg.norm(d, axis=1)
    u = d / dist[:, None]
    v = np.stack([-u[:, 1], u[:, 0]], axis=1)
    unit = dist / (2 * 19.0)                                    # pixels per design unit
    nose = lm[:, G["nose"][4]]
    chin = lm[:, G["jaw"][4]]
    mid = lm[:, G["inner_lip"][[0, 4]]].mean(axis=1)
    e_up = nose + ((_face.UPPER_TEETH_Y - 13.5) * unit)[:, None] * v
    e_lo = chin - (_face.LOWER_TEETH_BELOW_CHIN * unit)[:, None] * v
    f = frame
    vx, vy, ux, uy = v[f, 0], v[f, 1], u[f, 0], u[f, 1]
    h_up = (px - e_up[f, 0]) * vx + (py - e_up[f, 1]) * vy         # pixels, + below edge
    h_lo = (px - e_lo[f, 0]) * vx + (py - e_lo[f, 1]) * vy
    q = ((px - mid[f, 0]) * ux + (py - mid[f, 1]) * uy) / unit[f]  # design units, lateral
    a_up = np.clip(0.5 - h_up, 0.0, 1.0)
    a_lo = np.clip(0.5 + h_lo, 0.0, 1.0)
    side = np.clip((q / 10.0) ** 2, 0.0, 1.0)
    teeth_up = 228.0 - 70.0 * side
    teeth_lo = 196.0 - 70.0 * side
    dark = 32.0 + 10.0 * (1.0 - side)
    return a_up * teeth_up + (1.0 - a_up) * (a_lo * teeth_lo + (1.0 - a_lo) * dark)


# ------------------------------------------------------------------------------------
# The camera
# ------------------------------------------------------------------------------------
def _gaussian_weights(sd: float, truncate: float = 4.0) -> np.ndarray:
    """The 1-D kernel of ``scipy.ndimage.gaussian_filter`` (same formula, same floats):
    exp(-x^2 / (2 sd^2)) / sum, x = -r..r, r = int(truncate sd + 1/2)."""
    radius = int(truncate * float(sd) + 0.5)
    x = np.arange(-radius, radius + 1)
    phi = np.exp(-0.5 / (float(sd) * float(sd)) * x**2)
    return phi / phi.sum()


@numba.njit(cache=True)
def _camera_kernel(img: np.ndarray, w: np.ndarray, s: int, out: np.ndarray) -> None:
    """out[b] = uint8(clip(rint(area mean over s x s blocks of (rows then columns)
    separable correlation of img[b] with the symmetric kernel w, edges extended))).

    The floating-point operations, in order, of ``gaussian_filter(img, (0, sd, sd),
    mode="nearest")`` (scipy's symmetric-kernel loop: x_0 w_0 + sum_{j=r..1}
    (x_{-j} + x_j) w_j, rows pass first) followed by ``downscale_local_mean(., (1, s, s))``
    (each block row summed left to right, block rows summed top to bottom, / s^2).
    """
    B, N, _ = img.shape
    r = (w.shape[0] - 1) // 2
    n = N // s
    buf = np.empty((N, N))
    line = np.empty(N + 2 * r)
    for b in range(B):
        for i in range(N):                      # along axis 1 (down the columns)
            for c in range(N):
                buf[i, c] = img[b, i, c] * w[r]
            for jj in range(-r, 0):
                lo = min(max(i + jj, 0), N - 1)
                hi = min(max(i - jj, 0), N - 1)
                wj = w[r + jj]
                for c in range(N):
                    buf[i, c] += (img[b, lo, c] + img[b, hi, c]) * wj
        for i in range(N):                      # along axis 2 (along the rows)
            for c in range(N):
                line[r + c] = buf[i, c]
            for c in range(r):
                line[c] = buf[i, 0]
                line[r + N + c] = buf[i, N - 1]
            for c in range(N):
                buf[i, c] = line[r + c] * w[r]
            for jj in range(-r, 0):
                wj = w[r + jj]
                for c in range(N):
                    buf[i, c] += (line[r + c + jj] + line[r + c - jj]) * wj
        for i in range(n):
            for j in range(n):
                total = 0.0
                for a in range(s):
                    row = buf[i * s + a, j * s]
                    for c in range(1, s):
                        row += buf[i * s + a, j * s + c]
                    total = row if a == 0 else total + row
                v = np.rint(total / (s * s))
                out[b, i, j] = np.uint8(min(max(v, 0.0), 255.0))


def _camera(scene: np.ndarray, psf_sd: float, s: int) -> np.ndarray:
    """Frames (B, N/s, N/s) uint8 of the scene (B, N, N) float64: blurred by the PSF (sd
    in scene pixels), integrated over s x s pixels, rounded (see :func:`render_frames`)."""
    w = _gaussian_weights(psf_sd) if psf_sd > 1e-15 else np.ones(1)   # as scipy: no blur
    out = np.empty((scene.shape[0], scene.shape[1] // s, scene.shape[2] // s), dtype=np.uint8)
    _camera_kernel(np.ascontiguousarray(scene), w, s, out)
    return out


def render_frames(landmarks: np.ndarray, image_size: int = 128,
                  supersample: int = RENDER_SUPERSAMPLE, psf_px: float = CAMERA_PSF_PX) -> np.ndarray:
    """Grayscale frames (T, image_size, image_size) uint8 of the face at the landmarks.

    Deterministic (no randomness; the texture and triangulation are fixed functions of
    ``image_size``). Landmarks are (T, 57, 2) pixel coordinates (x = column, y = row),
    as from :func:`~bayes_talk.data.face.face_landmarks` with the same ``image_size``.

    Camera model (``supersample`` = s, default :data:`RENDER_SUPERSAMPLE`; ``psf_px`` =
    sigma, default :data:`CAMERA_PSF_PX`): the lens blurs the scene with a Gaussian
    point-spread function of sd sigma pixels and each pixel integrates the blurred scene
    over its square, approximated by the mean of s x s samples at its sub-pixel centres,

        I[r, c] = (1 / s^2) sum_{i,j<s} (G_sigma * L)(c - 1/2 + (j + 1/2)/s, r - 1/2 + (i + 1/2)/s),

    where L is the continuous scene (the texture warped piecewise-affinely onto the
    landmarks, the mouth cavity, the backdrop). The frame is rendered at s x resolution
    (landmarks mapped by ``p -> (p + 1/2) s - 1/2``, the texture painted at s x), blurred
    as by ``scipy.ndimage.gaussian_filter(mode="nearest")`` (sd ``sigma s`` fine pixels)
    and area-averaged as by :func:`skimage.transform.downscale_local_mean`, both in one
    compiled pass with their floating-point operations in their order (bit for bit the
    same frames, tests/features/test_warp.py; 2-3x less CPU). Point sampling with an ideal lens
    (s = 1, sigma = 0: the format-1 corpus, reproduced bit for bit) resamples sharp
    texture edges at positions that shift with sub-pixel head motion; that aliasing
    showed up as AAM modes (benchmarks/render_aliasing.py, docs/face.md). Cost grows as s^2.
    """
    _face.check_image_size(image_size)
    if not isinstance(supersample, (int, np.integer)) or isinstance(supersample, bool) or supersample < 1:
        raise ValueError(f"supersample: expected an int >= 1, found {supersample!r}")
    if not (np.isfinite(psf_px) and psf_px >= 0):
        raise ValueError(f"psf_px: expected a finite number >= 0, found {psf_px!r}")
    lm = np.asarray(landmarks, dtype=np.float64)
    if lm.ndim != 3 or lm.shape[1:] != (_face.N_LANDMARKS, 2):
        raise ValueError(f"landmarks: expected shape (T, {_face.N_LANDMARKS}, 2), found {lm.shape}")
    if not np.all(np.isfinite(lm)):
        raise ValueError("landmarks: expected finite coordinates, found NaN or inf")
    n = int(image_size)
    s = int(supersample)
    N = n * s
    tex = _texture_cached(n, s)
    ref = _to_fine(_face.reference_shape(n), s)                # in fine texture pixels
    tri = _triangles_cached(n)
    cav = cavity_triangles(n)
    bg = _background_cached(n, s)
    k = n / _face.DESIGN_SIZE
    lm_fine = _to_fine(lm, s)
    T = lm.shape[0]
    batch = max(1, _RENDER_BATCH // (s * s))
    in_cavity = np.append(cav, False)                           # triangle -1: not covered
    inner = _face.LANDMARK_GROUPS["inner_lip"]
    out = np.empty((T, n, n), dtype=np.uint8)
    for b0 in range(0, T, batch):
        b1 = min(T, b0 + batch)
        img, t_id = warp_triangles(tex, ref, lm_fine[b0:b1], tri, (N, N), fill=bg)
        # the cavity's pixels lie in the bounding box of the inner lip (search only there)
        lip = lm_fine[b0:b1, inner]
        c0, r0 = np.clip(np.floor(lip.min(axis=(0, 1))).astype(np.int64) - 1, 0, N)
        c1, r1 = np.clip(np.ceil(lip.max(axis=(0, 1))).astype(np.int64) + 2, 0, N)
        frame, row, col = np.nonzero(in_cavity[t_id[:, r0:r1, c0:c1]])
        row += r0
        col += c0
        if frame.size:
            # sub-pixel centres in image pixel coordinates
            px = (col + 0.5) / s - 0.5
            py = (row + 0.5) / s - 0.5
            img[frame, row, col] = _cavity_colour(lm[b0:b1], frame, px, py, k)
        out[b0:b1] = _camera(img, psf_px * s, s)
    return out
