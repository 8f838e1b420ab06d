"""Landmark face (bayes_talk.data.face) and renderer (bayes_talk.corpus.render)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_erosion
from scipy.spatial import Delaunay
from skimage.transform import PiecewiseAffineTransform, warp

from bayes_talk.corpus import render
from bayes_talk.data import face
from bayes_talk.data.face import random_phone_intervals
from bayes_talk.data.labels import frame_labels
from bayes_talk.features.warp import warp_piecewise_affine

N_SEQ, N_FRAMES = 30, 50


@pytest.fixture(scope="module")
def corpus():
    rng = np.random.default_rng(20240601)
    out = []
    for _ in range(N_SEQ):
        iv = random_phone_intervals(rng, N_FRAMES)
        lm = face.face_landmarks(iv, N_FRAMES, rng=rng)
        out.append((iv, lm, frame_labels(iv, N_FRAMES)))
    return out


def test_landmarks_shape_dtype_and_inside_frame(corpus):
    for _, lm, _ in corpus:
        assert lm.shape == (N_FRAMES, face.N_LANDMARKS, 2)
        assert lm.dtype == np.float64
        assert lm.min() >= 2.0 and lm.max() <= 128 - 3.0
    assert 40 <= face.N_LANDMARKS <= 60


def test_same_seed_same_landmarks_other_seed_differs():
    iv = random_phone_intervals(np.random.default_rng(3), 40)
    a = face.face_landmarks(iv, 40, rng=np.random.default_rng(11))
    b = face.face_landmarks(iv, 40, rng=np.random.default_rng(11))
    c = face.face_landmarks(iv, 40, rng=np.random.default_rng(12))
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 0.1


def test_bilabial_frames_have_closed_lips_open_vowels_do_not(corpus):
    bil, opn = [], []
    for _, lm, labels in corpus:
        ap = face.inner_lip_aperture(lm)
        bil += [a for a, lab in zip(ap, labels) if lab in ("p", "b", "m")]
        opn += [a for a, lab in zip(ap, labels) if lab in ("aa", "ae", "ah")]
    bil, opn = np.array(bil), np.array(opn)
    assert len(bil) >= 30 and len(opn) >= 30
    assert np.median(bil) < 0.05
    assert np.percentile(bil, 90) < 0.5
    assert np.median(opn) > 3.0


def test_silence_is_rest_with_closed_mouth():
    iv = [(0.0, 2.0, "sil")]
    tr = face.face_trajectories(iv, 50, rng=np.random.default_rng(0))
    assert np.all(tr.articulators[:, face.ARTICULATORS.index("aperture")] == 0.0)
    assert 0.02 <= tr.lead_s <= 0.04


def test_rounding_coarticulates_into_preceding_consonant():
    """Cohen-Massaro anticipation: /t/ before /uw/ is rounder than /t/ before /iy/."""
    spread = face.ARTICULATORS.index("spread")
    vals = {}
    for v in ("uw", "iy"):
        iv = [(0.0, 0.3, "sil"), (0.3, 0.4, "t"), (0.4, 0.6, v), (0.6, 1.0, "sil")]
        s = [face.face_trajectories(iv, 25, rng=np.random.default_rng(k)).articulators[8, spread]
             for k in range(10)]  # frame 8 centre = 0.34 s, inside /t/
        vals[v] = np.mean(s)
    assert vals["uw"] < -0.2 and vals["iy"] > 0.2


def test_labiodental_tucks_and_raises():
    iv = [(0.0, 0.3, "sil"), (0.3, 0.45, "f"), (0.45, 0.8, "sil")]
    tr = face.face_trajectories(iv, 20, rng=np.random.default_rng(1))
    k = int(0.375 * 25.0)  # frame containing the /f/ centre
    assert tr.articulators[k, face.ARTICULATORS.index("tuck")] > 0.8
    assert tr.articulators[k, face.ARTICULATORS.index("raise")] > 1.0


@pytest.mark.parametrize(
    "intervals, n_frames, match",
    [
        ([(0.0, 0.5, "xx")], 10, "unknown phone"),
        ([(0.5, 0.2, "aa")], 10, "start < end"),
        ([(0.0, 0.5, "aa"), (0.4, 0.8, "m")], 10, "non-overlapping"),
        ([], 10, "intervals"),
        ([(0.0, 0.5, "aa")], 0, "n_frames"),
    ],
)
def test_bad_input_raises(intervals, n_frames, match):
    with pytest.raises(ValueError, match=match):
        face.face_landmarks(intervals, n_frames, rng=np.random.default_rng(0))


def test_rng_required():
    with pytest.raises(ValueError, match="rng"):
        face.face_landmarks([(0.0, 0.5, "aa")], 5, rng=0)


def test_render_deterministic_and_mouth_appearance_changes(corpus):
    lm = np.concatenate([c[1] for c in corpus[:6]])
    a = render.render_frames(lm)
    b = render.render_frames(lm)
    assert a.dtype == np.uint8 and a.shape == (len(lm), 128, 128)
    np.testing.assert_array_equal(a, b)
    ap = face.inner_lip_aperture(lm)
    inner = face.LANDMARK_GROUPS["inner_lip"]
    darkest = np.empty(len(lm))
    for t in range(len(lm)):
        x0, y0 = np.floor(lm[t, inner].min(axis=0)).astype(int)
        x1, y1 = np.ceil(lm[t, inner].max(axis=0)).astype(int)
        darkest[t] = a[t, y0:y1 + 1, x0:x1 + 1].min()
    # the camera's optics and pixel integration spread the (grey 32-42) cavity between the
    # teeth, often 1-2 px tall, over its neighbours; lips and skin stay above ~95
    assert np.all(darkest[ap == 0] > 85)              # closed lips: no cavity visible
    assert np.mean(darkest[ap > 5] < 80) > 0.9        # wide open: a dark cavity


def test_teeth_show_in_labiodental():
    iv = [(0.0, 0.3, "sil"), (0.3, 0.5, "f"), (0.5, 0.8, "sil")]
    lm = face.face_landmarks(iv, 20, rng=np.random.default_rng(2))
    k = int(0.4 * 25.0)
    img = render.render_frames(lm[k:k + 1])[0]
    inner = face.LANDMARK_GROUPS["inner_lip"]
    x0, y0 = np.floor(lm[k, inner].min(axis=0)).astype(int)
    x1, y1 = np.ceil(lm[k, inner].max(axis=0)).astype(int)
    # bright upper teeth between the lips (grey 228, a 1-2 px band: the camera's optics
    # and pixel integration mix it with the lips); lips and skin there stay below ~140
    assert img[y0:y1 + 1, x0:x1 + 1].max() > 170


def test_fast_warp_matches_skimage_on_interior_pixels(corpus):
    rng = np.random.default_rng(7)
    image = rng.uniform(0, 255, (128, 128))
    image = np.asarray(render.face_texture()) + 0.3 * image   # structured + random
    src = face.reference_shape(128)
    dst = corpus[0][1][17]
    tri = Delaunay(dst).simplices
    ours, covered = warp_piecewise_affine(image, src, dst, tri, (128, 128))
    tform = PiecewiseAffineTransform.from_estimate(dst, src)   # output -> input coords
    ref = warp(image, tform, output_shape=(128, 128), order=1, preserve_range=True)
    interior = binary_erosion(covered[0], iterations=2)
    assert interior.sum() > 5000
    np.testing.assert_allclose(ours[0][interior], ref[interior], atol=1e-8)


def test_render_rejects_bad_landmarks():
    with pytest.raises(ValueError, match="landmarks"):
        render.render_frames(np.zeros((3, 10, 2)))


def test_cavity_triangles_tile_the_inner_lip_polygon():
    ref = face.reference_shape(128)
    tri = render.face_triangles(128)[render.cavity_triangles(128)]
    v = ref[tri]
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    poly = ref[face.LANDMARK_GROUPS["inner_lip"]]
    x, y = poly[:, 0], poly[:, 1]
    poly_area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert area == pytest.approx(poly_area, rel=1e-9)


def _subpixel_aliasing(corpus, **camera) -> float:
    """Variance of a still face's AAM appearance parameters under sub-pixel translation,
    as a fraction of the held-out appearance variance of talking faces (same renderer,
    its own AAM). A perfect camera + AAM gives 0: Procrustes removes the translation."""
    from bayes_talk.features.aam import AAM

    lm_fit = np.concatenate([lm[::4] for _, lm, _ in corpus[:12]])
    aam = AAM.fit(render.render_frames(lm_fit, **camera), lm_fit, variance=0.99, texture_inset=1.0)
    lm_test = np.concatenate([lm for _, lm, _ in corpus[24:]])
    talk = aam.project(render.render_frames(lm_test, **camera), lm_test)[:, aam.param_slices["combined"]]
    offsets = np.array([(dx, dy) for dx in np.arange(0, 1, 0.2) for dy in np.arange(0, 1, 0.2)])
    still = face.reference_shape(128)[None] + offsets[:, None, :]
    c = aam.project(render.render_frames(still, **camera), still)[:, aam.param_slices["combined"]]
    return float(c.var(axis=0).sum() / talk.var(axis=0).sum())


def test_area_integrating_camera_removes_subpixel_aliasing(corpus):
    old = _subpixel_aliasing(corpus, supersample=1, psf_px=0.0)    # format-1 point sampling
    new = _subpixel_aliasing(corpus)                                # the corpus default
    print(f"\nsub-pixel translation / talking-face appearance variance: point sampling {old:.4f}, "
          f"camera model {new:.4f}")
    assert new < 0.25 * old


def test_render_rejects_bad_camera_settings():
    lm = face.reference_shape(128)[None]
    with pytest.raises(ValueError, match="supersample"):
        render.render_frames(lm, supersample=0)
    with pytest.raises(ValueError, match="psf_px"):
        render.render_frames(lm, psf_px=-1.0)
