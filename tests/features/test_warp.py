"""The compiled piecewise-affine warp against the NumPy rasteriser it replaced
(tests/warp_reference.py): bit for bit the same values, coverage and tie rule on shared
edges, on random and real landmark sets, degenerate triangles and triangles partly
outside the frame; and the renderer on top of it, frame for frame."""
from __future__ import annotations

import numpy as np
import pytest
import warp_reference as reference
from scipy.ndimage import gaussian_filter
from scipy.spatial import Delaunay
from skimage.transform import downscale_local_mean

from bayes_talk.corpus import render
from bayes_talk.data import face
from bayes_talk.features.warp import bilinear_sample, warp_piecewise_affine, warp_triangles


def _landmarks(n_seq: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.concatenate([face.face_landmarks(face.random_phone_intervals(rng, 60), 60, rng=rng)
                           for _ in range(n_seq)])


def _assert_same(images, src, dst, tri, shape, fill=0.0) -> np.ndarray:
    ours, t_ours = warp_triangles(images, src, dst, tri, shape, fill)
    ref, t_ref = reference.warp_triangles(images, src, dst, tri, shape, fill)
    np.testing.assert_array_equal(t_ours, t_ref)
    np.testing.assert_array_equal(ours, ref)
    warped, covered = warp_piecewise_affine(images, src, dst, tri, shape, fill)
    np.testing.assert_array_equal(warped, ours)
    np.testing.assert_array_equal(covered, t_ref >= 0)
    return t_ours


def _n_shared_edge_pixels(dst, tri, shape) -> int:
    """(frame, pixel) pairs the reference rasteriser writes more than once."""
    frame, pixel, _, _ = reference.rasterise_triangles(np.asarray(dst)[None] if np.ndim(dst) == 2 else dst,
                                                       np.asarray(tri), shape)
    key = frame * (shape[0] * shape[1]) + pixel
    return key.size - np.unique(key).size


def test_real_faces_at_1x_and_supersampled():
    lm = _landmarks(2, 0)
    tex, ref, tri = render.face_texture(128), face.reference_shape(128), render.face_triangles(128)
    degenerate = []
    for s in (1, 2):
        dst = (lm + 0.5) * s - 0.5
        v = dst[:, tri]
        e1, e2 = v[:, :, 1] - v[:, :, 0], v[:, :, 2] - v[:, :, 0]
        degenerate.append(np.abs(e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]) <= 1e-9)
        fine_tex = render.face_texture(128) if s == 1 else np.kron(tex, np.ones((2, 2)))
        t_id = _assert_same(fine_tex, (ref + 0.5) * s - 0.5, dst, tri, (128 * s, 128 * s),
                            fill=np.arange(128 * s * 128 * s, dtype=np.float64).reshape(128 * s, -1))
        assert (t_id >= 0).mean() > 0.3
    # the data exercise skipped (collapsed: closed lips, blinks) triangles
    assert np.any(degenerate[0])


def test_shared_edges_degenerate_and_outside_triangles():
    """Integer vertices put pixel centres exactly on shared edges (the tie rule decides),
    a collapsed vertex makes zero-area triangles, shifts push triangles off the frame."""
    rng = np.random.default_rng(1)
    g = np.stack(np.meshgrid(np.arange(0.0, 44.0, 4.0), np.arange(0.0, 44.0, 4.0)), -1).reshape(-1, 2)
    tri = Delaunay(g).simplices
    dst = np.repeat(g[None], 4, axis=0)
    dst[1, 13] = dst[1, 14]                     # zero-area triangles
    dst[2] += [-20.0, 15.0]                     # partly outside the frame
    dst[3] = dst[3] * 1.5 - 7.3                 # partly outside, non-integer
    assert _n_shared_edge_pixels(dst[:2], tri, (40, 40)) > 100
    images = rng.uniform(0.0, 255.0, (4, 50, 50))
    _assert_same(images, g * 1.1, dst, tri, (40, 40), fill=-1.0)
    _assert_same(images[0], dst * 0.9 + 2.0, dst, tri, (40, 40))


def test_random_point_sets():
    rng = np.random.default_rng(2)
    for _ in range(3):
        P = int(rng.integers(5, 40))
        tri = Delaunay(rng.uniform(0.0, 1.0, (P, 2))).simplices
        src = rng.uniform(-5.0, 70.0, (6, P, 2))
        dst = rng.uniform(-20.0, 100.0, (6, P, 2))   # overlapping, flipped, outside
        images = rng.uniform(0.0, 255.0, (6, 64, 72))
        _assert_same(images, src, dst, tri, (70, 90), fill=rng.uniform(0.0, 1.0, (70, 90)))
        _assert_same(images[:1], src[0], dst, tri, (33, 31))


def test_bilinear_sample_matches_reference():
    rng = np.random.default_rng(3)
    images = rng.uniform(0.0, 255.0, (5, 20, 30))
    x, y = rng.uniform(-3.0, 33.0, 5000), rng.uniform(-3.0, 23.0, 5000)
    frame = rng.integers(0, 5, 5000)
    np.testing.assert_array_equal(bilinear_sample(images, frame, x, y), reference.bilinear_sample(images, frame, x, y))
    np.testing.assert_array_equal(bilinear_sample(images, None, x, y), reference.bilinear_sample(images, None, x, y))
    with pytest.raises(ValueError, match="frame"):
        bilinear_sample(images, frame + 5, x, y)


@pytest.mark.parametrize("camera", [{}, {"supersample": 1, "psf_px": 0.0}, {"supersample": 3, "psf_px": 0.3}])
def test_render_frames_match_reference(camera):
    lm = _landmarks(1, 4)
    lm[::7] += [3.3, -2.7]                      # head motion, sub-pixel
    np.testing.assert_array_equal(render.render_frames(lm, **camera), reference.render_frames(lm, **camera))


@pytest.mark.parametrize(("s", "sd"), [(1, 0.0), (1, 0.7), (2, 1.4), (3, 2.1), (2, 9.0)])
def test_camera_is_scipy_blur_then_skimage_block_mean(s, sd):
    """The renderer's compiled camera against the library calls it replaces, bit for bit
    before rounding shows: random scenes with values near the .5 rounding boundaries."""
    rng = np.random.default_rng(5)
    scene = rng.uniform(0.0, 255.0, (3, 12 * s, 12 * s))
    scene[1] = np.round(scene[1]) + 0.5                          # rounding ties
    scene[2, :, : 6 * s] = 300.0                                 # clipped at 255
    expected = gaussian_filter(scene, (0.0, sd, sd), mode="nearest") if sd > 0 else scene
    expected = downscale_local_mean(expected, (1, s, s)) if s > 1 else expected
    np.testing.assert_array_equal(render._camera(scene, sd, s), np.clip(np.rint(expected), 0, 255).astype(np.uint8))


def test_bad_inputs():
    tri = np.array([[0, 1, 2]])
    pts = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]])
    with pytest.raises(ValueError, match="triangles"):
        warp_triangles(np.zeros((8, 8)), pts, pts, tri + 1, (8, 8))
    with pytest.raises(ValueError, match="images"):
        warp_triangles(np.zeros((3, 8, 8)), pts, np.stack([pts, pts]), tri, (8, 8))
    with pytest.raises(ValueError, match="src_points"):
        warp_triangles(np.zeros((8, 8)), pts[:2], pts, tri, (8, 8))
