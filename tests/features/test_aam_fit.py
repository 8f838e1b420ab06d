"""AAM search (bayes_talk.features.aam_fit) and sparse-annotation tracking
(bayes_talk.corpus.tracking) on rendered synthetic faces (no speech synthesis needed)."""
from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest

from bayes_talk.corpus import load_corpus, render
from bayes_talk.corpus.tracking import (
    NoAnnotatedFrameError,
    propose_prototypes,
    read_annotations,
    track_corpus,
)
from bayes_talk.data import face
from bayes_talk.data.face import random_phone_intervals
from bayes_talk.data.labels import write_lab
from bayes_talk.data.speech import write_wav
from bayes_talk.features.aam_fit import (
    LOST_THRESHOLD,
    AAMFitter,
    FrameSizeError,
    LandmarkCountError,
    TooFewPrototypesError,
)

N_SEQ, N_FRAMES, N_PROTO_SEQ = 8, 40, 6
SR = 22050


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(1601)
    lms, ivs = [], []
    for _ in range(N_SEQ):
        iv = random_phone_intervals(rng, N_FRAMES)
        ivs.append(iv)
        lms.append(face.face_landmarks(iv, N_FRAMES, rng=rng))
    lm = np.stack(lms)
    frames = render.render_frames(lm.reshape(-1, face.N_LANDMARKS, 2)).reshape(N_SEQ, N_FRAMES, 128, 128)
    return frames, lm, ivs


@pytest.fixture(scope="module")
def fitter(data):
    frames, lm, _ = data
    sel = np.arange(0, N_FRAMES, 3)
    imgs = frames[:N_PROTO_SEQ][:, sel].reshape(-1, 128, 128)
    lms = lm[:N_PROTO_SEQ][:, sel].reshape(-1, face.N_LANDMARKS, 2)
    return AAMFitter.from_prototypes(imgs, lms, n_levels=2)


