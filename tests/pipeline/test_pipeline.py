"""Command line end to end: corpus build -> train -> synth, and its refusals."""
from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from bayes_talk.app.cli import main
from bayes_talk.base.bundle import ESTIMATOR_DIR, write_bundle_manifest
from bayes_talk.estimators.calibrated import BandCalibrated
from bayes_talk.pipeline import load_trained

SMALL = {"latent_dim": 3, "max_iter": 20, "min_count": 3, "max_frames_per_state": 80, "fallback_frames": 100}


@pytest.fixture(scope="module")
def corpus_dir(shared_built_corpus) -> Path:
    """The session's shared 10-utterance corpus (tests/conftest.py; read-only: copy to change it)."""
    return shared_built_corpus


@pytest.fixture(scope="module")
def model_dir(corpus_dir, tmp_path_factory) -> Path:
    from bayes_talk.pipeline import train

    out = tmp_path_factory.mktemp("pipe") / "model"
    train(corpus_dir, "ssgpdm-vlmm", out, workers=1, **SMALL)
    return out


def _first_utterance(corpus_dir: Path) -> tuple[Path, Path]:
    wavs = sorted((corpus_dir / "utterances").rglob("*.wav"))
    wav = wavs[0]
    return wav, wav.with_suffix(".lab")


def test_synth_writes_trajectory_landmarks_segments_and_video(model_dir, corpus_dir, tmp_path):
    wav, lab = _first_utterance(corpus_dir)
    out = tmp_path / "synth"
    assert main(["synth", str(model_dir), "--audio", str(wav), "--labels", str(lab), "--out", str(out)]) == 0
    traj, var = np.load(out / "trajectory.npy"), np.load(out / "variance.npy")
    lms = np.load(out / "landmarks.npy")
    segs = json.loads((out / "segments.json").read_text())["segments"]
    assert traj.shape == var.shape and traj.shape[0] == lms.shape[0] and np.all(var > 0)
    assert segs[0]["start"] == 0 and segs[-1]["stop"] == traj.shape[0]
    assert all(a["stop"] == b["start"] for a, b in itertools.pairwise(segs))
    video = (out / "face.mp4").read_bytes()
    assert len(video) > 1000 and b"ftyp" in video[:64]
    # a second run into the same directory is refused, nothing is touched
    before = (out / "trajectory.npy").stat().st_mtime_ns
    assert main(["synth", str(model_dir), "--audio", str(wav), "--labels", str(lab), "--out", str(out)]) == 2
    assert (out / "trajectory.npy").stat().st_mtime_ns == before


