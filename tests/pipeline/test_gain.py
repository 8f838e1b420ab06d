"""A quieter recording gives the same face: the front end scales every recording to the
model's active-speech level before its MFCCs (bayes_talk.features.audio.normalise_level),
so the same held-out sentence at -6 and -20 dB is synthesised as at its own level; models
that do not record the setting are fed their features as before."""
from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from bayes_talk.app.cli import main
from bayes_talk.features.audio import AudioSettings
from bayes_talk.features.frontend import FLOOR_DBFS, LEVEL_DBFS
from bayes_talk.pipeline import load_trained, read_utterance
from bayes_talk.pipeline.front_end import front_end

SMALL = {"latent_dim": 3, "max_iter": 20, "min_frames_per_state": 10, "max_frames_per_state": 60, "fallback_frames": 80}
#: the largest move of the trajectory allowed for a gain change (of its standard deviation)
BOUND = 0.02


@pytest.fixture(scope="module")
def model_dir(shared_built_corpus, tmp_path_factory) -> Path:
    """The default family, small, trained on the shared corpus but its last utterance."""
    from bayes_talk.pipeline import DEFAULT_MODEL, train

    out = tmp_path_factory.mktemp("gain") / "model"
    train(shared_built_corpus, DEFAULT_MODEL, out, workers=1, alignment=False, holdout=1, **SMALL)
    return out


def _moved(x: np.ndarray, ref: np.ndarray) -> float:
    """RMS over frames of ``x - ref``, over ``ref``'s standard deviation, averaged over the
    columns (AAM parameters or MFCCs)."""
    return float(np.mean(np.sqrt(np.mean((x - ref) ** 2, axis=0)) / ref.std(axis=0)))


def test_a_held_out_utterance_6_and_20_db_quieter_gives_the_same_face(model_dir, shared_built_corpus, tmp_path):
    """The same recording scaled by -6 and -20 dB (float samples): the synthesised trajectory
    moves by at most ``BOUND`` of its sd; fed the features without the level normalisation
    (a model trained before it), the same model's trajectory moves by more. Rounded to 16
    bits, the quieter recordings carry 6 and 20 dB more quantisation noise relative to the
    speech, which the normalisation raises with it: the model's features then move by a few
    thousandths of their sd (what they move by is what the synthesis sees; whether that moves
    the trajectory depends on how near the synthesis is to switching between modes, measured
    in docs/audio.md)."""
    desc = json.loads((model_dir / "bayes_talk_model.json").read_text())
    assert desc["audio"]["level_dbfs"] == LEVEL_DBFS
    (held,) = desc["held_out"]
    wav = next((shared_built_corpus / "utterances").rglob(f"{held}.wav"))
    lab = wav.with_suffix(".lab")
    x, sr = sf.read(wav, dtype="float64")
    trajs, wavs = {}, {}
    for db in (0, -6, -20):
        wavs[db] = tmp_path / f"minus{-db}.wav"
        sf.write(wavs[db], x * 10 ** (db / 20), sr, subtype="DOUBLE")
        out = tmp_path / f"out{-db}"
        assert main(["-q", "synth", str(model_dir), "--audio", str(wavs[db]), "--labels", str(lab), "--out", str(out),
                     "--no-video"]) == 0
        trajs[db] = np.load(out / "trajectory.npy")
    for db in (-6, -20):
        assert _moved(trajs[db], trajs[0]) <= BOUND, db
    tm = load_trained(model_dir)
    raw_front = front_end(dataclasses.replace(tm.audio, level_dbfs=None))
    raw = {db: tm.model.predict_dist(read_utterance(wavs[db], lab, tm.fps, **raw_front), posterior="laplace",
                                     seed=0).mean for db in (0, -20)}
    assert _moved(raw[-20], raw[0]) > 2 * BOUND
    # 16-bit quieter recordings: the model's features (what the synthesis sees) barely move
    front = front_end(tm.audio)
    pcm = np.round(x * 32767).astype(np.int16)
    feats = {}
    for db in (0, -6, -20):
        p = tmp_path / f"pcm{-db}.wav"
        sf.write(p, np.round(pcm * 10 ** (db / 20)).astype(np.int16), sr, subtype="PCM_16")
        feats[db] = read_utterance(p, lab, tm.fps, **front).mfcc
    assert _moved(feats[-6], feats[0]) < 0.002 and _moved(feats[-20], feats[0]) < 0.005
    raw_feats = {db: read_utterance(tmp_path / f"pcm{-db}.wav", lab, tm.fps, **raw_front).mfcc for db in (0, -20)}
    assert _moved(raw_feats[-20], raw_feats[0]) > 0.1


def test_models_without_the_setting_read_as_before():
    """A bundle that does not record the level (or the floor) had none when it was trained."""
    d = AudioSettings(sample_rate=22050).to_dict()
    assert d["level_dbfs"] == LEVEL_DBFS and AudioSettings.from_dict(d) == AudioSettings(sample_rate=22050)
    del d["level_dbfs"]
    old = AudioSettings.from_dict(d)
    assert old.level_dbfs is None and old.floor_dbfs == FLOOR_DBFS
    assert front_end(old)["level_dbfs"] is None
    oldest = AudioSettings.from_dict(None)
    assert (oldest.cmvn, oldest.fmax, oldest.floor_dbfs, oldest.level_dbfs) == ("off", None, None, None)


def test_the_feature_cache_is_keyed_by_the_level(shared_built_corpus, tmp_path):
    from bayes_talk.corpus import load_corpus

    corpus = tmp_path / "c"
    shutil.copytree(shared_built_corpus, corpus)
    new = load_corpus(corpus, n_workers=1)
    off = load_corpus(corpus, n_workers=1, level_dbfs=None)        # not the cached features of -20 dBFS
    assert all(not np.allclose(a.mfcc, b.mfcc) for a, b in zip(new.sequences, off.sequences))
    direct = load_corpus(corpus, n_workers=1, level_dbfs=None, cache=False)
    assert all(np.array_equal(a.mfcc, b.mfcc) for a, b in zip(off.sequences, direct.sequences))
    again = load_corpus(corpus, n_workers=1)
    assert all(np.array_equal(a.mfcc, b.mfcc) for a, b in zip(new.sequences, again.sequences))
