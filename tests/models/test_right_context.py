"""Right-context (anticipatory) switching states: eq. (1) of bayes_talk.models.right_context,
the back-off to the base state, training, persistence."""
from __future__ import annotations

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.estimators.registry import make_estimator
from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.models.right_context import RIGHT_MARK, next_different
from bayes_talk.models.switching import FALLBACK

SMALL = {"latent_dim": 2, "max_iter": 15, "min_count": 4, "max_frames_per_state": 80, "fallback_frames": 100}


def test_next_different_label_of_every_frame():
    assert next_different(["a", "a", "b", "b", "b", "c"]) == ["b", "b", "c", "c", "c", "sil"]
    assert next_different(["a"]) == ["sil"]
    assert next_different([]) == []


@pytest.fixture(scope="module")
def data():
    return make_utterances(12, seed=0), make_utterances(3, seed=1)


@pytest.fixture(scope="module")
def rc_model(data):
    return make_estimator("ssgpdm-phone-rc", **SMALL).fit(data[0])


def test_states_name_the_next_phone_and_back_off_to_the_phone(rc_model, data):
    test = data[1][0]
    segs = rc_model.segment(test.labels)
    nxt = next_different(list(test.labels))
    for s in segs:
        assert s.state == (RIGHT_MARK + nxt[s.stop - 1], test.labels[s.start])
        assert all(lab == test.labels[s.start] for lab in test.labels[s.start:s.stop])
    refined = [k for k in rc_model.models_ if k[0].startswith(RIGHT_MARK)]
    plain = [k for k in rc_model.models_ if k != FALLBACK and not k[0].startswith(RIGHT_MARK)]
    assert refined and plain  # pair models where there are frames enough, phone models for back-off
    # every pair model was trained on runs of its phone followed by its next phone only
    for k in refined:
        assert sum(rc_model.models_[k].seq_lengths_) >= SMALL["latent_dim"] + 1
    # an unseen (next phone, phone) pair backs off to the phone's own model
    phone = plain[0][0]
    used, _ = rc_model.model_for((RIGHT_MARK + "never-a-phone", phone))
    assert used == (phone,)
    assert rc_model.name == "ssgpdm-phone-rc"


def test_right_context_changes_synthesis_and_survives_save_load(rc_model, data, tmp_path):
    train, test = data
    base = SwitchingSGPDM(states="phone", **SMALL).fit(train)
    s = test[0]
    r = rc_model.synthesize(s.mfcc, s.labels)
    assert r.mean.shape == s.aam.shape and np.all(np.isfinite(r.mean))
    assert not np.allclose(r.mean, base.synthesize(s.mfcc, s.labels).mean)
    rc_model.save(tmp_path / "m")
    m2 = SwitchingSGPDM.load(tmp_path / "m")
    assert m2.right_context and m2.name == "ssgpdm-phone-rc"
    assert m2.segment(s.labels) == rc_model.segment(s.labels)
    np.testing.assert_array_equal(m2.synthesize(s.mfcc, s.labels).mean, r.mean)


def test_vlmm_right_context_refines_vlmm_states(data):
    m = make_estimator("ssgpdm-vlmm-rc", **SMALL).fit(data[0])
    s = data[1][1]
    base_segs = m.states_model_.base.segment(s.labels)
    segs = m.segment(s.labels)
    assert [(a.start, a.stop) for a in segs] == [(b.start, b.stop) for b in base_segs]
    assert all(a.state[1:] == b.state and a.state[0].startswith(RIGHT_MARK) for a, b in zip(segs, base_segs))


def test_right_context_must_be_a_bool():
    with pytest.raises(ValueError, match="right_context"):
        SwitchingSGPDM(right_context="yes")
