"""The sparse SGPDM (issue 14): exactness at Z = X, the bound, gradients, predictive, fit, I/O."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from test_gp_core import _toy

from bayes_talk.gp.kernels import rbf, train_cov
from bayes_talk.gp.predictive import GPPredictor
from bayes_talk.gp.sparse import fitc_loglik, sparse_predictor, titsias_bound
from bayes_talk.gp.terms import matrix_normal_loglik
from bayes_talk.models.sgpdm import SGPDM
from bayes_talk.models.sparse_sgpdm import SparseSGPDM
from bayes_talk.synthesis.latents import predict_across

f64 = torch.float64


def _points(N=25, M=7, D=3, seed=1):
    rng = np.random.default_rng(seed)
    X = torch.as_tensor(rng.normal(size=(N, 2)))
    Z = torch.as_tensor(rng.normal(size=(M, 2)))
    V = torch.as_tensor(rng.normal(size=(N, D)))
    return X, Z, V


def test_bounds_are_exact_at_z_equal_x_and_below_exact_otherwise():
    X, Z, V = _points()
    a, g, b = 1.3, 0.7, 20.0
    exact = float(matrix_normal_loglik(train_cov(X, a, g, b), V))
    assert float(titsias_bound(V, X, X, a, g, b, jitter=0.0)) == pytest.approx(exact, rel=1e-10)
    assert float(fitc_loglik(V, X, X, a, g, b, jitter=0.0)) == pytest.approx(exact, rel=1e-10)
    # Titsias: a lower bound for every Z, tighter with more inducing points (Z nested)
    rng = np.random.default_rng(5)
    more = torch.cat([Z, torch.as_tensor(rng.normal(size=(10, 2)))])
    lo, hi = (float(titsias_bound(V, X, z, a, g, b, jitter=0.0)) for z in (Z, more))
    assert lo < hi < exact


def test_fitc_equals_its_dense_formula():
    X, Z, V = _points()
    a, g, b = 0.8, 1.1, 50.0
    Knm, Kmm = rbf(X, Z, a, g), rbf(Z, Z, a, g)
    Q = Knm @ torch.linalg.solve(Kmm, Knm.mT)
    C = Q + torch.diag(a - Q.diagonal() + 1.0 / b)
    ref = float(matrix_normal_loglik(C, V))
    assert float(fitc_loglik(V, X, Z, a, g, b, jitter=0.0)) == pytest.approx(ref, rel=1e-10)


@pytest.mark.parametrize("term", [titsias_bound, fitc_loglik])
def test_sparse_terms_gradients_pass_gradcheck(term):
    X, Z, V = _points(N=10, M=4, D=2)
    X, Z = X.clone().requires_grad_(True), Z.clone().requires_grad_(True)
    lg = torch.tensor([0.1, -0.3, 2.0], dtype=f64, requires_grad=True)

    def f(X, Z, lg):
        return term(V, X, Z, lg[0].exp(), lg[1].exp(), lg[2].exp(), 1e-6)

    assert torch.autograd.gradcheck(f, (X, Z, lg), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_sparse_predictor_matches_exact_at_z_equal_x_and_titsias_formula_otherwise():
    X, Z, V = _points(N=20, M=6)
    a, g, b = 1.1, 0.9, 30.0
    Xs = torch.as_tensor(np.random.default_rng(3).normal(size=(5, 2)))
    exact = GPPredictor(X, V, a, g, b)
    sp = sparse_predictor(X, V, X, a, g, b, jitter=0.0)
    for got, ref in zip(sp.mean_var(Xs), exact.mean_var(Xs)):
        np.testing.assert_allclose(got.numpy(), ref.numpy(), rtol=1e-7, atol=1e-9)
    # M < N: Titsias §3, μ = β k_xm Σ K_mn V, σ² = k_xx − k_xm (K_mm⁻¹ − Σ) k_mx + β⁻¹
    Kmm, Kmn, kx = rbf(Z, Z, a, g), rbf(Z, X, a, g), rbf(Xs, Z, a, g)
    S = torch.linalg.inv(Kmm + b * Kmn @ Kmn.mT)
    mu = b * kx @ S @ Kmn @ V
    var = a - ((kx @ (torch.linalg.inv(Kmm) - S)) * kx).sum(1) + 1.0 / b
    got_mu, got_var = sparse_predictor(X, V, Z, a, g, b, jitter=0.0).mean_var(Xs)
    np.testing.assert_allclose(got_mu.numpy(), mu.numpy(), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(got_var.numpy(), var.numpy(), rtol=1e-8)


def test_sparse_log_joint_equals_exact_sgpdm_with_all_frames_as_inducing_points():
    audio, video = _toy(30)
    views, lens = {"audio": audio, "visual": video}, [12, 18]
    kw = {"latent_dim": 2, "learn_dynamics": True, "dyn_alpha": 1.0, "dyn_gamma": 2.0, "dyn_beta": 100.0, "init_scale": 1.0}
    exact = SGPDM(max_iter=5, **kw).fit(views, seq_lengths=lens)
    sp = SparseSGPDM(max_iter=1, n_inducing=1000, jitter=0.0, **kw).fit(views, seq_lengths=lens)
    with torch.no_grad():
        for k in exact._log:
            sp._log[k].copy_(exact._log[k])
        sp._X.copy_(exact._X)
        sp._Z.copy_(exact._X)
        got = {k: float(v) for k, v in sp.terms().items()}
    want = {k: float(n["log_prob_sum"].detach()) for k, n in exact.trace().nodes.items() if n["type"] == "sample"}
    assert set(got) == set(want)
    for k, w in want.items():
        assert got[k] == pytest.approx(w, rel=1e-9), k
    assert float(sp.trace().log_prob_sum().detach()) == pytest.approx(float(exact.log_joint().detach()), rel=1e-9)


def test_fit_improves_the_bound_and_round_trips_training_audio():
    audio, video = _toy(50, seed=5)
    m = SparseSGPDM(latent_dim=2, n_inducing=12, max_iter=100).fit({"audio": audio, "visual": video})
    hist = np.array(m.history.log_joint)
    assert len(hist) > 3 and np.all(np.diff(hist) >= -1e-8 * np.abs(hist[1:])) and hist[-1] > hist[0]
    assert m.Z_.shape == (12, 2)
    mu, var, _X = predict_across(m, audio, X_init="nn", method="sequence")
    rel = np.sqrt(((mu - video) ** 2).mean(0)) / video.std(0)
    assert rel.max() < 0.25, rel
    assert var.shape == video.shape and np.all(var > 0)


def test_save_load_round_trip_and_format_check(tmp_path):
    audio, video = _toy(30, seed=2)
    m = SparseSGPDM(latent_dim=2, n_inducing=8, max_iter=20).fit({"audio": audio, "visual": video},
                                                                  seq_lengths=[10, 20])
    path = m.save(tmp_path / "sparse")
    assert path.with_suffix(".npz").exists() and path.suffix == ".json"
    back = SparseSGPDM.load(tmp_path / "sparse")
    np.testing.assert_array_equal(back.Z_, m.Z_)
    np.testing.assert_array_equal(back.X_, m.X_)
    Xs = m.X_[:5] + 0.01
    for a, b in zip(m.predict_view("visual", Xs), back.predict_view("visual", Xs)):
        np.testing.assert_allclose(a, b, rtol=1e-12)
    exact = SGPDM(latent_dim=2, max_iter=1).fit({"audio": audio, "visual": video})
    exact.save(tmp_path / "exact")
    with pytest.raises(ValueError, match="bayes_talk.sparse_sgpdm"):
        SparseSGPDM.load(tmp_path / "exact")
    with pytest.raises(ValueError, match="back-constraint"):
        SparseSGPDM(back_constraint="audio")