def _perturb(lm: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A similarity (2 px shift, 2 degrees, 3 % scale) of the true shape plus 0.7 px noise."""
    c = lm.mean(axis=0)
    a = np.deg2rad(rng.choice([-2.0, 2.0]))
    R = 1.03 * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return (lm - c) @ R.T + c + rng.choice([-2.0, 2.0], size=2) + rng.normal(0, 0.7, lm.shape)


def test_perturbed_shape_is_recovered(data, fitter):
    frames, lm, _ = data
    rng = np.random.default_rng(3)
    errs, start_errs = [], []
    for s in range(N_PROTO_SEQ, N_SEQ):
        for t in range(1, N_FRAMES, 4):              # frames never used as prototypes
            init = _perturb(lm[s, t], rng)
            assert fitter.score(frames[s, t], init) > LOST_THRESHOLD   # the start is a bad fit
            r = fitter.fit(frames[s, t], init)
            errs.append(np.linalg.norm(r.landmarks - lm[s, t], axis=1))
            start_errs.append(np.linalg.norm(init - lm[s, t], axis=1))
            assert r.score < LOST_THRESHOLD
    e = np.concatenate(errs)
    print(f"\nstart error median {np.median(np.concatenate(start_errs)):.2f} px -> "
          f"fit median {np.median(e):.3f}, p95 {np.percentile(e, 95):.3f}, max {e.max():.3f} px")
    assert np.median(e) < 0.25 and np.percentile(e, 95) < 1.0


def test_track_from_one_annotated_frame_and_without(data, fitter):
    frames, lm, _ = data
    s = N_SEQ - 1
    res = fitter.track(frames[s], {10: lm[s, 10]})
    assert res.source[10] == "annotated" and not res.lost
    e = np.linalg.norm(res.landmarks - lm[s], axis=2)
    assert np.median(e) < 0.25 and e.max() < 2.0
    # no annotation: searched from the prototypes' mean pose
    res = fitter.track(frames[s], {})
    e = np.linalg.norm(res.landmarks - lm[s], axis=2)
    assert not res.lost and np.median(e) < 0.25


def test_lost_frame_reported_with_its_index(data, fitter):
    frames, lm, _ = data
    s = N_SEQ - 2
    f = frames[s].copy()
    f[17] = np.random.default_rng(0).integers(0, 256, size=(128, 128))   # not a face
    res = fitter.track(f, {0: lm[s, 0]})
    assert res.lost == [17]
    assert np.all(np.isnan(res.landmarks[17])) and res.scores[17] > LOST_THRESHOLD
    e = np.linalg.norm(res.landmarks[18:] - lm[s, 18:], axis=2)
    assert np.median(e) < 0.25                       # resumed from the last good frame


def test_fitter_bad_inputs(data, fitter):
    frames, lm, _ = data
    with pytest.raises(FrameSizeError, match=r"100x100 .*128x128"):
        fitter.track(np.zeros((3, 100, 100), np.uint8), {0: lm[0, 0]})
    with pytest.raises(LandmarkCountError, match=r"50 landmarks, but the AAM has 57"):
        fitter.fit(frames[0, 0], lm[0, 0, :50])
    with pytest.raises(TooFewPrototypesError, match=r"4 annotated frames are too few"):
        AAMFitter.from_prototypes(frames[0, :4], lm[0, :4])


# ------------------------------------------------------------------ the corpus command
def _user_corpus(root, data, annotate):
    """Two videos as a sparsely annotated user corpus: silent WAV, .lab, PNG frames."""
    frames, lm, ivs = data
    root.mkdir()
    for k, s in enumerate((N_SEQ - 2, N_SEQ - 1)):
        name = f"v{k}"
        write_wav(root / f"{name}.wav", np.zeros(N_FRAMES * SR // 25, np.int16), SR)
        write_lab(root / f"{name}.lab", [(round(a, 4), round(b, 4), p) for a, b, p in ivs[s]])
        (root / name).mkdir()
        for t in range(N_FRAMES):
            iio.imwrite(root / name / f"{t:04d}.png", frames[s, t])
        if annotate == "sparse":
            if k == 0:   # a landmarks file per annotated frame (.pts and .npy)
                (root / f"{name}.annotations").mkdir()
                for t in range(0, N_FRAMES, 3):
                    pts = lm[s, t]
                    txt = "version: 1\nn_points: 57\n{\n" + "\n".join(f"{x} {y}" for x, y in pts) + "\n}\n"
                    (root / f"{name}.annotations" / f"{t:04d}.pts").write_text(txt)
            else:        # a sparse array with NaN rows
                a = np.full_like(lm[s], np.nan)
                a[::3] = lm[s, ::3]
                np.save(root / f"{name}.annotations.npy", a)
    return root


def test_track_corpus_then_load_corpus(data, tmp_path):
    _frames, lm, _ = data
    root = _user_corpus(tmp_path / "c", data, "sparse")
    with pytest.raises(ValueError, match="corpus track"):
        load_corpus(root, cache=False)
    s = track_corpus(root, per_phone=1)
    assert s.n_annotated == 28 and not any(s.lost.values()) and not s.not_written
    for k, seq_i in enumerate((N_SEQ - 2, N_SEQ - 1)):
        got = np.load(root / f"v{k}.landmarks.npy")
        e = np.linalg.norm(got - lm[seq_i], axis=2)
        assert np.median(e) < 0.25
        tj = json.loads((root / f"v{k}.track.json").read_text())
        assert tj["source"][::3] == ["annotated"] * 14 and len(tj["scores"]) == N_FRAMES
    c = load_corpus(root, cache=False)
    assert [q.aam.shape[0] for q in c] == [N_FRAMES, N_FRAMES] and c.aam_path == root / "aam.npz"
    # rerunning overwrites our own files; a file we did not write is never overwritten
    track_corpus(root, per_phone=1)
    np.save(root / "v0.landmarks.npy", np.zeros((N_FRAMES, 57, 2)))
    with pytest.raises(FileExistsError, match="v0.landmarks.npy: exists and was not written"):
        track_corpus(root, per_phone=1)


def test_track_corpus_named_errors(data, tmp_path):
    _frames, lm, _ = data
    root = _user_corpus(tmp_path / "none", data, None)
    with pytest.raises(NoAnnotatedFrameError, match="no annotated frame in any video.*prototypes.json"):
        track_corpus(root, per_phone=2)
    listing = json.loads((root / "prototypes" / "prototypes.json").read_text())
    assert listing["frames"] and all((root / "prototypes" / f["image"]).exists() for f in listing["frames"])
    assert {f["phone"] for f in listing["frames"]} >= {"sil"}

    root = _user_corpus(tmp_path / "one", data, "sparse")
    (root / "v1.annotations.npy").unlink()
    with pytest.raises(NoAnnotatedFrameError, match="v1: video has no annotated frame"):
        track_corpus(root, per_phone=1)

    root = _user_corpus(tmp_path / "count", data, "sparse")
    np.save(root / "v0.annotations" / "0002.npy", lm[N_SEQ - 2, 2, :50])
    with pytest.raises(LandmarkCountError, match=r"0002.npy: frame 2 has 50 landmarks, expected 57"):
        read_annotations(root / "v0.annotations", N_FRAMES)

    root = _user_corpus(tmp_path / "size", data, "sparse")
    for p in (root / "v1").iterdir():
        iio.imwrite(p, np.zeros((96, 128), np.uint8))
    with pytest.raises(FrameSizeError, match=r"v1: frames are 96x128 pixels"):
        track_corpus(root, per_phone=1)

    root = _user_corpus(tmp_path / "few", data, "sparse")
    a = np.load(root / "v1.annotations.npy")
    a[9:] = np.nan                                   # frames 0, 3, 6 only
    np.save(root / "v1.annotations.npy", a)
    import shutil
    shutil.rmtree(root / "v0.annotations")
    with pytest.raises(NoAnnotatedFrameError):
        track_corpus(root, per_phone=1)
    with pytest.raises(TooFewPrototypesError, match="3 annotated frames are too few"):
        track_corpus(root, per_phone=1, search_unannotated=True)


def test_propose_prototypes_refuses_non_empty_out(data, tmp_path):
    root = _user_corpus(tmp_path / "p", data, None)
    out = tmp_path / "out"
    p = propose_prototypes(root, 2, out, per_video=1)
    frames = json.loads(p.read_text())["frames"]
    assert {f["video"] for f in frames} == {"v0", "v1"}
    png = iio.imread(out / frames[0]["image"])
    assert png.shape == (128, 128) and png.dtype == np.uint8
    with pytest.raises(FileExistsError, match="not empty"):
        propose_prototypes(root, 2, out)


def test_cli_propose_then_track_without_annotations(data, tmp_path, capsys, monkeypatch):
    from bayes_talk.app.cli import main

    root = _user_corpus(tmp_path / "cli", data, None)
    monkeypatch.chdir(tmp_path)   # a relative corpus path is recorded as given, no machine's directory
    assert main(["corpus", "propose-prototypes", "cli", "--prototypes", "1"]) == 0
    assert json.loads((root / "prototypes" / "prototypes.json").read_text())["corpus"] == "cli"
    assert main(["corpus", "track", str(root)]) == 2
    err = capsys.readouterr().err
    assert "no annotated frame in any video" in err and "NAME.annotations" in err
