"""The per-frame exports of a synthesis (bayes_talk.pipeline.exports): what they hold, that
reading each one back gives the very arrays written, and their refusals. On a small AAM of
rendered faces and a hand-made synthesis result (the command line's ``synth --export`` is in
tests/pipeline/test_pipeline.py)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bayes_talk.corpus import render
from bayes_talk.data import face
from bayes_talk.features.aam import AAM
from bayes_talk.pipeline import exports as X
from bayes_talk.synthesis.result import SynthesisResult

T, K, FPS = 6, 4, 25.0


@pytest.fixture(scope="module")
def aam() -> AAM:
    rng = np.random.default_rng(0)
    lm = np.concatenate([face.face_landmarks(face.random_phone_intervals(rng, 12), 12, image_size=48, rng=rng)
                         for _ in range(3)])
    return AAM.fit(render.render_frames(lm, image_size=48), lm, variance=0.95)


@pytest.fixture(scope="module")
def result(aam) -> SynthesisResult:
    """A four-component mixture over T frames of the AAM's parameters (mean-removed)."""
    rng = np.random.default_rng(1)
    sd = 0.2 * np.sqrt(np.r_[aam.combined_pca.eigenvalues, np.full(6, 1e-4)])
    dm = rng.normal(size=(1, K, T, aam.n_params)) * sd
    return SynthesisResult("laplace", None, dm, np.broadcast_to((0.5 * sd) ** 2, dm.shape).copy(), seed=7)


def test_the_export_holds_the_results_moments_exact_quantiles_and_landmarks(aam, result):
    off = aam.mean_params
    fx = X.frame_export(result, FPS, aam=aam, offset=off, seed=3, n_draws=64)
    np.testing.assert_array_equal(fx.time, np.arange(T) / FPS)
    np.testing.assert_array_equal(fx.mean, result.mean)
    np.testing.assert_array_equal(fx.sd, np.sqrt(result.var))
    for q, got in ((0.05, fx.q05), (0.5, fx.q50), (0.95, fx.q95)):
        np.testing.assert_allclose(got, result.quantile(q), rtol=1e-13, atol=1e-15)   # the mixture's own
    np.testing.assert_array_equal(fx.q50, result.quantile(0.5))
    lo, hi = result.interval(0.9)                                        # bit for bit as bands.npz has them
    np.testing.assert_array_equal(fx.q05, lo)
    np.testing.assert_array_equal(fx.q95, hi)
    # F(q05) = 0.05, F(q95) = 0.95 of the mixture: exact quantiles, not a Gaussian's
    np.testing.assert_allclose(result.cdf(fx.q05), 0.05, atol=1e-10)
    np.testing.assert_allclose(result.cdf(fx.q95), 0.95, atol=1e-10)
    assert np.all(fx.q05 < fx.q50) and np.all(fx.q50 < fx.q95)
    # the landmarks of the mean (landmarks.npy) and their sd over 64 draws of the predictive
    np.testing.assert_allclose(fx.landmarks, aam.reconstruct(result.mean + off)[0], rtol=0, atol=1e-10)
    draws = result.sample(64, seed=3) + off
    want_sd = np.stack([aam.reconstruct(d)[0] for d in draws]).std(axis=0)
    np.testing.assert_allclose(fx.landmark_sd, want_sd, rtol=1e-9, atol=1e-12)
    assert fx.landmark_sd.shape == (T, aam.n_landmarks, 2) and np.all(fx.landmark_sd > 0)
    again, other = (X.frame_export(result, FPS, aam=aam, offset=off, seed=s, n_draws=64) for s in (3, 4))
    np.testing.assert_array_equal(again.landmark_sd, fx.landmark_sd)     # seeded
    assert not np.array_equal(other.landmark_sd, fx.landmark_sd)
    assert fx.param_names[:2] == ["c1", "c2"] and fx.param_names[-6:] == [
        "tx", "ty", "log_scale", "rotation", "texture_mean", "log_texture_std"]
    assert len(fx.param_names) == aam.n_params


