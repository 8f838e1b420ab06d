"""`synth --audio-dir / --audio-list`: many files through one model load, a broken file
reported and skipped, the summary, the refusals (bayes_talk.pipeline.batch)."""
from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from bayes_talk.app.cli import main
from bayes_talk.pipeline import batch, talking_face, trained

SMALL = {"latent_dim": 3, "max_iter": 20, "min_count": 3, "max_frames_per_state": 80, "fallback_frames": 100}
#: the cheapest synthesis: deena2010's Algorithm 2, no video
FAST = ["--no-video", "--posterior", "map", "--algorithm", "predict"]


@pytest.fixture(scope="module")
def model_dir(shared_built_corpus, tmp_path_factory) -> Path:
    from bayes_talk.pipeline import train

    out = tmp_path_factory.mktemp("batch") / "model"
    train(shared_built_corpus, "ssgpdm-vlmm", out, workers=1, alignment=False, **SMALL)
    return out


@pytest.fixture
def audio_dir(shared_built_corpus, tmp_path) -> Path:
    """Two utterances of the built corpus with their .lab beside, and broken.wav: an empty file."""
    d = tmp_path / "audio"
    d.mkdir()
    for name in ("utt0008", "utt0009"):
        for ext in ("wav", "lab"):
            shutil.copy(shared_built_corpus / "utterances" / f"{name}.{ext}", d / f"{name}.{ext}")
    (d / "broken.wav").write_bytes(b"")
    return d


@pytest.fixture
def load_count(monkeypatch) -> list[str]:
    """Every call of load_trained, wherever synth or the batch would make it."""
    calls: list[str] = []
    real = trained.load_trained

    def counting(model_dir):
        calls.append(str(model_dir))
        return real(model_dir)

    for mod in (batch, talking_face, trained):
        monkeypatch.setattr(mod, "load_trained", counting)
    return calls


