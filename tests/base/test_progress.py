"""Progress a user sees (bayes_talk.base.progress): the heartbeat of a stage off a terminal,
while the stage's code is busy in one call; its end with the stage; the time left; the
stage lines with INFO; the bar on a terminal; silence when progress is off; and the
stages of ``synth``.

The heartbeat interval is set to 0.05 s; the tests sleep several intervals and assert at
least one heartbeat, never a count."""
from __future__ import annotations

import logging
import re
import threading
import time
from typing import ClassVar

import pytest

from bayes_talk.base import progress

INTERVAL = 0.05


def _beats(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == progress.HEARTBEAT_LOGGER]


def _progress_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("bayes_talk progress")]


@pytest.fixture(autouse=True)
def _enabled():
    progress.set_enabled(True)
    yield
    progress.set_enabled(True)


def test_the_heartbeat_fires_while_the_stage_is_blocked_and_stops_with_it(caplog):
    with caplog.at_level(logging.INFO, logger=progress.HEARTBEAT_LOGGER):
        with progress.stage("loading model", interval=INTERVAL) as s:
            time.sleep(10 * INTERVAL)           # one long call: no advance
            assert _progress_threads()
        beats = _beats(caplog)
        assert beats and all(re.fullmatch(r"loading model: \d+\.\d s elapsed", b) for b in beats), beats
        assert s.beats == len(beats)
        assert not _progress_threads()          # joined when the stage ended
        n = len(caplog.records)
        time.sleep(6 * INTERVAL)
        assert len(caplog.records) == n         # nothing after the stage


def test_the_heartbeat_gives_done_total_and_the_time_left_when_the_total_is_known(caplog):
    with caplog.at_level(logging.INFO, logger=progress.HEARTBEAT_LOGGER), \
            progress.stage("synthesis", total=200, unit="frames", interval=INTERVAL) as s:
        s.advance(20)
        s.advance()
        time.sleep(10 * INTERVAL)
        assert s.done == 21
        s.update(50)
        s.set_total(400)
        time.sleep(10 * INTERVAL)
    beats = _beats(caplog)
    assert any(re.fullmatch(r"synthesis: 21/200 frames \(10 %\), \d+\.\d s elapsed, about [\d.]+ (s|min) .*left", b)
               for b in beats), beats
    assert any(b.startswith("synthesis: 50/400 frames (12 %)") and "left" in b for b in beats), beats


def test_an_unknown_total_has_no_time_left_and_nothing_done_says_so(caplog):
    with caplog.at_level(logging.INFO, logger=progress.HEARTBEAT_LOGGER):
        with progress.stage("labelling", interval=INTERVAL) as s:
            s.advance(3)
            time.sleep(8 * INTERVAL)
        with progress.stage("synthesis", total=10, interval=INTERVAL):
            time.sleep(8 * INTERVAL)
    beats = _beats(caplog)
    assert any(b.startswith("labelling: 3 frames, ") and "left" not in b for b in beats), beats
    assert any(b.startswith("synthesis: 0/10 frames (0 %), ") and b.endswith("time left unknown") for b in beats), beats


def test_only_the_innermost_stage_beats_and_names_its_path(caplog):
    with caplog.at_level(logging.INFO, logger=progress.HEARTBEAT_LOGGER), \
            progress.stage("synthesis", total=100, interval=INTERVAL):
        with progress.stage("MAP", total=4, unit="restarts", interval=INTERVAL):
            progress.current().advance(1)     # how code deep inside reports
            time.sleep(10 * INTERVAL)
            assert progress.current().name == "MAP"
            caplog.clear()
            time.sleep(6 * INTERVAL)
            inner = _beats(caplog)
        assert progress.current().name == "synthesis"
    assert progress.current().name == ""          # none open: a stand-in that does nothing
    progress.current().advance(5)
    assert inner and all(b.startswith("synthesis / MAP: 1/4 restarts") for b in inner), inner


def test_start_and_end_lines_with_info_and_a_failed_stage(caplog):
    with caplog.at_level(logging.INFO, logger="bayes_talk.base.progress"):
        with progress.stage("writing outputs", total=3, unit="files") as s:
            s.advance(3)
        with pytest.raises(RuntimeError), progress.stage("rendering video", total=8):
            raise RuntimeError("boom")
    lines = [r.getMessage() for r in caplog.records if r.name == "bayes_talk.base.progress"]
    assert lines[0] == "writing outputs: started (3 files)"
    assert re.fullmatch(r"writing outputs: done in \d+\.\d s \(3/3 files\)", lines[1]), lines
    assert lines[2] == "rendering video: started (8 frames)"
    assert lines[3].startswith("rendering video: failed after ") and not _progress_threads()


