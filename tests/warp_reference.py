"""The vectorised NumPy piecewise-affine warp that bayes_talk.features.warp replaced, kept
as the reference its compiled version must reproduce bit for bit (tests/features/test_warp.py). Not
used by the package.

Per destination triangle, all pixel centres of its bounding box are tested with
barycentric coordinates in one NumPy pass over a batch of frames; covered pixels map to
the source by the same barycentric weights and are sampled bilinearly; the (frame, pixel)
pairs are written in (frame, triangle, row, column) order, so a pixel on a shared edge
keeps the later triangle's value. :func:`render_frames` is the renderer's loop of the
same session on top of it (bayes_talk.corpus.render.render_frames, before).
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter
from skimage.transform import downscale_local_mean

from bayes_talk.corpus import render as _render
from bayes_talk.data import face as _face

_BATCH = 32          # frames rasterised together (amortises NumPy call overhead)
_EDGE_TOL = 1e-7     # barycentric tolerance: pixel centres on edges belong to both


def rasterise_triangles(
    dst_points: np.ndarray, triangles: np.ndarray, output_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel centres covered by each triangle, for a batch of point sets.

    Parameters
    ----------
    dst_points : (B, P, 2) vertex positions, (x = column, y = row); pixel (r, c) has its
        centre at (x, y) = (c, r).
    triangles : (M, 3) vertex indices.
    output_shape : (H, W).

    Returns
    -------
    frame : (n,) batch index of each covered (pixel, triangle) pair.
    pixel : (n,) flat pixel index ``r * W + c``.
    tri : (n,) triangle index.
    bary : (n, 3) barycentric coordinates of the pixel centre in that triangle.
    """
    H, W = output_shape
    B = dst_points.shape[0]
    M = triangles.shape[0]
    v = dst_points[:, triangles].reshape(B * M, 3, 2)
    ax, ay = v[:, 0, 0], v[:, 0, 1]
    e1x, e1y = v[:, 1, 0] - ax, v[:, 1, 1] - ay
    e2x, e2y = v[:, 2, 0] - ax, v[:, 2, 1] - ay
    det = e1x * e2y - e1y * e2x
    ok = np.abs(det) > 1e-9
    x0 = np.clip(np.ceil(v[..., 0].min(axis=1) - 1e-6), 0, W - 1).astype(np.int64)
    x1 = np.clip(np.floor(v[..., 0].max(axis=1) + 1e-6), 0, W - 1).astype(np.int64)
    y0 = np.clip(np.ceil(v[..., 1].min(axis=1) - 1e-6), 0, H - 1).astype(np.int64)
    y1 = np.clip(np.floor(v[..., 1].max(axis=1) + 1e-6), 0, H - 1).astype(np.int64)
    nx = np.maximum(x1 - x0 + 1, 0)
    ny = np.maximum(y1 - y0 + 1, 0)
    # A triangle entirely outside the frame gets clipped to an edge row/column; its
    # pixels then fail the barycentric test, which is correct if wasteful.
    n = np.where(ok, nx * ny, 0)
    tid = np.repeat(np.arange(B * M), n)
    local = np.arange(tid.size) - np.repeat(np.cumsum(n) - n, n)
    nxt = nx[tid]
    px = x0[tid] + local % nxt
    py = y0[tid] + local // nxt
    dx = px - ax[tid]
    dy = py - ay[tid]
    inv = 1.0 / np.where(ok, det, 1.0)[tid]
    l1 = (dx * e2y[tid] - dy * e2x[tid]) * inv
    l2 = (e1x[tid] * dy - e1y[tid] * dx) * inv
    l0 = 1.0 - l1 - l2
    inside = (l0 >= -_EDGE_TOL) & (l1 >= -_EDGE_TOL) & (l2 >= -_EDGE_TOL)
    tid = tid[inside]
    bary = np.stack([l0[inside], l1[inside], l2[inside]], axis=1)
    pixel = py[inside] * W + px[inside]
    return tid // M, pixel, tid % M, bary


