"""The phonetic-context view (bayes_talk.features.context_view): a supervised reduction of
the label and MFCC window that joins the audio view of the switching model."""
from __future__ import annotations

import numpy as np
import pytest
from toydata import make_utterances

from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.features.context_view import ContextView

SMALL = {"latent_dim": 3, "max_iter": 30, "min_count": 4, "max_frames_per_state": 100, "fallback_frames": 120}


@pytest.fixture(scope="module")
def data():
    return make_utterances(16, seed=0), make_utterances(3, seed=5)


def test_training_frames_get_out_of_fold_values_and_new_frames_the_full_fit(data):
    """The training view is the out-of-fold prediction (it fits the training faces worse
    than the full-data fit does, and differs from it), new utterances get the full fit,
    and the view predicts held-out faces better than their mean does."""
    train, test = data
    cv = ContextView(label_window=4, mfcc_window=2)
    oof = cv.fit(train)
    assert [o.shape for o in oof] == [(s.n_frames, s.aam.shape[1]) for s in train] and cv.n_dims == 5
    full = [cv.transform(s.mfcc, s.labels) for s in train]
    err_oof = np.mean([np.mean((o - s.aam) ** 2) for o, s in zip(oof, train)])
    err_full = np.mean([np.mean((f - s.aam) ** 2) for f, s in zip(full, train)])
    assert err_full < err_oof and not np.allclose(oof[0], full[0])
    z = np.vstack([s.aam for s in test])
    pred = np.vstack([cv.transform(s.mfcc, s.labels) for s in test])
    assert np.mean((pred - z) ** 2) < 0.7 * np.mean((z - z.mean(0)) ** 2)
    assert cv.alpha_ in (1.0, 10.0, 100.0, 1000.0)


def test_off_by_default_and_bad_input_is_named(data):
    train, _ = data
    off = ContextView(0)
    assert off.fit(train)[0].shape == (train[0].n_frames, 0) and not off.enabled
    assert off.transform(train[0].mfcc, train[0].labels).shape == (train[0].n_frames, 0)
    with pytest.raises(ValueError, match="whole number of frames"):
        ContextView(-1)
    cv = ContextView(2)
    with pytest.raises(ValueError, match="before fit"):
        cv.transform(train[0].mfcc, train[0].labels)
    cv.fit(train)
    with pytest.raises(ValueError, match="one phone label per frame"):
        cv.transform(train[0].mfcc, train[0].labels[:-1])


def test_switching_model_explains_the_context_view_and_saves_it(data, tmp_path):
    """With ``context_view`` the state models' audio GPs explain [audio, context] columns;
    synthesis uses them; a saved and loaded model synthesises the same trajectory."""
    train, test = data
    m = SwitchingSGPDM(states="phone", right_context=True, context_view=3, **SMALL).fit(train)
    Dy, Dz = train[0].mfcc.shape[1], train[0].aam.shape[1]
    assert all(sm.means_["audio"].shape == (Dy + Dz,) for sm in m.models_.values())
    s = test[0]
    assert m.audio_input(s.mfcc, s.labels).shape == (s.n_frames, Dy + Dz)
    with pytest.raises(ValueError, match="one phone label per frame"):
        m.audio_input(s.mfcc)
    r = m.synthesize(s.mfcc, s.labels)
    plain = SwitchingSGPDM(states="phone", right_context=True, **SMALL).fit(train)
    assert not np.allclose(plain.synthesize(s.mfcc, s.labels).mean, r.mean)
    m.save(tmp_path / "m")
    back = SwitchingSGPDM.load(tmp_path / "m")
    np.testing.assert_array_equal(back.audio_input(s.mfcc, s.labels), m.audio_input(s.mfcc, s.labels))
    np.testing.assert_allclose(back.synthesize(s.mfcc, s.labels).mean, r.mean, atol=1e-10)
