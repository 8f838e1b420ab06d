"""Combined AAM (bayes_talk.features.aam) on rendered synthetic faces."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.ndimage import binary_erosion
from skimage.transform import PiecewiseAffineTransform, warp

from bayes_talk.corpus import render
from bayes_talk.data import face
from bayes_talk.data.face import random_phone_intervals
from bayes_talk.data.labels import frame_labels
from bayes_talk.features.aam import AAM, remove_sequence_mean
from bayes_talk.features.procrustes import procrustes_align

N_SEQ, N_FRAMES, N_TRAIN = 20, 50, 15
BILABIAL, OPEN = ("p", "b", "m"), ("aa", "ae", "ah")


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(777)
    lms, labels = [], []
    for _ in range(N_SEQ):
        iv = random_phone_intervals(rng, N_FRAMES)
        lms.append(face.face_landmarks(iv, N_FRAMES, rng=rng))
        labels.append(frame_labels(iv, N_FRAMES))
    lm = np.stack(lms)                                     # (S, T, P, 2)
    frames = render.render_frames(lm.reshape(-1, face.N_LANDMARKS, 2)).reshape(N_SEQ, N_FRAMES, 128, 128)
    return frames, lm, labels


@pytest.fixture(scope="module")
def model(data):
    frames, lm, _ = data
    n = N_TRAIN * N_FRAMES
    return AAM.fit(frames[:N_TRAIN].reshape(n, 128, 128), lm[:N_TRAIN].reshape(n, -1, 2))


@pytest.fixture(scope="module")
def held_out(data, model):
    frames, lm, _ = data
    n = (N_SEQ - N_TRAIN) * N_FRAMES
    f = frames[N_TRAIN:].reshape(n, 128, 128)
    l = lm[N_TRAIN:].reshape(n, -1, 2)
    return f, l, model.project(f, l)


def test_project_reconstruct_recovers_landmarks_and_texture(model, held_out):
    f, l, p = held_out
    assert p.shape == (len(f), model.n_params) and p.dtype == np.float64
    lm_hat, tex_hat = model.reconstruct(p)
    err = np.linalg.norm(lm_hat - l, axis=-1).mean()
    tex = model.warp_to_mean(f, l)
    psnr = 10 * np.log10(255.0**2 / np.mean((tex_hat - tex) ** 2))
    print(f"\nheld-out landmark error {err:.4f} px, texture PSNR {psnr:.2f} dB, "
          f"modes shape/texture/combined {model.n_shape_modes}/{model.n_texture_modes}/"
          f"{model.n_combined}, n_params {model.n_params}, W_s {model.shape_texture_weight:.3f}")
    assert err < 0.5
    assert psnr >= 35.0


def test_render_reproduces_frames(model, held_out):
    f, _, p = held_out
    r = model.render(p[:50])
    assert r.dtype == np.uint8 and r.shape == (50, 128, 128)
    psnr = 10 * np.log10(255.0**2 / np.mean((r.astype(float) - f[:50]) ** 2))
    print(f"\nheld-out rendered-frame PSNR {psnr:.2f} dB")
    assert psnr >= 28.0


def test_fast_warp_to_mean_matches_skimage(model, held_out):
    f, l, _ = held_out
    k = 37
    ours = model.texture_images(model.warp_to_mean(f[k:k + 1], l[k:k + 1]), fill=0.0)[0]
    tex_pts = model._a["tex_points"]
    tform = PiecewiseAffineTransform.from_estimate(tex_pts, l[k])   # mean frame -> image
    ref = warp(f[k].astype(np.float64), tform, output_shape=model.texture_shape, order=1,
               preserve_range=True)
    mask = model.texture_images(np.ones((1, model.n_pixels)), fill=0.0)[0] > 0
    interior = binary_erosion(mask, iterations=2)
    assert interior.sum() > 0.8 * model.n_pixels
    np.testing.assert_allclose(ours[interior], ref[interior], atol=1e-8)


def test_nearest_centroid_separates_bilabial_from_open_vowel_frames(data, model):
    frames, lm, labels = data
    c = model.param_slices["combined"]

    def collect(seqs):
        X, y = [], []
        for s in seqs:
            keep = [t for t, lab in enumerate(labels[s]) if lab in BILABIAL + OPEN]
            if keep:
                X.append(model.project(frames[s][keep], lm[s][keep])[:, c])
                y += [labels[s][t] in BILABIAL for t in keep]
        return np.concatenate(X), np.array(y)

    Xtr, ytr = collect(range(N_TRAIN))
    Xte, yte = collect(range(N_TRAIN, N_SEQ))
    assert ytr.sum() >= 5 and (~ytr).sum() >= 5 and yte.sum() >= 3 and (~yte).sum() >= 3
    mu_b, mu_o = Xtr[ytr].mean(axis=0), Xtr[~ytr].mean(axis=0)
    pred = np.linalg.norm(Xte - mu_b, axis=1) < np.linalg.norm(Xte - mu_o, axis=1)
    acc = float(np.mean(pred == yte))
    print(f"\nnearest-centroid accuracy {acc:.3f} on {len(yte)} held-out frames "
          f"({int(yte.sum())} bilabial)")
    assert acc >= 0.9


def test_fit_is_deterministic(data, model):
    frames, lm, _ = data
    n = N_TRAIN * N_FRAMES
    again = AAM.fit(frames[:N_TRAIN].reshape(n, 128, 128), lm[:N_TRAIN].reshape(n, -1, 2))
    x = frames[N_TRAIN, :5], lm[N_TRAIN, :5]
    np.testing.assert_array_equal(again.project(*x), model.project(*x))


def test_save_load_round_trip(tmp_path, model, held_out):
    f, l, p = held_out
    npz, js = model.save(tmp_path / "aam")
    assert npz.exists() and js.exists()
    assert not list(tmp_path.glob("*.tmp"))
    back = AAM.load(tmp_path / "aam.json")
    assert back.n_params == model.n_params
    np.testing.assert_array_equal(back.project(f[:10], l[:10]), model.project(f[:10], l[:10]))
    for a, b in zip(back.reconstruct(p[:10]), model.reconstruct(p[:10])):
        np.testing.assert_array_equal(a, b)
    with np.load(npz, allow_pickle=False) as z:
        assert "mean_shape" in z.files


def test_truncated_or_wrong_version_file_raises(tmp_path, model):
    npz, js = model.save(tmp_path / "m")
    data = npz.read_bytes()
    npz.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="truncated"):
        AAM.load(tmp_path / "m")
    npz.write_bytes(data)
    meta = json.loads(js.read_text())
    meta["version"] = 999
    js.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="version expected 1, found 999"):
        AAM.load(tmp_path / "m")
    js.write_text(js.read_text()[:20])
    with pytest.raises(ValueError, match="JSON"):
        AAM.load(tmp_path / "m")
    with pytest.raises(ValueError, match="not found"):
        AAM.load(tmp_path / "absent")


def test_procrustes_removes_similarity_transforms():
    base = face.rest_shape(128)
    rng = np.random.default_rng(0)
    shapes = []
    for _ in range(6):
        s, r, t = np.exp(rng.normal(0, 0.1)), rng.normal(0, 0.2), rng.normal(0, 5, 2)
        R = np.array([[np.cos(r), -np.sin(r)], [np.sin(r), np.cos(r)]])
        shapes.append(s * base @ R.T + t)
    mean, aligned, pose = procrustes_align(np.stack(shapes))
    assert np.abs(aligned - aligned[0]).max() < 1e-9
    assert np.abs(mean - aligned[0]).max() < 1e-9
    np.testing.assert_allclose(pose[:, :2], np.stack(shapes).mean(axis=1), atol=1e-9)


def test_remove_sequence_mean():
    rng = np.random.default_rng(1)
    x = rng.normal(3.0, 2.0, (40, 7))
    y = remove_sequence_mean(x)
    np.testing.assert_allclose(y.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(x - y, np.broadcast_to(x.mean(axis=0), x.shape), atol=1e-12)
    ys = remove_sequence_mean([x, 2 * x])
    np.testing.assert_allclose(ys[1], 2 * y, atol=1e-12)
    with pytest.raises(ValueError, match="params"):
        remove_sequence_mean(np.zeros(5))


def test_bad_inputs_raise(model, held_out):
    f, l, p = held_out
    with pytest.raises(ValueError, match="images"):
        model.project(f[:2, :64], l[:2])
    with pytest.raises(ValueError, match="landmarks"):
        model.project(f[:2], l[:3])
    with pytest.raises(ValueError, match="params"):
        model.reconstruct(p[:2, :-1])
    with pytest.raises(ValueError, match="variance"):
        AAM.fit(f[:5], l[:5], variance=1.5)


def test_texture_inset_drops_the_outline_ring(data, held_out):
    """texture_inset=1 (the built-in corpus choice): texture pixels >= 1 px inside the
    mean-shape hull; fewer pixels and texture modes, same accuracy bounds as above."""
    from scipy.spatial import ConvexHull

    frames, lm, _ = data
    f, l, _ = held_out
    X, L = frames[:N_TRAIN, ::5].reshape(-1, 128, 128), lm[:N_TRAIN, ::5].reshape(-1, face.N_LANDMARKS, 2)
    plain = AAM.fit(X, L)
    inset = AAM.fit(X, L, texture_inset=1.0)
    assert inset.n_pixels < plain.n_pixels and inset.meta["texture_inset"] == 1.0
    eq = ConvexHull(inset._a["tex_points"]).equations
    xy = np.stack([inset._a["pixel_cols"], inset._a["pixel_rows"]], axis=1).astype(float)
    assert (-(xy @ eq[:, :2].T + eq[:, 2])).min(axis=1).min() >= 1.0 - 1e-9
    print(f"\n{len(X)} frames: texture modes {plain.n_texture_modes} -> {inset.n_texture_modes}, "
          f"n_params {plain.n_params} -> {inset.n_params}")
    assert inset.n_texture_modes < plain.n_texture_modes
    p = inset.project(f, l)
    lm_hat, tex_hat = inset.reconstruct(p)
    assert np.linalg.norm(lm_hat - l, axis=-1).mean() < 0.5
    tex = inset.warp_to_mean(f, l)
    assert 10 * np.log10(255.0**2 / np.mean((tex_hat - tex) ** 2)) >= 35.0
    r = inset.render(p[:50])
    assert 10 * np.log10(255.0**2 / np.mean((r.astype(float) - f[:50]) ** 2)) >= 28.0
    with pytest.raises(ValueError, match="texture_inset"):
        AAM.fit(X[:5], L[:5], texture_inset=-1.0)