def test_synth_exports_frames_and_a_landmark_track_that_read_back(model_dir, corpus_dir, tmp_path):
    from bayes_talk.pipeline.exports import FrameExport, read_landmark_track

    wav, lab = _first_utterance(corpus_dir)
    out = tmp_path / "x"
    args = ["synth", str(model_dir), "--audio", str(wav), "--labels", str(lab), "--out", str(out), "--no-video",
            "--posterior", "map", "--algorithm", "predict"]
    assert main(args + ["--export", "json"]) == 0
    fx = FrameExport.read(out / "frames.json")
    traj, lms = np.load(out / "trajectory.npy"), np.load(out / "landmarks.npy")
    np.testing.assert_array_equal(fx.mean, traj)
    np.testing.assert_array_equal(fx.sd, np.sqrt(np.load(out / "variance.npy")))
    with np.load(out / "bands.npz") as b:             # the exact quantiles bands.npz holds
        np.testing.assert_array_equal(fx.q05, b["lower90"])
        np.testing.assert_array_equal(fx.q95, b["upper90"])
    np.testing.assert_allclose(fx.landmarks, lms, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(fx.offset, load_trained(model_dir).offset)
    assert fx.landmark_sd.shape == lms.shape and np.all(fx.landmark_sd >= 0) and fx.landmark_sd.max() > 0
    track, fps = read_landmark_track(out / "landmarks_track.json")
    np.testing.assert_array_equal(track, fx.landmarks)
    assert fps == 25.0 and fx.n_frames == traj.shape[0]
    # another export into the same directory: refused without --force; with it the CSV pair
    # replaces the JSON pair
    assert main(args + ["--export", "csv"]) == 2
    assert main(args + ["--export", "csv", "--force"]) == 0
    assert not (out / "frames.json").exists() and not (out / "landmarks_track.json").exists()
    back = FrameExport.read(out / "frames.csv")
    np.testing.assert_array_equal(back.mean, traj)
    np.testing.assert_array_equal(back.landmarks, fx.landmarks)
    np.testing.assert_array_equal(read_landmark_track(out / "landmarks_track.csv")[0], fx.landmarks)


def test_synth_with_vi_writes_its_diagnostics_and_says_when_it_is_unreliable(model_dir, corpus_dir, tmp_path,
                                                                             monkeypatch, caplog):
    import dataclasses
    import logging

    from bayes_talk.posterior.methods import vi

    fast = dataclasses.make_dataclass("Options", [("steps", int, 60), ("particles", int, 2)], bases=(vi.Options,),
                                      frozen=True)
    monkeypatch.setattr(vi, "Options", fast)  # fast
    wav, lab = _first_utterance(corpus_dir)
    out = tmp_path / "vi"
    with caplog.at_level(logging.WARNING):
        assert main(["synth", str(model_dir), "--audio", str(wav), "--labels", str(lab), "--no-video",
                     "--posterior", "vi", "--draws", "16", "--out", str(out)]) == 0
    diag = json.loads((out / "diagnostics.json").read_text())
    assert diag["method"] == "vi" and diag["n_draws"] == 16
    d = diag["diagnostics"]
    assert {"khat", "psis_ess", "vi_elbo_start", "vi_elbo_end", "vi_steps"} <= set(d) and d["vi_steps"] == 60
    assert diag["converged"] == (d["khat"] <= 0.7)
    if not diag["converged"]:  # where the user looks: the log, naming k̂, without "raise --draws"
        msg = [r.getMessage() for r in caplog.records if "did not converge" in r.getMessage()]
        assert msg and "k̂" in msg[0] and "--draws" not in msg[0]
    with np.load(out / "bands.npz") as b:
        assert np.all(b["lower90"] <= b["upper90"])


def test_synth_post_filters_the_mean_on_request_and_moves_the_bands_with_it(model_dir, corpus_dir, tmp_path):
    """Unfiltered by default (as evaluate scores it); --lowpass-hz 4 is deena2010's filter."""
    from bayes_talk.synthesis.sequential import POST_FILTER_HZ, lowpass

    wav, lab = _first_utterance(corpus_dir)
    args = ["synth", str(model_dir), "--audio", str(wav), "--labels", str(lab), "--no-video", "--posterior", "map"]
    assert main(args + ["--out", str(tmp_path / "f"), "--lowpass-hz", str(POST_FILTER_HZ)]) == 0
    assert main(args + ["--out", str(tmp_path / "r")]) == 0
    f, r = np.load(tmp_path / "f" / "trajectory.npy"), np.load(tmp_path / "r" / "trajectory.npy")
    np.testing.assert_allclose(f, lowpass(r, POST_FILTER_HZ), rtol=1e-10, atol=1e-12)
    assert not np.allclose(f, r)
    with np.load(tmp_path / "f" / "bands.npz") as bf, np.load(tmp_path / "r" / "bands.npz") as br:
        np.testing.assert_allclose(bf["upper90"] - f, br["upper90"] - r, rtol=1e-8, atol=1e-10)
    assert json.loads((tmp_path / "f" / "segments.json").read_text())["post_filter_hz"] == POST_FILTER_HZ
    assert json.loads((tmp_path / "r" / "segments.json").read_text())["post_filter_hz"] is None


def test_synth_with_laplace_posterior_writes_bands_and_diagnostics(model_dir, corpus_dir, tmp_path):
    wav, lab = _first_utterance(corpus_dir)
    out = tmp_path / "post"
    args = ["synth", str(model_dir), "--audio", str(wav), "--labels", str(lab), "--no-video"]
    assert main(args + ["--out", str(out), "--posterior", "laplace", "--draws", "16"]) == 0
    traj, var = np.load(out / "trajectory.npy"), np.load(out / "variance.npy")
    with np.load(out / "bands.npz") as b:
        lo50, hi50, lo90, hi90 = b["lower50"], b["upper50"], b["lower90"], b["upper90"]
    assert lo90.shape == traj.shape and np.all(lo90 <= lo50) and np.all(lo50 <= hi50) and np.all(hi50 <= hi90)
    assert np.mean((lo90 <= traj) & (traj <= hi90)) > 0.95          # the mean sits inside its own band
    diag = json.loads((out / "diagnostics.json").read_text())
    segs = json.loads((out / "segments.json").read_text())["segments"]
    assert diag["method"] == "laplace" and diag["n_draws"] == 16
    assert diag["diagnostics"]["n_segments"] == len(segs) and "map_converged" in diag["diagnostics"]
    assert diag["converged"] == (not diag["problems"])
    # the posterior mean differs from the paper's path; its variance adds the spread of the draws
    ref = tmp_path / "map"
    assert main(args + ["--out", str(ref), "--posterior", "map"]) == 0
    assert not np.allclose(traj, np.load(ref / "trajectory.npy"))
    assert var.shape == traj.shape and np.all(var > 0)
    # the paper's path is one Gaussian per entry: its bands are the exact normal ones
    z95 = 1.6448536269514722
    traj_m, sd_m = np.load(ref / "trajectory.npy"), np.sqrt(np.load(ref / "variance.npy"))
    with np.load(ref / "bands.npz") as b:
        np.testing.assert_allclose(b["lower90"], traj_m - z95 * sd_m, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(b["upper90"], traj_m + z95 * sd_m, rtol=1e-9, atol=1e-12)
    # a sampler for a model that has none is refused by name
    from bayes_talk.pipeline import synth
    with pytest.raises(ValueError, match="posterior must be one of"):
        synth(model_dir, wav, lab, tmp_path / "bad", posterior="gibbs")


def _calibrate(m: Path, cal) -> None:
    """Save the model of directory ``m`` wrapped with ``cal``, as ``train --calibrate-bands`` does."""
    BandCalibrated.wrap(load_trained(m).uncalibrated, cal).save(m / ESTIMATOR_DIR, overwrite=True)
    write_bundle_manifest(m)


def test_synth_applies_the_saved_band_calibration(model_dir, corpus_dir, tmp_path, monkeypatch):
    from bayes_talk.calibration.bands import BandCalibration
    from bayes_talk.pipeline import synth, train
    from bayes_talk.posterior import sampling as posterior
    from bayes_talk.synthesis.result import SynthesisResult

    m = tmp_path / "model"
    shutil.copytree(model_dir, m)
    D = len(json.loads((m / "bayes_talk_model.json").read_text())["aam_offset"])

    def fake_posterior(model, mfcc, labels, method, n_draws, seed, **kw):   # the wiring is under test
        rng = np.random.default_rng(seed)
        shape = (1, n_draws, mfcc.shape[0], D)
        return SynthesisResult(method, None, rng.normal(size=shape), rng.uniform(0.1, 1, size=shape), seed=seed)

    monkeypatch.setattr(posterior, "sample_synthesis", fake_posterior)
    scale = np.linspace(0.5, 3.0, D)
    _calibrate(m, BandCalibration(scale, "laplace"))
    assert load_trained(m).calibration is not None and load_trained(model_dir).calibration is None
    assert isinstance(load_trained(m).model, BandCalibrated)
    wav, lab = _first_utterance(corpus_dir)
    args = ["synth", str(m), "--audio", str(wav), "--labels", str(lab), "--no-video", "--posterior", "laplace",
            "--draws", "16"]
    assert main(args + ["--out", str(tmp_path / "cal")]) == 0
    assert main(args + ["--out", str(tmp_path / "raw"), "--raw-bands"]) == 0
    t_cal, t_raw = np.load(tmp_path / "cal" / "trajectory.npy"), np.load(tmp_path / "raw" / "trajectory.npy")
    np.testing.assert_allclose(t_cal, t_raw, atol=1e-10)                 # the mean is unchanged
    np.testing.assert_allclose(np.load(tmp_path / "cal" / "variance.npy"),
                               np.load(tmp_path / "raw" / "variance.npy") * scale**2, rtol=1e-8)
    with np.load(tmp_path / "cal" / "bands.npz") as c, np.load(tmp_path / "raw" / "bands.npz") as r:
        np.testing.assert_allclose(c["upper90"] - t_cal, scale * (r["upper90"] - t_raw), rtol=1e-5, atol=1e-8)
    full = json.loads((tmp_path / "cal" / "diagnostics.json").read_text())
    diag = full["diagnostics"]
    assert diag["band_calibration"]["scale_max"] == pytest.approx(3.0)
    assert "band-calibrated" in full["trajectory_holds"] and full["mean_shrinkage"] is None   # no stage 0 here
    raw = json.loads((tmp_path / "raw" / "diagnostics.json").read_text())
    assert "band_calibration" not in raw["diagnostics"] and "no band calibration" in raw["trajectory_holds"]
    # stage 3, the pool with the constant band: variance (1 − w) s² v + w v_c, the mean unchanged
    w, cv = np.linspace(0.0, 1.0, D), np.full(D, 0.7)
    _calibrate(m, BandCalibration(scale, "laplace", control_var=cv, pool_weight=w))
    assert main(args + ["--out", str(tmp_path / "pool")]) == 0
    np.testing.assert_allclose(np.load(tmp_path / "pool" / "trajectory.npy"), t_raw, atol=1e-10)
    np.testing.assert_allclose(np.load(tmp_path / "pool" / "variance.npy"),
                               (1 - w) * np.load(tmp_path / "raw" / "variance.npy") * scale**2 + w * cv, rtol=1e-8)
    assert json.loads((tmp_path / "pool" / "diagnostics.json").read_text())["pool_weight"] == pytest.approx(list(w))
    # a calibration of another model's size is refused by name
    _calibrate(m, BandCalibration(np.ones(D + 1), "laplace"))
    with pytest.raises(ValueError, match=f"{D + 1} factors but the prediction has {D}"):
        synth(m, wav, lab, tmp_path / "bad", posterior="laplace", n_draws=16, video=False)
    with pytest.raises(ValueError, match="calibrate_bands: expected a fraction"):
        train(corpus_dir, "sgplvm", tmp_path / "sg", calibrate_bands=0.2)


def test_synth_writes_posterior_netcdf_bands_plot_and_uncertainty_video(model_dir, corpus_dir, tmp_path, capsys):
    import arviz as az

    from bayes_talk.corpus import load_corpus

    wav, lab = _first_utterance(corpus_dir)
    seq = next(s for s in load_corpus(corpus_dir).sequences if s.name == wav.stem)
    truth = tmp_path / "truth.npy"
    np.save(truth, seq.aam)
    out = tmp_path / "u"
    args = ["synth", str(model_dir), "--audio", str(wav), "--labels", str(lab), "--draws", "8"]
    assert main(args + ["--out", str(out), "--truth", str(truth)]) == 0
    idata = az.from_netcdf(out / "posterior.nc")
    summ = az.summary(idata)
    T, D = seq.aam.shape
    assert len(summ) == 2 * T * D + T * 3 and np.isfinite(summ["mean"]).all()
    assert idata.posterior["latents"].shape[1:] == (8, T, 3)
    np.testing.assert_array_equal(idata.observed_data["aam"].values, seq.aam)
    assert idata.posterior.attrs["bayes_talk_method"] == "laplace"
    # the bands written are those of the stored mixture (rebuilt here from posterior.nc)
    from bayes_talk.synthesis.result import SynthesisResult

    res = SynthesisResult("laplace", idata.posterior["latents"].values, idata.posterior["aam_mean"].values,
                          idata.posterior["aam_gp_var"].values)
    with np.load(out / "bands.npz") as b:
        lo, hi = res.interval(0.9)
        np.testing.assert_allclose(b["lower90"], lo, rtol=1e-12)
        np.testing.assert_allclose(b["upper90"], hi, rtol=1e-12)
    np.testing.assert_allclose(np.load(out / "trajectory.npy"), res.mean, rtol=1e-12)
    assert (out / "bands.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import imageio.v3 as iio

    frame = iio.imread(out / "uncertainty.mp4", index=T // 2)[..., 0]
    face = iio.imread(out / "face.mp4", index=T // 2)[..., 0]
    assert frame.shape[1] >= 2 * face.shape[1] and frame[:, face.shape[1] + 2:].max() > 20  # the sd panel
    # a truth of the wrong shape is refused before anything is synthesised
    bad = tmp_path / "bad.npy"
    np.save(bad, seq.aam[:-1])
    assert main(args + ["--out", str(tmp_path / "v"), "--truth", str(bad)]) == 2
    assert f"expected AAM parameters of shape ({T}, {D})" in capsys.readouterr().err
    assert not (tmp_path / "v").exists()


def test_train_refuses_a_non_empty_directory(corpus_dir, tmp_path):
    (tmp_path / "mine.txt").write_text("keep me")
    assert main(["train", str(corpus_dir), "--out", str(tmp_path)]) == 2
    assert (tmp_path / "mine.txt").read_text() == "keep me"


def test_labels_that_disagree_with_the_audio_are_refused(model_dir, corpus_dir, tmp_path, capsys):
    wav, lab = _first_utterance(corpus_dir)
    short = tmp_path / "short.lab"
    lines = lab.read_text().strip().splitlines()
    short.write_text("\n".join(lines[: len(lines) // 2]) + "\n")
    assert main(["synth", str(model_dir), "--audio", str(wav), "--labels", str(short),
                 "--out", str(tmp_path / "o")]) == 2
    assert "labels end at" in capsys.readouterr().err


def test_a_model_directory_of_the_layout_before_issue_26_loads(model_dir, tmp_path):
    """Trained before issue 26: the switching model's ``model.json`` + ``arrays.npz`` at the
    top of the directory and ``band_calibration.json`` beside them; ``load_trained`` reads it
    as the band-calibrated wrapper, with the same arrays."""
    from bayes_talk.base.files import write_model_files
    from bayes_talk.calibration.bands import BandCalibration

    old = tmp_path / "m"
    shutil.copytree(model_dir, old)
    new = load_trained(model_dir).model
    meta, arrays = new.state()
    shutil.rmtree(old / ESTIMATOR_DIR)
    write_model_files(old / "model.json", old / "arrays.npz", meta, arrays)
    cal = BandCalibration(np.linspace(0.5, 2.0, len(load_trained(model_dir).offset)), "laplace")
    cal.save(old)
    write_bundle_manifest(old)
    tm = load_trained(old)
    assert isinstance(tm.model, BandCalibrated) and tm.calibration.to_dict() == cal.to_dict()
    for k, a in tm.uncalibrated.state()[1].items():
        np.testing.assert_array_equal(a, arrays[k])


def test_model_directory_of_another_version_is_refused(model_dir, tmp_path):
    other = tmp_path / "m"
    shutil.copytree(model_dir, other)
    desc = json.loads((other / "bayes_talk_model.json").read_text())
    desc["version"] = 7
    (other / "bayes_talk_model.json").write_text(json.dumps(desc))
    with pytest.raises(ValueError, match="version expected 1, found 7"):
        load_trained(other)
    (other / ESTIMATOR_DIR / "arrays.npz").write_bytes((model_dir / ESTIMATOR_DIR / "arrays.npz").read_bytes()[:500])
    shutil.copyfile(model_dir / "bayes_talk_model.json", other / "bayes_talk_model.json")   # the descriptor intact
    with pytest.raises(ValueError, match="arrays.npz.*(does not belong|truncated or corrupt)"):
        load_trained(other)


def test_the_loaded_model_names_its_training_corpus(model_dir, corpus_dir, tmp_path, monkeypatch):
    """``TrainedModel.training_corpus``: the directory as ``train`` recorded it, relative to where
    it ran; one not here is a FileNotFoundError naming the descriptor and the path."""
    assert load_trained(model_dir).training_corpus() == Path(str(corpus_dir))
    monkeypatch.chdir(tmp_path)          # recorded absolute here; a relative record resolves from the cwd
    (tmp_path / "c").symlink_to(corpus_dir)
    tm = load_trained(model_dir)
    tm.corpus = "c"
    assert tm.training_corpus() == Path("c")
    tm.corpus = "moved/away"
    with pytest.raises(FileNotFoundError, match=r"bayes_talk_model\.json: the training corpus 'moved/away' is not"):
        tm.training_corpus()


class _Recorder:
    """Stands in for a model: records what it was trained on (no training cost)."""

    def __init__(self):
        self.names: list[str] = []

    def save(self, path, overwrite=False):
        Path(path).mkdir(parents=True, exist_ok=True)


def test_train_holdout_excludes_the_named_utterances(corpus_dir, tmp_path, monkeypatch):
    from bayes_talk import pipeline

    seen = []

    def fake_fit(model, train, workers=2, **kw):
        rec = _Recorder()
        rec.names = [s.name for s in train]
        seen.append(rec.names)
        return rec

    from bayes_talk.pipeline import training

    monkeypatch.setattr(training, "fit_model", fake_fit)
    n = len(json.loads((corpus_dir / "manifest.json").read_text())["sequences"])
    lst = tmp_path / "held.txt"
    lst.write_text("utt0003\n# a comment\n\nutt0007\n")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "c").symlink_to(corpus_dir)
    monkeypatch.chdir(tmp_path)   # the corpus is recorded as given: no machine's directory in the model
    out = pipeline.train("data/c", "ssgpdm-vlmm", tmp_path / "m1", workers=1, holdout_list=lst)
    desc = json.loads((out / "bayes_talk_model.json").read_text())
    assert desc["held_out"] == ["utt0003", "utt0007"] and desc["n_train"] == n - 2
    assert desc["corpus"] == "data/c"
    assert len(seen[-1]) == n - 2 and not {"utt0003", "utt0007"} & set(seen[-1])
    # --holdout N: the last N, from the command line
    assert main(["train", str(corpus_dir), "--out", str(tmp_path / "m2"), "--holdout", "3",
                 "--model", "ssgpdm-vlmm", "--no-calibrate-bands"]) == 0
    desc = json.loads((tmp_path / "m2" / "bayes_talk_model.json").read_text())
    assert desc["held_out"] == [f"utt{i:04d}" for i in range(n - 3, n)] and seen[-1][-1] == f"utt{n - 4:04d}"
    # bad lists are refused naming the file and the problem
    lst.write_text("utt0003\nnope\n")
    with pytest.raises(ValueError, match=r"held\.txt: utterance\(s\) \['nope'\] are not in"):
        pipeline.train(corpus_dir, "ssgpdm-vlmm", tmp_path / "m3", workers=1, holdout_list=lst)
    with pytest.raises(ValueError, match=rf"holdout: expected an integer in \[0, {n - 1}\]"):
        pipeline.train(corpus_dir, "ssgpdm-vlmm", tmp_path / "m4", workers=1, holdout=n)


# --- issue 13: synth from a transcript, or from audio alone ---------------------------------
def test_synth_without_labels_aligns_the_text_or_uses_the_recogniser(model_dir, corpus_dir, tmp_path, caplog):
    import logging

    from bayes_talk.data.labels import read_labels

    wav, lab = _first_utterance(corpus_dir)
    manifest = json.loads((corpus_dir / "manifest.json").read_text())
    text = next(s["text"] for s in manifest["sequences"] if s["wav"].endswith(wav.name))
    args = ["synth", str(model_dir), "--audio", str(wav), "--no-video"]
    assert main(args + ["--text", text, "--out", str(tmp_path / "text")]) == 0
    aligned = read_labels(tmp_path / "text" / "labels.lab")
    assert [p for *_, p in aligned] == [p for *_, p in read_labels(lab)]    # espeak's own G2P
    with caplog.at_level(logging.WARNING):
        assert main(args + ["--out", str(tmp_path / "rec")]) == 0
    assert "phone recogniser" in caplog.text
    traj = np.load(tmp_path / "rec" / "trajectory.npy")
    assert traj.shape == np.load(tmp_path / "text" / "trajectory.npy").shape and np.all(np.isfinite(traj))
    assert read_labels(tmp_path / "rec" / "labels.lab")[-1][1] == pytest.approx(read_labels(lab)[-1][1])
    # labels and a transcript together are refused, nothing written
    assert main(args + ["--labels", str(lab), "--text", text, "--out", str(tmp_path / "both")]) == 2
    assert not (tmp_path / "both").exists()


def test_train_defaults_to_right_context_states_with_the_calibration(monkeypatch):
    import bayes_talk.pipeline as pl
    from bayes_talk.app import cli

    calls = []
    models = []
    monkeypatch.setattr(pl, "train", lambda corpus, kind, out, **kw: calls.append((kind, kw["calibrate_bands"]))
                        or models.append(kw["calibrated_model"]) or out)
    assert cli.main(["train", "c", "--out", "o"]) == 0
    assert cli.main(["train", "c", "--out", "o", "--no-calibrate-bands"]) == 0
    assert cli.main(["train", "c", "--out", "o", "--calibrate-bands", "0.3", "--model", "ssgpdm-vlmm"]) == 0
    assert cli.main(["train", "c", "--out", "o", "--model", "sgplvm"]) == 0
    assert calls == [(pl.DEFAULT_MODEL, pl.DEFAULT_CALIBRATION), (pl.DEFAULT_MODEL, None), ("ssgpdm-vlmm", 0.3),
                     ("sgplvm", None)]
    assert pl.DEFAULT_MODEL == "ssgpdm-phone-ctx-mean"
    assert cli.main(["train", "c", "--out", "o", "--calibrate-bands", "--no-calibrate-bands"]) == 2
    assert cli.main(["train", "c", "--out", "o", "--calibrated-model", "refit"]) == 0
    assert cli.main(["train", "c", "--out", "o", "--calibrated-model", "holdout"]) == 0
    assert models == [pl.DEFAULT_CALIBRATED_MODEL] * 4 + ["refit", "holdout"]
    with pytest.raises(SystemExit):
        cli.main(["train", "c", "--out", "o", "--calibrated-model", "both"])
    from bayes_talk.pipeline.training import train as real_train  # pl.train is the stub above

    with pytest.raises(ValueError, match="calibrated_model: expected one of holdout, refit, cv, found 'both'"):
        real_train("c", pl.DEFAULT_MODEL, "o", calibrate_bands=0.2, calibrated_model="both")


def test_synth_of_room_noise_then_speech_with_recognised_labels_converges(model_dir, corpus_dir, tmp_path):
    """A recording like a real one: 7 s of room noise (brown noise at about −45 dBFS, a 50 Hz
    hum, a door's click) before two sentences, labelled by the recogniser, 300+ frames (the
    window sweeps of the joint MAP): synth finishes, its joint MAP converges, and what
    ``diagnostics.json`` says agrees with it (no MAP problem listed)."""
    import soundfile as sf

    wavs = sorted((corpus_dir / "utterances").rglob("*.wav"))[:2]
    speech = [sf.read(w, dtype="float64") for w in wavs]
    sr = speech[0][1]
    rng = np.random.default_rng(7)
    n = int(7.0 * sr)
    brown = np.cumsum(rng.standard_normal(n))
    brown = (brown - np.convolve(brown, np.ones(2001) / 2001, mode="same")) * 10 ** (-45 / 20) / brown.std()
    hum = 10 ** (-50 / 20) * np.sin(2 * np.pi * 50 * np.arange(n) / sr)
    noise = brown + hum
    noise[int(3.1 * sr):int(3.1 * sr) + 200] += 0.3 * rng.standard_normal(200) * np.exp(-np.arange(200) / 40)
    y = np.concatenate([noise] + [x for x, _ in speech])
    wav = tmp_path / "room.wav"
    sf.write(wav, np.clip(y, -1, 1), sr, subtype="PCM_16")
    out = tmp_path / "out"
    assert main(["synth", str(model_dir), "--audio", str(wav), "--no-video", "--out", str(out)]) == 0
    diag = json.loads((out / "diagnostics.json").read_text())
    assert diag["diagnostics"]["dim"] // 3 > 250                       # the windowed path (MAP_WINDOW[0])
    assert diag["diagnostics"]["map_converged"], diag["problems"]
    assert not [p for p in diag["problems"] if "MAP did not converge" in p]
    assert np.all(np.isfinite(np.load(out / "trajectory.npy")))
