"""Built corpus: reproducibility, layout, loader, cache, user layout, AAM acceptance."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from bayes_talk.corpus import build_corpus, load_corpus, load_npz, load_sentences
from bayes_talk.data.labels import read_lab, write_textgrid
from bayes_talk.data.phones import BILABIALS

OPEN_VOWELS = {"aa", "ae", "ah"}


def _files(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


# Budget ~40 s on 2 shared cores: every corpus is built once per module. `big` (40
# utterances: the acceptance test's data size; built and featurised in 2 worker
# processes) and `small` (4: layout, loader, cache, user layouts; built in-process) are
# shared; tests build only what they must (a 4-utterance rebuild, 2 utterances of seed 1).


@pytest.fixture(scope="module")
def big(built_once) -> Path:
    """40 utterances, seed 0 (the acceptance corpus), built in 2 worker processes, once per
    test run (its tests may run on both pytest-xdist workers; conftest.built_once). Read-only:
    nothing is loaded from it here (``big_corpus`` loads a copy)."""
    return built_once("corpus_big_n40_seed0", lambda out: build_corpus(out, n_utterances=40, seed=0, n_workers=2),
                      leaf="c")


@pytest.fixture(scope="module")
def big_corpus(big, tmp_path_factory):
    """A copy of ``big`` loaded once (cold cache: featurised in worker processes; the copy
    keeps the shared build free of a feature cache, so every worker's load is cold)."""
    return load_corpus(shutil.copytree(big, tmp_path_factory.mktemp("big") / "c"), n_workers=2)


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    return build_corpus(tmp_path_factory.mktemp("small") / "c", n_utterances=4, seed=0)


def test_rebuild_is_byte_identical_and_keeps_user_files(small, big, tmp_path):
    again = tmp_path / "again"
    again.mkdir()
    (again / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not empty"):
        build_corpus(again, n_utterances=4, seed=0)
    # `small` was built in this process; this rebuild runs in 2 worker processes
    build_corpus(again, n_utterances=4, seed=0, force=True, n_workers=2)
    assert (again / "notes.txt").read_text() == "mine"
    a, b = _files(small), _files(again)
    b.pop("notes.txt")
    a.pop("features.npz", None), b.pop("features.npz", None)
    differing = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    assert not differing, f"files differ between identical builds: {differing}"
    # utterance i does not depend on n_utterances: the 40-utterance build starts alike
    g = _files(big)
    for k, v in a.items():
        if k.startswith("utterances/"):
            assert g[k] == v, k


def test_other_seed_differs(small, tmp_path):
    other = build_corpus(tmp_path / "s1", n_utterances=2, seed=1)
    for ext in (".wav", ".landmarks.npz", ".frames.npz"):
        f = f"utterances/utt0000{ext}"
        assert (other / f).read_bytes() != (small / f).read_bytes(), f


def test_manifest_and_layout(small):
    m = json.loads((small / "manifest.json").read_text())
    assert m["format"] == "bayes_talk-corpus" and m["fps"] == 25.0 and m["audio_rate"] == 22050
    assert len(m["phone_set"]) == 40 and m["image_size"] == 128 and m["seed"] == 0
    assert [s["text"] for s in m["sequences"]] == load_sentences(None, 4)
    for f in m["files"]:
        assert (small / f).is_file(), f
    for s in m["sequences"]:
        fr = load_npz(small / s["frames"], ("frames",))["frames"]
        lm = load_npz(small / s["landmarks"], ("landmarks",))["landmarks"]
        info = sf.info(str(small / s["wav"]))
        assert info.samplerate == 22050 and info.subtype == "PCM_16"
        assert fr.dtype == np.uint8 and fr.shape == (s["n_frames"], 128, 128)
        assert lm.dtype == np.float64 and lm.shape[:2] == (s["n_frames"], s["n_landmarks"])
        assert info.frames == s["n_frames"] * 882


def test_loader_frame_counts_and_cache(small, tmp_path):
    c = load_corpus(small)
    m = json.loads((small / "manifest.json").read_text())
    for seq, sm in zip(c, m["sequences"]):
        T = sm["n_frames"]
        assert seq.mfcc.shape == (T, 20) and seq.aam.shape[0] == T and len(seq.labels) == T
        assert seq.landmarks.shape[0] == T
        assert np.allclose(seq.aam.mean(axis=0), 0.0, atol=1e-9)  # mean removal default on
        assert seq.meta["text"] == sm["text"]
    raw = load_corpus(small, mean_removal=False)
    for a, b in zip(c, raw):
        assert np.allclose(a.aam + a.meta["aam_mean"], b.aam)
    key = str(load_npz(small / "features.npz")["key"])
    # the cache is invalidated when an input changes: edit a label in a copy
    cp = tmp_path / "cp"
    shutil.copytree(small, cp)
    lab = cp / m["sequences"][0]["lab"]
    lines = lab.read_text().splitlines()
    i = next(j for j, ln in enumerate(lines) if ln.split()[2] != "sil")
    s, e, _ = lines[i].split()
    lines[i] = f"{s} {e} zh"
    lab.write_text("\n".join(lines) + "\n")
    c2 = load_corpus(cp)
    assert str(load_npz(cp / "features.npz")["key"]) != key
    assert "zh" in c2[0].labels and c2[0].labels != c[0].labels
    lines[i] = f"{s} {e} qq"
    lab.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"'qq'.*utt0000\.lab"):
        load_corpus(cp)


def test_loader_errors_name_files(small, tmp_path):
    cp = tmp_path / "cp"
    shutil.copytree(small, cp)
    m = json.loads((cp / "manifest.json").read_text())
    wav = cp / m["sequences"][1]["wav"]
    y, sr = sf.read(wav, dtype="int16")
    sf.write(wav, y[: len(y) // 2], sr, subtype="PCM_16")  # shorter than its labels
    with pytest.raises(ValueError, match=r"utt0001\.lab.*utt0001\.wav"):
        load_corpus(cp)
    wav.write_bytes(b"RIFF garbage")
    with pytest.raises(ValueError, match=r"utt0001\.wav"):
        load_corpus(cp)


def _user_layout(small: Path, root: Path, kind: str) -> Path:
    m = json.loads((small / "manifest.json").read_text())
    root.mkdir()
    for k, s in enumerate(m["sequences"][:3]):
        name = f"spk_{k}"
        shutil.copy(small / s["wav"], root / f"{name}.wav")
        iv = read_lab(small / s["lab"])
        iv = [(a, b, "" if p == "sil" else p.upper() + ("1" if p in OPEN_VOWELS else "")) for a, b, p in iv]
        write_textgrid(root / f"{name}.TextGrid", iv)
        fr = load_npz(small / s["frames"])["frames"]
        lm = load_npz(small / s["landmarks"])["landmarks"]
        if kind == "features":
            np.save(root / f"{name}.visual.npy", lm.reshape(len(lm), -1))
        else:
            import imageio.v3 as iio

            (root / name).mkdir()
            for t, im in enumerate(fr):
                iio.imwrite(root / name / f"{t:05d}.png", im)
            np.save(root / f"{name}.landmarks.npy", lm)
    return root


def test_user_corpus_features(small, tmp_path):
    root = _user_layout(small, tmp_path / "u", "features")
    c = load_corpus(root)
    built = load_corpus(small)
    assert c.kind == "user" and c.names == ["spk_0", "spk_1", "spk_2"] and c.aam is None
    for u, b in zip(c, built):
        assert u.labels == b.labels                      # TextGrid + normalisation = .lab
        assert np.allclose(u.mfcc, b.mfcc)
        lm = b.landmarks.reshape(len(b.landmarks), -1)
        assert np.allclose(u.aam, lm - lm.mean(axis=0))
    np.save(root / "spk_1.visual.npy", np.zeros((3, 4)))
    with pytest.raises(ValueError, match=r"spk_1\.visual\.npy: 3 frames"):
        load_corpus(root)


def test_user_corpus_frames_and_errors(small, tmp_path):
    root = _user_layout(small, tmp_path / "u", "frames")
    c = load_corpus(root)
    assert c.aam is not None and (root / "aam.npz").exists()
    for s in c:
        assert s.aam.shape == (s.n_frames, c.aam.n_params) and s.landmarks.shape[0] == s.n_frames
    lm = np.load(root / "spk_2.landmarks.npy")
    np.save(root / "spk_2.landmarks.npy", lm[:-3])
    with pytest.raises(ValueError, match=r"spk_2\.landmarks\.npy"):
        load_corpus(root)
    np.save(root / "spk_2.landmarks.npy", lm)
    y, _ = sf.read(root / "spk_0.wav", dtype="int16")
    sf.write(root / "spk_0.wav", y[::2].copy(), 11025, subtype="PCM_16")
    with pytest.raises(ValueError, match=r"spk_1\.wav: sample rate 22050"):
        load_corpus(root)


def test_sentence_rules(tmp_path):
    p = tmp_path / "s.txt"
    p.write_text("one two three four five\n\nsix seven eight nine ten\nOne two  three four five\n")
    assert load_sentences(p, 2) == ["one two three four five", "six seven eight nine ten"]
    with pytest.raises(ValueError, match="line 4 repeats line 1"):
        load_sentences(p, 3)
    with pytest.raises(ValueError, match="only 3 sentences"):
        load_sentences(p, 5)
    lines = load_sentences(None, 300)
    assert len(set(lines)) == 300 and all(5 <= len(s.split()) <= 12 for s in lines)


def test_worker_features_equal_in_process_features(big, big_corpus):
    """big_corpus was featurised in worker processes; recompute two sequences here."""
    from bayes_talk.base.executor import single_thread as _single_thread_blas
    from bayes_talk.corpus.workers import features_task
    from bayes_talk.features.audio import cmvn

    m = json.loads((big / "manifest.json").read_text())
    for k in (0, 39):
        sm, seq = m["sequences"][k], big_corpus[k]
        task = {"name": sm["name"], "wav": str(big / sm["wav"]), "labels": str(big / sm["lab"]),
                "n_frames": sm["n_frames"], "visual": str(big / sm["frames"]),
                "landmarks": str(big / sm["landmarks"]), "features": None,
                "aam": str(big / m["aam"]["path"])}
        with _single_thread_blas():
            _, arr = features_task(task)
        np.testing.assert_array_equal(cmvn(arr["mfcc"], seq.meta["cmvn"]), seq.mfcc)
        np.testing.assert_array_equal(arr["visual"] - seq.meta["aam_mean"], seq.aam)


def test_aam_separates_bilabial_closure_from_open_vowels(big_corpus):
    """Acceptance: nearest centroid on AAM parameters, train on 30 utterances, test on 10."""
    c = big_corpus
    assert len(c) == 40
    print(f"\ncorpus AAM: {c.aam.n_params} parameters (modes shape/texture/combined "
          f"{c.aam.n_shape_modes}/{c.aam.n_texture_modes}/{c.aam.n_combined})")

    def frames(seqs):
        X, y = [], []
        for s in seqs:
            for t, lab in enumerate(s.labels):
                if lab in BILABIALS or lab in OPEN_VOWELS:
                    X.append(s.aam[t])
                    y.append(lab in BILABIALS)
        return np.array(X), np.array(y)

    Xtr, ytr = frames(c.sequences[:30])
    Xte, yte = frames(c.sequences[30:])
    assert ytr.sum() > 20 and (~ytr).sum() > 20 and yte.sum() > 5 and (~yte).sum() > 5
    mu1, mu0 = Xtr[ytr].mean(axis=0), Xtr[~ytr].mean(axis=0)
    pred = np.linalg.norm(Xte - mu1, axis=1) < np.linalg.norm(Xte - mu0, axis=1)
    acc = float(np.mean(pred == yte))
    print(f"nearest-centroid accuracy {acc:.3f} on {len(yte)} held-out frames")
    assert acc >= 0.90


def test_test_corpus_projected_through_another_aam(small, tmp_path):
    """A separately built corpus (own seed, own AAM) is featurised in another corpus's
    AAM space: same dimension as that AAM, equal to projecting its frames directly, its
    own cache untouched; frames of another size are refused naming both."""
    from bayes_talk.features.aam import AAM

    other = build_corpus(tmp_path / "o", n_utterances=2, seed=3, image_size=96)
    with pytest.raises(ValueError, match=r"96x96.*128x128"):
        load_corpus(other, aam=small / "aam.npz")
    own = build_corpus(tmp_path / "p", n_utterances=2, seed=3)
    proj = load_corpus(own, aam=small / "aam.npz", mean_removal=False)
    aam = AAM.load(small / "aam.npz")
    assert proj.aam_path == small / "aam.npz"
    fr = load_npz(own / "utterances/utt0000.frames.npz")["frames"]
    lm = load_npz(own / "utterances/utt0000.landmarks.npz")["landmarks"]
    T = proj[0].n_frames
    np.testing.assert_allclose(proj[0].aam, aam.project(fr[:T], lm[:T]), atol=1e-10)
    assert not (own / "features.npz").exists()            # its own cache is another file
    native = load_corpus(own, mean_removal=False)
    assert native.aam_path == own / "aam.npz"
    assert not np.allclose(native[0].aam[:, :3], proj[0].aam[:, :3])
