"""Latent dimensions private to a view (SGPDMConfig.view_dims, SwitchingConfig.private_dims;
shared and private latent spaces, Ek et al. 2008): the audio GP reads the first k latent
dimensions only, in training, in every predictive and in the synthesis density. The
objective and the synthesis density against autograd are in test_sgpdm_direct.py and
test_posterior.py (the ``toy_private`` cases)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from bayes_talk.gp.numpy_gp import numpy_gp
from bayes_talk.gp.predictive_fused import PackedGPs
from bayes_talk.models.sgpdm import SGPDM
from bayes_talk.models.switching import SwitchingModel
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan


def _views(N=60, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 6, N)[:, None]
    audio = np.hstack([np.sin(t), np.cos(t), np.sin(2 * t)]) + 0.05 * rng.standard_normal((N, 3))
    # a face with a component the audio does not carry (the last column)
    video = np.hstack([np.cos(t), np.sin(3 * t), rng.standard_normal((N, 1))])
    return {"audio": audio, "visual": video}


@pytest.fixture(scope="module")
def private_sgpdm():
    return SGPDM(latent_dim=3, max_iter=40, view_dims={"audio": 2}).fit(_views(), seq_lengths=[30, 30])


def test_the_audio_gp_reads_only_the_shared_dimensions(private_sgpdm):
    """Moving a point along the private dimension leaves the audio predictive (torch and
    NumPy twins) exactly unchanged and moves the visual one; the audio loglik's gradient
    is zero in the private dimension."""
    m = private_sgpdm
    assert m.predictors_["audio"].X.shape == (60, 2) and m.predictors_["audio"].in_dims == 2
    assert m.predictors_["visual"].in_dims is None and m.X_.shape == (60, 3)
    X = m.X_[:7].copy()
    Xp = X.copy()
    Xp[:, 2] += 3.0
    for view, same in (("audio", True), ("visual", False)):
        a, b = m.predict_view(view, X), m.predict_view(view, Xp)
        assert np.array_equal(a[0], b[0]) == same and np.array_equal(a[1], b[1]) == same
        g = numpy_gp(m.predictors_[view])
        assert np.array_equal(g.mean_var(X)[0], g.mean_var(Xp)[0]) == same
    Y = m.predict_view("audio", X)[0] + 0.1
    _, gx, _ = numpy_gp(m.predictors_["audio"]).loglik(Y, X)
    assert gx.shape == (7, 3) and np.all(gx[:, 2] == 0.0) and np.abs(gx[:, :2]).max() > 0
    Xt = torch.tensor(X, requires_grad=True)
    m.predictors_["audio"].log_lik(torch.as_tensor(Y), Xt).sum().backward()
    assert torch.all(Xt.grad[:, 2] == 0.0)


def test_private_dimensions_start_from_what_the_shared_ones_leave(private_sgpdm):
    """The initial private dimension is uncorrelated with the shared ones (PCA of the
    views' residual after least squares on the shared initial scores)."""
    m = private_sgpdm
    X0 = m._init_latents({v: Y - Y.mean(0) for v, Y in _views().items()})
    assert X0.shape == (60, 3)
    c = np.corrcoef(X0.T)
    assert np.abs(c[2, :2]).max() < 1e-8
    full = SGPDM(latent_dim=3)._init_latents({v: Y - Y.mean(0) for v, Y in _views().items()})
    assert not np.allclose(full[:, 2], X0[:, 2])   # the papers' init is not the private one


def test_a_saved_private_model_predicts_the_same(private_sgpdm, tmp_path):
    m = private_sgpdm
    m2 = SGPDM.load(m.save(tmp_path / "m"))
    assert m2.config.view_dims == {"audio": 2} and m2.predictors_["audio"].in_dims == 2
    X = m.X_[:5] + 0.1
    for view in ("audio", "visual"):
        np.testing.assert_array_equal(m.predict_view(view, X)[0], m2.predict_view(view, X)[0])


@pytest.mark.parametrize("kw, match", [
    ({"view_dims": {"face": 1}}, "not among the views"),
    ({"view_dims": {"audio": 0}}, "1 to latent_dim"),
    ({"view_dims": {"audio": 4}}, "1 to latent_dim"),
    ({"view_dims": {"audio": 2}, "back_constraint": "audio"}, "back-constraint"),
])
def test_bad_view_dims_are_refused_by_name(kw, match):
    with pytest.raises(ValueError, match=match):
        SGPDM(latent_dim=3, max_iter=2, **kw).fit(_views())


def test_private_dims_outside_the_latent_space_are_refused():
    for bad in (-1, 6, 2.5):
        with pytest.raises(ValueError, match="private_dims"):
            SwitchingModel(latent_dim=6, private_dims=bad)
    assert SwitchingModel(latent_dim=6, private_dims=2)._state_cfg()["view_dims"] == {"audio": 4}
    assert SwitchingModel(latent_dim=6)._state_cfg()["view_dims"] is None


def test_the_sparse_sgpdm_refuses_private_dimensions():
    from bayes_talk.models.sparse_sgpdm import SparseSGPDM

    with pytest.raises(ValueError, match="view_dims"):
        SparseSGPDM(latent_dim=3, view_dims={"audio": 2})


def test_packed_gps_must_read_the_same_dimensions(private_sgpdm):
    m = private_sgpdm
    with pytest.raises(ValueError, match="same latent dimensions"):
        PackedGPs([numpy_gp(m.predictors_["audio"]), numpy_gp(m.predictors_["visual"])])


def test_the_synthesis_density_leaves_the_private_dimension_to_the_prior(toy_vlmm_private):
    """In the whole-utterance density the audio terms do not see the private dimension:
    with the dynamics, entry and smoothness terms the same, moving every frame's private
    coordinate changes ln p by exactly what the prior terms (SwitchingLatents, smoothness
    factors) change; the audio part is unchanged."""
    from toydata import make_utterances

    from bayes_talk.synthesis.joint import SwitchingLatents, pyro_log_density

    model = toy_vlmm_private
    s = make_utterances(1, seed=4, mean_len=20)[0]
    plan = make_plan(model, s.mfcc, s.labels, smoothness="off")
    X = model.synthesize(s.mfcc, s.labels, smoothness="off").latents
    Xp = X.copy()
    Xp[:, 2] += 0.05
    dens = UtteranceDensity(plan)
    tm = dens.terms
    # the audio terms themselves: the same values to the bit, no gradient in the private dim
    (ll, g), (llp, gp) = (tm.audio_grad(Z[tm.a_idx], 1) for Z in (X, Xp))
    np.testing.assert_array_equal(ll, llp)
    np.testing.assert_array_equal(g, gp)
    assert not g[:, 2].any() and g[:, :2].any()
    # ... and ln p minus the prior terms is that audio sum. The two sides are differences of
    # numbers of size |ln p| ≈ 2·10⁴ whose dynamics terms divide GP means' round-off by the
    # dynamics noise (10⁻⁶): ~10⁻⁸ absolute is round-off here (measured 1.5·10⁻⁸ on an
    # AVX-512 machine, under 10⁻⁹ where the old check passed); a private dimension seen by
    # the audio GPs would move the audio sum by O(1) for this 0.05 shift.
    for Z in (X, Xp):
        lp = dens(Z)[0]
        audio_part = lp - float(SwitchingLatents(plan).log_prob(torch.as_tensor(Z)))
        assert audio_part == pytest.approx(ll.sum(), rel=0, abs=1e-11 * abs(lp))
    assert dens(X)[0] != pytest.approx(dens(Xp)[0], rel=1e-9)   # the prior does see it
    assert float(pyro_log_density(plan, torch.as_tensor(Xp))) == pytest.approx(dens(Xp)[0], rel=1e-8)


def test_a_saved_switching_model_with_private_dimensions_synthesises_the_same(toy_vlmm_private, tmp_path):
    """The switching model keeps ``private_dims`` through save/load (its config and every
    state's ``view_dims``) and the loaded model's posterior is the same to the bit; its
    parameters round-trip like every estimator's."""
    from toydata import make_utterances

    from bayes_talk.estimators.registry import load_estimator

    model = toy_vlmm_private
    assert model.get_params()["private_dims"] == 1
    assert all(m.config.view_dims == {"audio": 2} for m in model.models_.values())
    loaded = load_estimator(model.save(tmp_path / "m"))
    assert loaded.config.private_dims == 1
    assert all(m.predictors_["audio"].in_dims == 2 for m in loaded.models_.values())
    s = make_utterances(1, seed=6, mean_len=20)[0]
    a, b = model.predict_dist(s, "laplace", n_draws=8, seed=0), loaded.predict_dist(s, "laplace", n_draws=8, seed=0)
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.var, b.var)