def test_nothing_is_shown_with_progress_off(caplog, capsys):
    progress.set_enabled(False)
    with caplog.at_level(logging.DEBUG):
        with progress.stage("synthesis", total=10, interval=INTERVAL) as s:
            s.advance(2)
            time.sleep(8 * INTERVAL)
            assert not _progress_threads()
        assert list(progress.bar(range(3), desc="x")) == [0, 1, 2]
    assert not [r for r in caplog.records if r.name.startswith(("bayes_talk.progress", "bayes_talk.base.progress"))]
    assert capsys.readouterr().err == ""


def test_no_heartbeat_thread_when_its_logger_is_off(caplog):
    with caplog.at_level(logging.WARNING, logger=progress.HEARTBEAT_LOGGER), \
            progress.stage("synthesis", interval=INTERVAL):
        assert not _progress_threads()
        time.sleep(4 * INTERVAL)
    assert not _beats(caplog)


def test_a_terminal_gets_a_bar_redrawn_while_blocked(monkeypatch, capsys):
    monkeypatch.setattr(progress, "_terminal", lambda: True)
    with progress.stage("synthesis", total=50, unit="frames", interval=INTERVAL) as s:
        s.advance(5)
        time.sleep(10 * INTERVAL)
        s.update(20)
    assert not _progress_threads()
    err = capsys.readouterr().err
    assert "synthesis" in err and "| 20/50 " in err
    assert err.count("| 5/50 ") >= 2, err       # drawn at the advance, redrawn while blocked


def test_bar_and_mapper_advance_a_stage(caplog):
    with caplog.at_level(logging.INFO, logger=progress.HEARTBEAT_LOGGER):
        def slow(x):
            time.sleep(4 * INTERVAL)
            return -x

        monkey = progress.HEARTBEAT_S
        progress.HEARTBEAT_S = INTERVAL
        try:
            assert list(progress.ProgressMapper(None, "training states", "state").map(slow, [1, 2, 3])) == [-1, -2, -3]
        finally:
            progress.HEARTBEAT_S = monkey
    assert any(re.match(r"training states: [0-2]/3 state", b) for b in _beats(caplog)), _beats(caplog)
    assert not _progress_threads()


def test_a_bad_interval_is_refused():
    with pytest.raises(ValueError, match="interval must be > 0"):
        progress.stage("x", interval=0)


def test_synth_runs_every_stage(monkeypatch, tmp_path):
    """synth's stages, in order, with the synthesis's total the number of frames (the model
    and the writers replaced by stand-ins: the stages are what is tested)."""
    from types import SimpleNamespace

    import numpy as np

    from bayes_talk.pipeline import talking_face as tf

    opened = []
    real = progress.Stage.open

    def record(self):
        opened.append((self.name, self.total, self.unit))
        return real(self)

    monkeypatch.setattr(progress.Stage, "open", record)
    T, D = 7, 3

    class Result:
        mean, var, segments, warnings, n_frames, diagnostics, method, n_draws = (
            np.zeros((T, D)), np.ones((T, D)), [], [], T, {}, "laplace", 10)

    class Model:
        synthesis_options: ClassVar[dict] = {"posterior": ("laplace",)}
        post_filter = False

        def predict_dist(self, utt, **kw):
            assert progress.current().name == "synthesis"
            return Result()

    class AAM:
        def reconstruct(self, p):
            return np.zeros((len(p), 2, 2)), None

        def render(self, p):
            return np.zeros((len(p), 4, 4), np.uint8)

    tm = SimpleNamespace(model=Model(), uncalibrated=Model(), kind="ssgpdm", fps=25.0, audio=None,
                         offset=np.zeros(D), aam=AAM(), calibration=None, directory="model")
    utt = SimpleNamespace(mfcc=np.zeros((T, 20)))
    monkeypatch.setattr(tf, "load_trained", lambda d: tm)
    monkeypatch.setattr(tf, "_check_speech", lambda wav, recognise: None)
    monkeypatch.setattr(tf, "front_end", lambda audio: {})
    monkeypatch.setattr(tf, "read_utterance", lambda *a, **k: utt)
    monkeypatch.setattr(tf, "_derived_labels", lambda *a: [(0.0, 0.28, "sil")])
    monkeypatch.setattr(tf, "utterance_from_intervals", lambda *a, **k: utt)
    monkeypatch.setattr(tf, "_write_uncertainty", lambda out, names, res, truth, tm, writing: {})
    monkeypatch.setattr(tf, "write_video", lambda path, frames, fps, **k: (list(frames), path)[1])  # frames consumed
    monkeypatch.setattr(tf, "uncertainty_frames", lambda aam, res, offset, seed=None: tf.render_frames(
        aam, np.zeros((T * (1 + tf.VIDEO_DRAWS), D))))
    tf.synth("model", "a.wav", None, tmp_path / "out")
    names = [n for n, _, _ in opened]
    assert names == ["loading model", "reading audio", "labelling", "featurising audio", "synthesis",
                     "writing outputs", "rendering video"], names
    assert opened[4] == ("synthesis", T, "frames")
    assert opened[6] == ("rendering video", T * (2 + tf.VIDEO_DRAWS), "frames")
