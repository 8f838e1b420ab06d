"""Piecewise-affine warping of images between two landmark sets (a shared triangulation).

Used by the AAM (shape-free texture sampling, :mod:`bayes_talk.features.aam`), the AAM
fitter (:mod:`bayes_talk.features.aam_fit`) and the synthetic-face renderer
(:mod:`bayes_talk.data.render`).

Speed. Warping is done by :func:`warp_piecewise_affine`, a vectorised rasteriser: for
every destination triangle, all pixel centres of its bounding box are tested with
barycentric coordinates in one NumPy pass over a batch of frames (no Python loop over
triangles); covered pixels map to the source by the same barycentric weights and are
sampled bilinearly. Degenerate (zero-area) triangles, e.g. closed lips, are skipped;
pixels on shared edges take one of the (equal) candidate values deterministically.
It agrees with ``skimage.transform.warp`` + ``PiecewiseAffineTransform`` on interior
pixels (tests/test_face.py) at a fraction of its cost (benchmarks/render.py).
"""
from __future__ import annotations

import numpy as np

__all__ = ["bilinear_sample", "rasterise_triangles", "warp_piecewise_affine"]

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