def bilinear_sample(images: np.ndarray, frame: np.ndarray | None, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of float64 images (Bi, Hs, Ws) at points (x = column, y = row).

    ``frame`` (same length as x) selects the image of each point (None: image 0).
    Coordinates are clamped to the image (edge pixels extend outwards), which matches
    ``scipy.ndimage.map_coordinates(order=1, mode="nearest")`` inside the image.
    """
    _, Hs, Ws = images.shape
    x = np.clip(x, 0.0, Ws - 1.0)
    y = np.clip(y, 0.0, Hs - 1.0)
    xi = np.minimum(np.floor(x).astype(np.int64), Ws - 2)
    yi = np.minimum(np.floor(y).astype(np.int64), Hs - 2)
    fx = x - xi
    fy = y - yi
    flat = images.reshape(-1)
    base = yi * Ws + xi
    if frame is not None:
        base = base + frame * (Hs * Ws)
    top = flat[base] * (1.0 - fx) + flat[base + 1] * fx
    bot = flat[base + Ws] * (1.0 - fx) + flat[base + Ws + 1] * fx
    return top * (1.0 - fy) + bot * fy


def warp_piecewise_affine(
    images: np.ndarray,
    src_points: np.ndarray,
    dst_points: np.ndarray,
    triangles: np.ndarray,
    output_shape: tuple[int, int],
    fill: float | np.ndarray = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Piecewise-affine warp of source image(s) so that src_points land on dst_points.

    Output pixel ``p`` inside destination triangle ``(i, j, k)`` with barycentric
    coordinates ``(l0, l1, l2)`` takes the bilinear source sample at
    ``l0 src_i + l1 src_j + l2 src_k`` (the affine map of that triangle). Pixels covered
    by no (non-degenerate) triangle get ``fill``.

    Parameters
    ----------
    images : (Hs, Ws) one source image for all frames, or (B, Hs, Ws) one per frame.
    src_points : (P, 2) shared, or (B, P, 2), source vertices (x, y).
    dst_points : (P, 2) or (B, P, 2) destination vertices (x, y).
    triangles : (M, 3) vertex indices (the same triangulation for source and target).
    output_shape : (H, W).
    fill : scalar, or (H, W) image, for uncovered pixels.

    Returns
    -------
    warped : (B, H, W) float64 (B = 1 when nothing is batched).
    covered : (B, H, W) bool.
    """
    images = np.asarray(images, dtype=np.float64)
    dst = np.asarray(dst_points, dtype=np.float64)
    src = np.asarray(src_points, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    if dst.ndim == 2:
        dst = dst[None]
    B = dst.shape[0]
    if images.ndim == 2:
        images = images[None]
    if images.shape[0] not in (1, B):
        raise ValueError(f"images: expected 1 or {B} source images, found {images.shape[0]}")
    if src.ndim == 2:
        src = src[None]
    if src.shape[0] not in (1, B) or src.shape[1:] != dst.shape[1:] or dst.shape[2] != 2:
        raise ValueError(
            f"src_points/dst_points: expected matching (P, 2) or (B, P, 2) arrays, found "
            f"{src.shape} and {dst.shape}"
        )
    if triangles.ndim != 2 or triangles.shape[1] != 3 or triangles.min() < 0 or triangles.max() >= dst.shape[1]:
        raise ValueError(f"triangles: expected (M, 3) indices into {dst.shape[1]} points")
    H, W = output_shape
    out = np.empty((B, H * W))
    out[:] = np.broadcast_to(np.asarray(fill, dtype=np.float64), (H, W)).reshape(-1)
    covered = np.zeros((B, H * W), dtype=bool)
    for b0 in range(0, B, _BATCH):
        b1 = min(B, b0 + _BATCH)
        frame, pixel, tri, bary = rasterise_triangles(dst[b0:b1], triangles, (H, W))
        if src.shape[0] == 1:
            sv = src[0][triangles[tri]]                      # (n, 3, 2)
        else:
            sv = src[b0 + frame[:, None], triangles[tri]]    # (n, 3, 2)
        sx = np.einsum("nk,nk->n", bary, sv[..., 0])
        sy = np.einsum("nk,nk->n", bary, sv[..., 1])
        img_frame = None if images.shape[0] == 1 else frame + b0
        vals = bilinear_sample(images, img_frame, sx, sy)
        out[b0 + frame, pixel] = vals
        covered[b0 + frame, pixel] = True
    return out.reshape(B, H, W), covered.reshape(B, H, W)


def warp_triangles(images, src_points, dst_points, triangles, output_shape, fill=0.0):
    """:func:`warp_piecewise_affine` and the triangle each pixel was written by (-1: none),
    the last writer in pair order (as NumPy's fancy assignment leaves it)."""
    warped, _ = warp_piecewise_affine(images, src_points, dst_points, triangles, output_shape, fill)
    dst = np.asarray(dst_points, dtype=np.float64)
    dst = dst[None] if dst.ndim == 2 else dst
    H, W = output_shape
    tri_out = np.full((dst.shape[0], H * W), -1, dtype=np.int32)
    for b0 in range(0, dst.shape[0], _BATCH):
        frame, pixel, tri, _ = rasterise_triangles(dst[b0:b0 + _BATCH], np.asarray(triangles, dtype=np.int64), (H, W))
        tri_out[b0 + frame, pixel] = tri
    return warped, tri_out.reshape(-1, H, W)


def render_frames(landmarks, image_size=128, supersample=_render.RENDER_SUPERSAMPLE,
                  psf_px=_render.CAMERA_PSF_PX):
    """bayes_talk.corpus.render.render_frames as it was on this rasteriser (no checks)."""
    lm = np.asarray(landmarks, dtype=np.float64)
    n = int(image_size)
    s = int(supersample)
    N = n * s
    tex = _render._texture_cached(n, s)[None]
    ref = _render._to_fine(_face.reference_shape(n), s)
    tri = _render._triangles_cached(n)
    cav = _render.cavity_triangles(n)
    bg = _render._background_cached(n, s).reshape(-1)
    k = n / _face.DESIGN_SIZE
    lm_fine = _render._to_fine(lm, s)
    T = lm.shape[0]
    batch = max(1, 32 // (s * s))
    out = np.empty((T, n, n), dtype=np.uint8)
    for b0 in range(0, T, batch):
        b1 = min(T, b0 + batch)
        frame, pixel, t_id, bary = rasterise_triangles(lm_fine[b0:b1], tri, (N, N))
        sv = ref[tri[t_id]]
        vals = bilinear_sample(tex, None, np.einsum("nk,nk->n", bary, sv[..., 0]),
                               np.einsum("nk,nk->n", bary, sv[..., 1]))
        in_cav = cav[t_id]
        if in_cav.any():
            pc = pixel[in_cav]
            px = ((pc % N).astype(np.float64) + 0.5) / s - 0.5
            py = ((pc // N).astype(np.float64) + 0.5) / s - 0.5
            vals[in_cav] = _render._cavity_colour(lm[b0:b1], frame[in_cav], px, py, k)
        img = np.empty((b1 - b0, N * N))
        img[:] = bg
        img[frame, pixel] = vals
        img = img.reshape(b1 - b0, N, N)
        if psf_px > 0:
            img = gaussian_filter(img, (0.0, psf_px * s, psf_px * s), mode="nearest")
        if s > 1:
            img = downscale_local_mean(img, (1, s, s))
        out[b0:b1] = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return out