@pytest.mark.parametrize("fmt", ["json", "csv"])
def test_each_export_reads_back_to_the_same_arrays(aam, result, tmp_path, fmt):
    fx = X.frame_export(result, FPS, aam=aam, offset=aam.mean_params, seed=3, n_draws=16)
    path = fx.write(tmp_path / f"frames.{fmt}")
    back = X.FrameExport.read(path)
    for k in ("time", "mean", "sd", "q05", "q50", "q95", "landmarks", "landmark_sd"):
        assert np.array_equal(getattr(back, k), getattr(fx, k)), k
    assert back.param_names == fx.param_names and back.fps == pytest.approx(FPS, rel=1e-12)
    if fmt == "json":
        np.testing.assert_array_equal(back.offset, aam.mean_params)
        assert (back.method, back.seed, back.n_draws) == ("laplace", 3, 16)
        head = json.loads(path.read_text())
        assert head["format"] == X.FRAMES_FORMAT and head["version"] == 1
        assert head["n_params"] == aam.n_params and head["n_landmarks"] == aam.n_landmarks
        assert head["quantile_levels"] == [0.05, 0.5, 0.95] and len(head["frames"]) == T
        assert set(head["frames"][0]) == {"frame", "time", "mean", "sd", "q05", "q50", "q95", "landmarks",
                                          "landmark_sd"}
    else:
        header = path.read_text().splitlines()[0].split(",")
        assert header[:4] == ["frame", "time_s", "mean_c1", "mean_c2"]
        assert header[-4:] == [f"lm{aam.n_landmarks - 2}_sd_x", f"lm{aam.n_landmarks - 2}_sd_y",
                               f"lm{aam.n_landmarks - 1}_sd_x", f"lm{aam.n_landmarks - 1}_sd_y"]
        assert len(header) == 2 + 5 * aam.n_params + 4 * aam.n_landmarks
        assert len(path.read_text().splitlines()) == 1 + T
    assert [p.name for p in tmp_path.iterdir()] == [path.name]            # no temporary file left


@pytest.mark.parametrize("fmt", ["json", "csv"])
def test_the_landmark_track_reads_back(aam, result, tmp_path, fmt):
    lm = aam.reconstruct_landmarks(result.mean + aam.mean_params)
    path = X.write_landmark_track(tmp_path / f"landmarks_track.{fmt}", lm, FPS, aam.image_shape)
    back, fps = X.read_landmark_track(path)
    assert np.array_equal(back, lm) and fps == pytest.approx(FPS, rel=1e-12)
    if fmt == "csv":   # one row per landmark per frame
        rows = path.read_text().splitlines()
        assert rows[0] == "frame,time_s,landmark,x,y" and len(rows) == 1 + T * aam.n_landmarks
        assert rows[1].split(",")[:3] == ["0", "0.0", "0"]
    else:
        doc = json.loads(path.read_text())
        assert (doc["format"], doc["image_width"], doc["image_height"]) == (X.TRACK_FORMAT, 48, 48)


def test_an_export_without_an_aam_has_no_landmarks(result, tmp_path):
    fx = X.frame_export(result, FPS)
    assert fx.landmarks is None and fx.n_landmarks == 0 and fx.param_names[0] == "p1"
    for fmt in ("json", "csv"):
        back = X.FrameExport.read(fx.write(tmp_path / f"f.{fmt}"))
        assert back.landmarks is None and np.array_equal(back.q95, fx.q95)
    assert not any(c.startswith("lm") for c in fx.columns())


def test_bad_exports_are_refused_naming_the_problem(aam, result, tmp_path):
    with pytest.raises(ValueError, match="n_draws"):
        X.frame_export(result, FPS, aam=aam, offset=aam.mean_params, n_draws=1)
    with pytest.raises(ValueError, match="offset"):
        X.frame_export(result, FPS, aam=aam)
    with pytest.raises(ValueError, match="fps"):
        X.frame_export(result, 0.0)
    with pytest.raises(ValueError, match="export format"):
        X.export_file_names("xml")
    fx = X.frame_export(result, FPS)
    with pytest.raises(ValueError, match=r"\.json or \.csv"):
        fx.write(tmp_path / "frames.txt")
    bad = tmp_path / "other.json"
    bad.write_text(json.dumps({"format": "something.else", "version": 1}))
    with pytest.raises(ValueError, match="other.json.*format"):
        X.FrameExport.read(bad)
    with pytest.raises(ValueError, match="other.json.*format"):
        X.read_landmark_track(bad)
    (tmp_path / "t.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="t.csv"):
        X.read_landmark_track(tmp_path / "t.csv")
    with pytest.raises(ValueError, match="t.csv"):
        X.FrameExport.read(tmp_path / "t.csv")
