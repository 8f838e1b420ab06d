"""Issue 12's table, one test per row: every bad input ends in a named error or a
documented, logged behaviour -- never a traceback, never exit 0 with a wrong result --
and nothing outside the output directory changes."""
from __future__ import annotations

import json
import logging
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from bayes_talk.app.cli import main
from bayes_talk.base.bundle import BundleError
from bayes_talk.data.labels import read_labels
from bayes_talk.features.audio import cmvn, downmix, resample
from bayes_talk.features.mfcc import FMAX_HZ
from bayes_talk.pipeline import load_trained, read_utterance

SMALL = {"latent_dim": 3, "max_iter": 20, "min_frames_per_state": 10, "max_frames_per_state": 60, "fallback_frames": 80}


@pytest.fixture(scope="module")
def corpus_dir(shared_built_corpus) -> Path:
    """The session's shared 10-utterance corpus (tests/conftest.py; read-only: copy to change it)."""
    return shared_built_corpus


@pytest.fixture(scope="module")
def model_dir(corpus_dir, tmp_path_factory) -> Path:
    from bayes_talk.pipeline import train

    out = tmp_path_factory.mktemp("bad") / "model"
    # no aligner: every synth below is given its labels (the aligner is tested in test_alignment)
    train(corpus_dir, "ssgpdm-phone", out, workers=1, alignment=False, **SMALL)
    return out


def _utt(corpus_dir: Path, i: int = 0) -> tuple[Path, Path]:
    wav = sorted((corpus_dir / "utterances").glob("*.wav"))[i]
    return wav, wav.with_suffix(".lab")


def _tree(d: Path, skip: Path | None = None) -> dict[str, bytes]:
    """Every file under ``d`` (except under ``skip``) with its bytes."""
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*"))
            if p.is_file() and (skip is None or skip not in p.parents)}


def _feature_ratio(wav: Path, lab: Path, variant: Path, silent: Path) -> float:
    """RMS change of the model's features from ``variant`` over that from silence."""
    kw = {"sample_rate": 22050, "cmvn": "mean", "fmax": FMAX_HZ}
    ref = read_utterance(wav, lab, **kw).mfcc
    a, s = read_utterance(variant, lab, **kw).mfcc, read_utterance(silent, lab, **kw).mfcc
    T = min(len(ref), len(a), len(s))
    return float(np.sqrt(np.mean((a[:T] - ref[:T]) ** 2)) / np.sqrt(np.mean((s[:T] - ref[:T]) ** 2)))


# --- row 1: other sample rates ----------------------------------------------------------

def test_other_sample_rates_are_resampled_to_the_models_and_logged(corpus_dir, model_dir, tmp_path, caplog):
    wav, lab = _utt(corpus_dir)
    y, sr = sf.read(wav, dtype="float64")
    silent = tmp_path / "silent.wav"
    sf.write(silent, np.zeros_like(y), sr)
    desc = json.loads((model_dir / "bayes_talk_model.json").read_text())
    assert desc["audio"]["sample_rate"] == sr and desc["audio"]["cmvn"] == "mean"
    assert len(desc["audio"]["feature_statistics"]["mean"]) == 20
    for rate in (16000, 44100):
        p = tmp_path / f"r{rate}.wav"
        sf.write(p, resample(y, sr, rate), rate, subtype="FLOAT")
        with caplog.at_level(logging.WARNING, logger="bayes_talk.features.audio"):
            caplog.clear()
            assert _feature_ratio(wav, lab, p, silent) < 0.1
        assert any(f"{rate} Hz audio resampled to {sr} Hz" in r.getMessage() for r in caplog.records)
    _resampled_synthesis_barely_moves(model_dir, wav, lab, tmp_path / "r44100.wav", silent, tmp_path)


def _resampled_synthesis_barely_moves(model_dir: Path, wav: Path, lab: Path, resampled: Path, silent: Path,
                                      tmp_path: Path) -> None:
    """End to end: the synthesised trajectory from resampled audio moves < 10 % of what
    silence moves it."""
    outs = {}
    for name, path in (("orig", wav), ("resampled", resampled), ("silent", silent)):
        out = tmp_path / f"o_{name}"
        assert main(["-q", "synth", str(model_dir), "--audio", str(path), "--labels", str(lab),
                     "--out", str(out), "--no-video", "--algorithm", "predict"]) == 0
        outs[name] = np.load(out / "trajectory.npy")
    T = min(len(v) for v in outs.values())
    d = {k: np.sqrt(np.mean((outs[k][:T] - outs["orig"][:T]) ** 2)) for k in ("resampled", "silent")}
    assert d["resampled"] < 0.1 * d["silent"]


