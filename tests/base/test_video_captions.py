"""The demo's side-by-side video says which side is the truth (issue 28): captions drawn in
a strip above each panel."""
from __future__ import annotations

import inspect

import numpy as np
import pytest

from bayes_talk.base.video import caption_strip, side_by_side


def _videos():
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, (5, 32, 40), dtype=np.uint8), rng.integers(0, 256, (4, 32, 48), dtype=np.uint8)


def test_captions_go_in_a_strip_above_each_panel_and_leave_the_frames_alone():
    a, b = _videos()
    plain = side_by_side(a, b)
    out = side_by_side(a, b, labels=("ground truth", "synthesis"))
    assert plain.shape == (4, 32, 40 + 2 + 48)
    assert out.shape == (4, 16 + 32, 40 + 2 + 48) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[:, 16:], plain)               # the faces are untouched
    left, right = out[0, :16, :40], out[0, :16, 42:]
    assert (left > 128).sum() > 20 and (right > 128).sum() > 20     # text is drawn over each panel
    np.testing.assert_array_equal(out[:, :16, :40], np.broadcast_to(left, (4, 16, 40)))   # the same on every frame
    assert (out[:, :, 40:42] == 0).all()                             # the gap stays dark


def test_different_captions_draw_different_pixels_and_a_wrong_count_is_refused():
    assert not np.array_equal(caption_strip("ground truth", 64), caption_strip("synthesis", 64))
    assert caption_strip("", 64).max() == 0
    a, b = _videos()
    with pytest.raises(ValueError, match="one per video"):
        side_by_side(a, b, labels=("ground truth",))


def test_the_demo_captions_its_video_with_the_truth_on_the_left():
    from bayes_talk.app import demo

    assert "truth" in demo.DEMO_VIDEO_LABELS[0] and "synthesis" in demo.DEMO_VIDEO_LABELS[1]
    assert "side_by_side(gt_frames, syn_frames, labels=DEMO_VIDEO_LABELS)" in inspect.getsource(demo.run_demo)