def test_a_directory_of_files_loads_the_model_once_and_reports_the_broken_file(model_dir, audio_dir, tmp_path,
                                                                             load_count, capsys):
    out = tmp_path / "out"
    assert main(["synth", str(model_dir), "--audio-dir", str(audio_dir), "--out", str(out), *FAST]) == 1
    assert load_count == [str(model_dir)]
    printed = capsys.readouterr()
    assert "2 of 3 files synthesised" in printed.out and "FAILED" in printed.out
    assert "[broken.wav]" in printed.err and "cannot read audio" in printed.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["format"] == "bayes_talk.synth_batch" and summary["model"] == str(model_dir)
    assert (summary["n_files"], summary["n_ok"], summary["n_failed"]) == (3, 2, 1)
    rows = {Path(r["file"]).name: r for r in summary["files"]}
    assert list(rows) == ["broken.wav", "utt0008.wav", "utt0009.wav"]
    bad = rows["broken.wav"]
    assert bad["status"] == "failed" and "broken.wav" in bad["error"] and bad["frames"] is None
    assert bad["labels"] == "recognised"          # no labels beside it
    assert not (out / "broken").exists() or not any((out / "broken").iterdir())
    for name in ("utt0008", "utt0009"):
        r = rows[f"{name}.wav"]
        assert r["status"] == "ok" and r["error"] is None and r["labels"] == str(audio_dir / f"{name}.lab")
        assert r["out"] == str(out / name) and r["seconds"] >= 0
        assert r["frames"] == np.load(out / name / "trajectory.npy").shape[0] > 0
    with open(out / "summary.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert [Path(t["file"]).name for t in table] == list(rows)
    assert [t["status"] for t in table] == ["failed", "ok", "ok"] and table[1]["frames"] == str(rows["utt0008.wav"]["frames"])
    # each file's directory holds what one synth run writes, the same numbers
    single = tmp_path / "single"
    assert main(["synth", str(model_dir), "--audio", str(audio_dir / "utt0009.wav"), "--labels",
                 str(audio_dir / "utt0009.lab"), "--out", str(single), *FAST]) == 0
    assert sorted(p.name for p in (out / "utt0009").iterdir()) == sorted(p.name for p in single.iterdir())
    np.testing.assert_array_equal(np.load(out / "utt0009" / "trajectory.npy"), np.load(single / "trajectory.npy"))
    np.testing.assert_array_equal(np.load(out / "utt0009" / "variance.npy"), np.load(single / "variance.npy"))


def test_outputs_are_never_replaced_without_force(model_dir, audio_dir, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["synth", str(model_dir), "--audio-dir", str(audio_dir), "--out", str(out), *FAST]
    (audio_dir / "broken.wav").unlink()
    assert main(args) == 0
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "already holds outputs" in err and "--force" in err
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == before
    # one file's earlier outputs are enough to stop the whole batch before any work
    shutil.rmtree(out)
    (out / "utt0009").mkdir(parents=True)
    (out / "utt0009" / "trajectory.npy").write_bytes(b"the user's")
    assert main(args) == 2
    assert not (out / "utt0008").exists() and (out / "utt0009" / "trajectory.npy").read_bytes() == b"the user's"
    assert main([*args, "--force"]) == 0
    assert np.load(out / "utt0009" / "trajectory.npy").ndim == 2


def test_an_audio_list_takes_labels_from_its_second_column_and_runs_files_in_worker_processes(
        model_dir, audio_dir, tmp_path):
    labels = tmp_path / "labels"
    labels.mkdir()
    shutil.move(audio_dir / "utt0008.lab", labels / "first.lab")   # not beside its WAV
    listing = audio_dir / "files.txt"
    listing.write_text("# wav  [labels]\nutt0008.wav ../labels/first.lab\n\nutt0009.wav\nbroken.wav\n")
    out = tmp_path / "out"
    assert main(["synth", str(model_dir), "--audio-list", str(listing), "--out", str(out), "--file-workers", "2",
                 *FAST]) == 1
    rows = json.loads((out / "summary.json").read_text())["files"]
    assert [Path(r["file"]).name for r in rows] == ["utt0008.wav", "utt0009.wav", "broken.wav"]
    assert [r["status"] for r in rows] == ["ok", "ok", "failed"]
    assert Path(rows[0]["labels"]).resolve() == (labels / "first.lab").resolve()
    assert Path(rows[1]["labels"]).name == "utt0009.lab"
    for r in rows[:2]:
        assert np.load(Path(r["out"]) / "trajectory.npy").shape[0] == r["frames"]


@pytest.mark.parametrize("extra, message", [
    (["--labels", "X.lab"], "--labels belongs to one --audio"),
    (["--file-workers", "2", "--posterior", "nuts", "--workers", "2"], "--file-workers and --workers"),
])
def test_per_file_options_and_nested_processes_are_refused(model_dir, audio_dir, tmp_path, capsys, extra, message):
    out = tmp_path / "out"
    assert main(["synth", str(model_dir), "--audio-dir", str(audio_dir), "--out", str(out), *extra]) == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_file_workers_need_a_batch_and_lists_are_checked_before_any_work(model_dir, audio_dir, tmp_path, capsys):
    wav = audio_dir / "utt0008.wav"
    assert main(["synth", str(model_dir), "--audio", str(wav), "--out", str(tmp_path / "o"),
                 "--file-workers", "2"]) == 2
    assert "--file-workers runs the files of --audio-dir/--audio-list" in capsys.readouterr().err
    twice = tmp_path / "twice.txt"
    twice.write_text(f"{wav}\n{audio_dir}/sub/../utt0008.wav\n")
    assert main(["synth", str(model_dir), "--audio-list", str(twice), "--out", str(tmp_path / "o")]) == 2
    assert "would both write to" in capsys.readouterr().err
    bad = tmp_path / "bad.txt"
    bad.write_text(f"{wav}\n{wav} a.lab b.lab\n")
    assert main(["synth", str(model_dir), "--audio-list", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert f"{bad}, line 2: 3 fields" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["synth", str(model_dir), "--audio-dir", str(empty), "--out", str(tmp_path / "o")]) == 2
    assert "no .wav files" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