def test_resampled_audio_barely_moves_the_default_models_audio_context(corpus_dir, tmp_path):
    """The same robustness with the default family's audio context window (±2 frames,
    registry.FAMILY_DEFAULTS): the spliced, PCA-reduced MFCCs must not amplify the
    resampling's small feature change."""
    from bayes_talk.pipeline import DEFAULT_MODEL, train

    model = tmp_path / "model"
    train(corpus_dir, DEFAULT_MODEL, model, workers=1, alignment=False, **SMALL)   # synth is given the labels
    assert load_trained(model).uncalibrated.config.audio_context == 2
    wav, lab = _utt(corpus_dir)
    y, sr = sf.read(wav, dtype="float64")
    silent, r44 = tmp_path / "silent.wav", tmp_path / "r44100.wav"
    sf.write(silent, np.zeros_like(y), sr)
    sf.write(r44, resample(y, sr, 44100), 44100, subtype="FLOAT")
    _resampled_synthesis_barely_moves(model, wav, lab, r44, silent, tmp_path)


# --- row 2: gain and a one-sided stereo recording ---------------------------------------

def test_gain_and_one_silent_stereo_channel_do_not_move_the_features(corpus_dir, tmp_path):
    wav, lab = _utt(corpus_dir, 1)
    y, sr = sf.read(wav, dtype="float64")
    silent = tmp_path / "silent.wav"
    sf.write(silent, np.zeros_like(y), sr)
    for name, data in (("minus6", y * 10 ** (-6 / 20)), ("plus6", y * 10 ** (6 / 20)),
                       ("stereo", np.stack([np.zeros_like(y), y], axis=1))):
        p = tmp_path / f"{name}.wav"
        sf.write(p, data, sr, subtype="FLOAT")
        assert _feature_ratio(wav, lab, p, silent) < 0.1, name
    # without normalisation the gain change moves c0 (what CMN removes)
    raw = read_utterance(wav, lab, cmvn="off").mfcc
    quiet = read_utterance(tmp_path / "minus6.wav", lab, cmvn="off").mfcc
    assert np.abs(raw[:, 0] - quiet[:, 0]).mean() > 1.0


def test_downmix_rule():
    rng = np.random.default_rng(0)
    x = rng.standard_normal(4000)
    # one silent channel: the signal, not half of it
    assert np.allclose(downmix(np.stack([x, np.zeros_like(x)], 1)), x)
    # phase-inverted channels are not cancelled: the louder channel is kept
    assert np.allclose(downmix(np.stack([x, -0.9 * x], 1)), x)
    # correlated channels (dual mono + noise) are averaged
    n = 0.1 * rng.standard_normal((4000, 2))
    both = np.stack([x, x], 1) + n
    assert np.allclose(downmix(both), both.mean(axis=1))
    with pytest.raises(ValueError, match="cmvn"):
        cmvn(np.zeros((3, 2)), "median")
    z = cmvn(rng.standard_normal((50, 3)) * 4 + 2, "mean+var")
    assert np.allclose(z.mean(0), 0) and np.allclose(z.std(0), 1)


# --- rows 3 and 4: TextGrids -------------------------------------------------------------

def _tg(path: Path, tiers: list[tuple[str, list]]) -> Path:
    """A long-format TextGrid with the given interval tiers."""
    xmax = max(e for _, iv in tiers for _, e, _ in iv) if any(iv for _, iv in tiers) else 1.0
    lines = ['File type = "ooTextFile"', 'Object class = "TextGrid"', "", "xmin = 0", f"xmax = {xmax}",
             "tiers? <exists>", f"size = {len(tiers)}", "item []:"]
    for k, (name, iv) in enumerate(tiers, 1):
        lines += [f"    item [{k}]:", '        class = "IntervalTier"', f'        name = "{name}"',
                  "        xmin = 0", f"        xmax = {xmax}", f"        intervals: size = {len(iv)}"]
        for j, (s, e, t) in enumerate(iv, 1):
            lines += [f"        intervals [{j}]:", f"            xmin = {s}", f"            xmax = {e}",
                      f'            text = "{t}"']
    path.write_text("\n".join(lines) + "\n")
    return path


def test_textgrid_with_an_empty_phones_tier_is_a_named_error(corpus_dir, model_dir, tmp_path, capsys):
    wav, _lab = _utt(corpus_dir)
    tg = _tg(tmp_path / "x.TextGrid", [("words", [(0.0, 1.0, "hello")]), ("phones", [])])
    with pytest.raises(ValueError, match=r"tier 'phones' has no intervals"):
        read_labels(tg)
    before = _tree(tmp_path)
    assert main(["synth", str(model_dir), "--audio", str(wav), "--labels", str(tg),
                 "--out", str(tmp_path / "o"), "--no-video"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bayes-talk: error:") and "has no intervals" in err and "Traceback" not in err
    assert _tree(tmp_path) == before


def test_textgrid_tier_is_found_named_and_selectable(corpus_dir, model_dir, tmp_path, capsys):
    wav, lab = _utt(corpus_dir)
    phones = read_labels(lab)
    words = [(0.0, phones[-1][1], "the")]
    # a words tier first, phone tier not named "phones": the phone tier is found
    tg = _tg(tmp_path / "a.TextGrid", [("words", words), ("segments", phones)])
    assert read_labels(tg) == phones
    # asked for the words tier: the error names the tier read and the option
    with pytest.raises(ValueError, match=r"unknown phone label 'the'.*tier 'words'.*--tier"):
        read_labels(tg, tier="words")
    with pytest.raises(ValueError, match=r"no IntervalTier named 'phonez'; found \['segments', 'words'\]"):
        read_labels(tg, tier="phonez")
    before = _tree(tmp_path)
    args = ["synth", str(model_dir), "--audio", str(wav), "--labels", str(tg), "--no-video"]
    assert main(args + ["--out", str(tmp_path / "o1"), "--tier", "words"]) == 2
    assert "tier 'words'" in capsys.readouterr().err
    assert _tree(tmp_path) == before
    assert main(args + ["--out", str(tmp_path / "o2"), "--tier", "segments"]) == 0


# --- rows 5, 6, 7: model bundles ----------------------------------------------------------

def test_arrays_from_another_model_are_refused_naming_the_file(model_dir, tmp_path):
    other = tmp_path / "m"
    shutil.copytree(model_dir, other)
    npz = other / "estimator" / "arrays.npz"
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    k = next(k for k, v in arrays.items() if v.dtype.kind == "f" and v.size)
    arrays[k] = arrays[k] * 1.5 + 0.1               # same names and shapes: loads without the check
    np.savez(npz, **arrays)
    with pytest.raises(BundleError, match=r"arrays\.npz: does not belong to this model"):
        load_trained(other)


def test_aam_from_another_model_is_refused_naming_the_file(model_dir, corpus_dir, tmp_path):
    from bayes_talk.corpus import load_npz
    from bayes_talk.features.aam import AAM

    frames = load_npz(min((corpus_dir / "utterances").glob("*.frames.npz")))["frames"][:30]
    lms = load_npz(min((corpus_dir / "utterances").glob("*.landmarks.npz")))["landmarks"][:30]
    foreign = AAM.fit(frames, lms, variance=0.8)
    other = tmp_path / "m"
    shutil.copytree(model_dir, other)
    foreign.save(other / "aam.npz")
    with pytest.raises(BundleError, match=r"aam\.(npz|json): does not belong to this model"):
        load_trained(other)
    # a model saved before bundles were hashed: the AAM's size is still checked by name
    (other / "bundle_manifest.json").unlink()
    desc = json.loads((other / "bayes_talk_model.json").read_text())
    desc.pop("bundle_manifest")
    (other / "bayes_talk_model.json").write_text(json.dumps(desc))
    with pytest.raises(BundleError, match=r"aam\.npz: an AAM with \d+ parameters.*does not belong"):
        load_trained(other)


def test_train_force_interrupted_while_saving_refuses_to_load(model_dir, corpus_dir, tmp_path, monkeypatch):
    import bayes_talk.base.bundle
    from bayes_talk.pipeline import training

    out = tmp_path / "m"
    shutil.copytree(model_dir, out)
    trained = load_trained(model_dir).model
    monkeypatch.setattr(training, "fit_model", lambda model, train, workers=2, **kw: trained)

    def interrupted(directory):
        raise KeyboardInterrupt

    monkeypatch.setattr(bayes_talk.base.bundle, "write_bundle_manifest", interrupted)
    before = _tree(tmp_path, skip=out)
    corpus_before = _tree(corpus_dir)
    assert main(["train", str(corpus_dir), "--model", "ssgpdm-phone", "--out", str(out), "--force",
                 "--no-calibrate-bands"]) == 130
    with pytest.raises(BundleError, match=r"bundle_manifest\.json is missing: the model's save was interrupted"):
        load_trained(out)
    assert _tree(tmp_path, skip=out) == before and _tree(corpus_dir) == corpus_before


# --- row 8: synth --force replaces the whole output set ------------------------------------

def test_synth_force_replaces_the_whole_output_set(model_dir, corpus_dir, tmp_path):
    wav, lab = _utt(corpus_dir)
    out = tmp_path / "o"
    args = ["-q", "synth", str(model_dir), "--audio", str(wav), "--labels", str(lab), "--out", str(out),
            "--posterior", "map", "--algorithm", "predict"]
    assert main(args) == 0
    assert (out / "face.mp4").exists()
    (out / "mine.txt").write_text("keep me")
    assert main(args + ["--no-video"]) == 2                     # refused without --force
    assert main(args + ["--no-video", "--force"]) == 0
    assert not (out / "face.mp4").exists()                      # the earlier run's video is gone
    assert (out / "mine.txt").read_text() == "keep me"          # not ours: kept
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [".bayes_talk_outputs.json", "bands.npz", "bands.png", "landmarks.npy", "mine.txt", "posterior.nc",
         "segments.json", "trajectory.npy", "variance.npy"])
    # without an output record nothing there is known to be ours (issue 28): a hand-made
    # face.mp4 is refused without --force and survives a --force run that writes no video
    (out / ".bayes_talk_outputs.json").unlink()
    (out / "face.mp4").write_bytes(b"my own video")
    assert main(args + ["--no-video"]) == 2
    assert main(args + ["--no-video", "--force"]) == 0
    assert (out / "face.mp4").read_bytes() == b"my own video" and (out / "mine.txt").exists()


# --- row 9: a posterior that did not converge ------------------------------------------------

def test_unconverged_posterior_is_logged_and_marked(model_dir, corpus_dir, tmp_path, monkeypatch, caplog):
    import bayes_talk.posterior.sampling as post
    from bayes_talk.posterior.diagnostics import convergence_problems

    assert convergence_problems({"rhat_max": 1.01, "ess_bulk_min": 400.0, "ess_tail_min": 500.0,
                                 "divergences": 0}) == []
    assert len(convergence_problems({"rhat_max": 1.02, "ess_bulk_min": 50.0, "divergences": 1})) == 3
    real = post.sample_synthesis

    def bad_chains(*a, **kw):
        res = real(*a, **kw)
        res.diagnostics.update(rhat_max=1.94, ess_bulk_min=3.7)
        res.warnings = post._convergence_warnings("nuts", res.diagnostics)
        return res

    monkeypatch.setattr(post, "sample_synthesis", bad_chains)
    wav, lab = _utt(corpus_dir)
    with caplog.at_level(logging.WARNING):
        assert main(["synth", str(model_dir), "--audio", str(wav), "--labels", str(lab), "--out",
                     str(tmp_path / "o"), "--no-video", "--posterior", "laplace", "--draws", "8",
                     "--algorithm", "predict"]) == 0
    assert any("did not converge" in r.getMessage() and "R-hat 1.94" in r.getMessage() for r in caplog.records)
    diag = json.loads((tmp_path / "o" / "diagnostics.json").read_text())
    assert diag["converged"] is False and any("ESS 3.7" in p for p in diag["problems"])


# --- rows 10, 11: what the voice can pronounce; build arguments ------------------------------

def test_text_in_another_script_is_refused_with_the_line(tmp_path, capsys):
    for text, script in (("你好世界", "Cjk"), ("Привет, мир", "Cyrillic")):
        src = tmp_path / "s.txt"
        src.write_text(f"Hello there.\n{text}\n")
        out = tmp_path / "c"
        assert main(["corpus", "build", str(out), "--n-utterances", "2", "--sentences", str(src)]) == 2
        err = capsys.readouterr().err
        assert f"sentence 2 {text!r}" in err and script in err and "voice 'en'" in err
        assert not out.exists()


@pytest.mark.parametrize("argv, message", [
    (["--voice", "de"], "voice 'de' is not supported"),
    (["--voice", "xx"], "voice 'xx' is not supported"),
    (["--seed", "-1"], "argument --seed: expected an integer >= 0, found -1"),
])
def test_bad_build_arguments_leave_nothing_behind(tmp_path, capsys, argv, message):
    out = tmp_path / "c"
    with pytest.raises(SystemExit) if "--seed" in argv else _nothing():
        assert main(["corpus", "build", str(out), "--n-utterances", "1", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "ESPEAK_TO_ARPABET" not in err and "Traceback" not in err
    assert not out.exists()


def test_build_failing_midway_removes_what_it_created(tmp_path, capsys):
    out = tmp_path / "c"
    out.mkdir()
    assert main(["corpus", "build", str(out), "--n-utterances", "1", "--voice", "en-nosuchvoice"]) == 2
    assert "en-nosuchvoice" in capsys.readouterr().err
    assert out.is_dir() and not any(out.iterdir())              # the empty dir it was given, as it was
    assert main(["corpus", "build", str(tmp_path / "c2"), "--n-utterances", "1", "--voice", "en-x"]) == 2
    assert not (tmp_path / "c2").exists()


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


# --- row 12: NaN in a landmarks file or in the feature cache ---------------------------------

def test_nan_landmarks_name_the_file(corpus_dir, tmp_path):
    from bayes_talk.corpus import load_corpus, load_npz, save_npz

    c = tmp_path / "c"
    shutil.copytree(corpus_dir, c)
    lm_path = sorted((c / "utterances").glob("*.landmarks.npz"))[2]
    lm = load_npz(lm_path)["landmarks"]
    lm[4, 3, 0] = np.nan
    save_npz(lm_path, landmarks=lm)
    with pytest.raises(ValueError, match=rf"{lm_path.name}: landmarks contain NaN or inf \(first at frame 4\)"):
        load_corpus(c, cache=False, n_workers=1)


def test_nan_in_the_feature_cache_is_recomputed_with_a_warning(corpus_dir, tmp_path, caplog):
    from bayes_talk.corpus import load_corpus, load_npz, save_npz

    c = tmp_path / "c"
    shutil.copytree(corpus_dir, c)
    good = load_corpus(c, n_workers=1)
    cache = next(c.glob("features*.npz"))
    z = load_npz(cache)
    name = next(k for k in z if k.startswith("mfcc/"))
    z[name] = np.full_like(z[name], np.nan)
    save_npz(cache, **z)
    with caplog.at_level(logging.WARNING):
        again = load_corpus(c, n_workers=1)
    assert any(cache.name in r.getMessage() and "NaN" in r.getMessage() and "delete" in r.getMessage()
               for r in caplog.records)
    assert all(np.array_equal(a.mfcc, b.mfcc) for a, b in zip(good, again))


def test_an_unwritable_corpus_directory_loads_uncached_with_a_warning(corpus_dir, tmp_path, caplog,
                                                                     monkeypatch):
    """A read-only (or full) corpus directory must not lose the features just computed."""
    import bayes_talk.corpus.load as load_mod
    from bayes_talk.corpus import load_corpus

    c = tmp_path / "c"
    shutil.copytree(corpus_dir, c)
    for f in c.glob("features*.npz"):  # a cache an earlier test's load left in the fixture
        f.unlink()

    def refuse(path, *a, **k):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(load_mod, "save_npz", refuse)
    with caplog.at_level(logging.WARNING):
        got = load_corpus(c, n_workers=1)
    assert not list(c.glob("features*.npz"))
    assert any("cannot write the feature cache" in r.getMessage() and "Permission denied" in r.getMessage()
               for r in caplog.records)
    monkeypatch.undo()
    ref = load_corpus(c, cache=False, n_workers=1)
    assert all(np.array_equal(a.mfcc, b.mfcc) and np.array_equal(a.aam, b.aam) for a, b in zip(got, ref))


# --- row 13: what the outputs mean ----------------------------------------------------------

def test_outputs_are_documented_and_the_recipe_gives_the_landmarks(model_dir, corpus_dir, tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["synth", "--help"])
    text = capsys.readouterr().out
    assert "MEAN-REMOVED" in text and "aam_offset" in text and "tm.offset" in text
    flat = " ".join(text.split())
    from bayes_talk.posterior.methods import NUTS_DEFAULTS, PG_NUTS_BUDGET

    nuts = f"nuts {NUTS_DEFAULTS['chains']} x {NUTS_DEFAULTS['draws_per_chain']}"
    pg = f"pg-nuts {NUTS_DEFAULTS['chains']} x {PG_NUTS_BUDGET['draws_per_chain']}"
    assert "--draws DRAWS" in text and f"(default: laplace 64, {nuts}, {pg}, emcee 320, vi 64)" in flat
    assert f"NUTS chains (default {NUTS_DEFAULTS['chains']})" in flat
    # (argparse may wrap the line after the hyphen of "pg-nuts")
    assert re.search(rf"NUTS warm-up iterations per chain \(default {NUTS_DEFAULTS['warmup']}; pg- ?nuts "
                     rf"{PG_NUTS_BUDGET['warmup']}\)", flat), flat
    wav, lab = _utt(corpus_dir)
    out = tmp_path / "o"
    assert main(["-q", "synth", str(model_dir), "--audio", str(wav), "--labels", str(lab), "--out", str(out),
                 "--no-video", "--algorithm", "predict"]) == 0
    tm = load_trained(model_dir)
    lms, _ = tm.aam.reconstruct(np.load(out / "trajectory.npy") + tm.offset)
    assert np.allclose(lms, np.load(out / "landmarks.npy"))
    assert (Path(__file__).resolve().parents[2] / "docs" / "outputs.md").exists()


# --- messages: -v/-q anywhere, defaults in --help, Ctrl-C, small corpora ---------------------

def test_verbosity_anywhere_defaults_in_help_and_ctrl_c(tmp_path, capsys, monkeypatch):
    from bayes_talk.app import cli

    for argv in (["-v", "demo", "--help"], ["demo", "-v", "--help"], ["demo", "--help", "-q"]):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 0
    with pytest.raises(SystemExit):
        main(["corpus", "build", "--help"])
    assert "(default: 300)" in capsys.readouterr().out
    args = cli.build_parser().parse_args(["train", "x", "--out", "y", "-v"])
    assert args.verbose is True and args.quiet is False

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_cmd_demo", interrupted)  # build_parser looks it up at call time
    assert main(["demo", "--out", str(tmp_path / "d")]) == 130
    assert capsys.readouterr().err.strip() == "bayes-talk: error: interrupted"


def test_small_corpus_protocol_is_scaled_with_a_note():
    from bayes_talk.evaluation.protocols import get_protocol, scale_protocol
    from bayes_talk.evaluation.splits import make_splits

    p = get_protocol("deena2010")
    with pytest.raises(ValueError, match="needs at least 278 utterances, the corpus has 30"):
        make_splits(p, 30)
    q, note = scale_protocol(p, 30, 20)
    assert q.n_train + q.n_test == 30 and q.n_test >= 1 and "SMALL CORPUS" in note and "278" in note
    assert len(make_splits(q, 30)[0].test) == q.n_test
    assert scale_protocol(p, 300, 20) == (p, None)
    with pytest.raises(ValueError, match="fewer than --min-utterances 40"):
        scale_protocol(p, 30, 40)


def test_progress_is_silent_off_a_terminal_and_logged_with_verbose(caplog):
    from bayes_talk.base.progress import ProgressMapper, bar, enabled

    assert not enabled()                                   # pytest's stderr is not a terminal
    with caplog.at_level(logging.WARNING, logger="bayes_talk.base.progress"):
        assert list(bar(range(5), 5, "x")) == list(range(5))
    assert not caplog.records
    with caplog.at_level(logging.INFO, logger="bayes_talk.base.progress"):
        assert list(ProgressMapper(None, "training states", "state").map(abs, [-1, -2, 3])) == [1, 2, 3]
    messages = [r.getMessage() for r in caplog.records]
    assert messages[0] == "training states: started (3 state)"
    assert messages[-1].startswith("training states: done in ") and messages[-1].endswith(" (3/3 state)")
