"""The SGPDM objective against independent formulas, GPy, and finite differences."""
from __future__ import annotations

import logging
import math
import os

import numpy as np
import pytest
import torch
from scipy.stats import halfnorm, multivariate_normal

from bayes_talk.gp.kernels import rbf, train_cov
from bayes_talk.gp.linalg import CholeskyError, cholesky
from bayes_talk.gp.terms import dynamics_loglik, matrix_normal_loglik, observation_loglik
from bayes_talk.models.sgpdm import SGPDM
from bayes_talk.synthesis.latents import predict_across

f64 = torch.float64


def _np_rbf(X1, X2, a, g):
    d2 = ((X1[:, None, :] - X2[None, :, :]) ** 2).sum(-1)
    return a * np.exp(-0.5 * g * d2)


def test_observation_term_matches_columnwise_gaussians():
    rng = np.random.default_rng(1)
    N, D, d = 15, 4, 3
    X, Y = rng.normal(size=(N, d)), rng.normal(size=(N, D))
    a, g, b, w = 1.3, 0.7, 20.0, rng.uniform(0.5, 2.0, D)
    K = _np_rbf(X, X, a, g) + np.eye(N) / b
    # eq. 5 as written: N Σ ln w − ND/2 ln 2π − D/2 ln|K| − ½ tr(K⁻¹ Y W² Yᵀ)
    _, ld = np.linalg.slogdet(K)
    ref = N * np.log(w).sum() - N * D / 2 * np.log(2 * np.pi) - D / 2 * ld \
        - 0.5 * np.trace(np.linalg.solve(K, Y @ np.diag(w ** 2) @ Y.T))
    # and column by column with scipy
    ref2 = N * np.log(w).sum() + sum(multivariate_normal(np.zeros(N), K).logpdf(Y[:, m] * w[m]) for m in range(D))
    got = observation_loglik(*(torch.as_tensor(v) for v in (Y, X)), torch.tensor(a, dtype=f64),
                             torch.tensor(g, dtype=f64), torch.tensor(b, dtype=f64), torch.as_tensor(w))
    assert float(got) == pytest.approx(ref, rel=1e-12)
    assert float(got) == pytest.approx(ref2, rel=1e-12)


def test_dynamics_term_matches_formula_for_two_sequences():
    rng = np.random.default_rng(2)
    lens, d = [5, 7], 3
    X = rng.normal(size=(12, d))
    a, g, b = 0.5, 0.3, 100.0
    Xin = np.vstack([X[0:4], X[5:11]])
    Xout = np.vstack([X[1:5], X[6:12]])
    K = _np_rbf(Xin, Xin, a, g) + np.eye(10) / b
    ref = sum(multivariate_normal(np.zeros(d), np.eye(d)).logpdf(X[i]) for i in (0, 5))
    ref += sum(multivariate_normal(np.zeros(10), K).logpdf(Xout[:, j]) for j in range(d))
    got = dynamics_loglik(torch.as_tensor(X), lens, a, g, b)
    assert float(got) == pytest.approx(ref, rel=1e-12)


def test_matches_gpy_gp_regression():
    GPy = pytest.importorskip("GPy")
    rng = np.random.default_rng(3)
    N, D, d = 40, 3, 2
    X, Y = rng.normal(size=(N, d)), rng.normal(size=(N, D))
    alpha, gamma, noise_var = 1.7, 0.8, 0.05
    kern = GPy.kern.RBF(d, variance=alpha, lengthscale=1.0 / math.sqrt(gamma))
    m = GPy.models.GPRegression(X, Y, kern, noise_var=noise_var)
    gpy_ll = float(m.log_likelihood())
    # GPy adds 1e-8 to its noise variance: β = 1/(σ² + 1e-8) on our side
    beta = 1.0 / (noise_var + 1e-8)
    ours = observation_loglik(torch.as_tensor(Y), torch.as_tensor(X), torch.tensor(alpha, dtype=f64),
                              torch.tensor(gamma, dtype=f64), torch.tensor(beta, dtype=f64),
                              torch.ones(D, dtype=f64))
    assert float(ours) == pytest.approx(gpy_ll, rel=1e-8)


def test_closed_form_backward_passes_gradcheck():
    rng = np.random.default_rng(4)
    X = torch.as_tensor(rng.normal(size=(8, 2)), dtype=f64).requires_grad_(True)
    V = torch.as_tensor(rng.normal(size=(8, 3)), dtype=f64).requires_grad_(True)
    lg = torch.tensor([0.1, -0.3, 2.0], dtype=f64, requires_grad=True)

    def f(X, V, lg):
        K = train_cov(X, lg[0].exp(), lg[1].exp(), lg[2].exp())
        return matrix_normal_loglik(K, V)

    assert torch.autograd.gradcheck(f, (X, V, lg), eps=1e-6, atol=1e-6, rtol=1e-5)


def _toy(N=40, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, N)[:, None]
    audio = np.hstack([np.sin(t), np.cos(t), np.sin(2 * t), np.cos(3 * t)]) + 0.02 * rng.normal(size=(N, 4))
    video = np.hstack([np.cos(t) ** 2, np.sin(t) * np.cos(t), np.sin(3 * t)]) + 0.02 * rng.normal(size=(N, 3))
    return audio, video


@pytest.mark.parametrize("bc", [None, "audio"])
def test_log_joint_gradient_matches_finite_differences(bc):
    audio, video = _toy(20)
    m = SGPDM(latent_dim=2, max_iter=1, learn_dynamics=True, back_constraint=bc, bc_hidden=4)
    m.fit({"audio": audio, "visual": video}, seq_lengths=[8, 12])
    free = m._free_tensors()
    for t in free:
        t.requires_grad_(True)
        t.grad = None  # training left the last closure's gradient (of −L) behind
    vals = [t.detach().clone() for t in free]

    # every free tensor: X (or φ), log α/γ/β of both views and of the dynamics, log w
    names = list(m._log)
    assert {"w/audio", "w/visual", "alpha/dyn", "gamma/dyn", "beta/dyn"} <= set(names)
    # central differences on a handful of coordinates of every tensor
    m.log_joint().backward()
    grads = [t.grad.clone() for t in free]
    h = 1e-6
    for t, g, v in zip(free, grads, vals):
        flat = v.reshape(-1)
        for i in np.linspace(0, flat.numel() - 1, min(4, flat.numel())).astype(int):
            plus, minus = flat.clone(), flat.clone()
            plus[i] += h
            minus[i] -= h
            t.data = plus.reshape(v.shape)
            with torch.no_grad():
                fp = float(m.log_joint())
                t.data = minus.reshape(v.shape)
                fm = float(m.log_joint())
            t.data = v.clone()
            fd = (fp - fm) / (2 * h)
            assert float(g.reshape(-1)[i]) == pytest.approx(fd, rel=1e-4, abs=1e-4)


def test_pyro_log_joint_equals_papers_objective_term_by_term():
    audio, video = _toy(25)
    m = SGPDM(latent_dim=2, max_iter=20, learn_dynamics=True).fit(
        {"audio": audio, "visual": video}, seq_lengths=[10, 15])
    h = {k: (np.asarray(v) if np.ndim(v) else float(v)) for k, v in m.hyper_.items()}
    X = m.X_
    expected = {}
    for v, Y in (("audio", audio), ("visual", video)):
        Yc = Y - Y.mean(0)
        N, D = Yc.shape
        w = h[f"w/{v}"]
        K = _np_rbf(X, X, h[f"alpha/{v}"], h[f"gamma/{v}"]) + np.eye(N) / h[f"beta/{v}"]
        expected[f"Y/{v}"] = N * np.log(w).sum() + sum(
            multivariate_normal(np.zeros(N), K).logpdf(Yc[:, j] * w[j]) for j in range(D))
        expected[f"w/{v}"] = halfnorm(scale=1e3).logpdf(w).sum()
    Xin, Xout = np.vstack([X[0:9], X[10:24]]), np.vstack([X[1:10], X[11:25]])
    Kx = _np_rbf(Xin, Xin, h["alpha/dyn"], h["gamma/dyn"]) + np.eye(len(Xin)) / h["beta/dyn"]
    expected["X"] = sum(multivariate_normal(np.zeros(2), np.eye(2)).logpdf(X[i]) for i in (0, 10)) + sum(
        multivariate_normal(np.zeros(len(Xin)), Kx).logpdf(Xout[:, j]) for j in range(2))
    thetas = [h[f"{p}/{v}"] for v in ("audio", "visual", "dyn") for p in ("alpha", "gamma", "beta")]
    expected["hyperprior"] = -np.log(thetas).sum()
    tr = m.trace()
    got = {k: float(n["log_prob_sum"].detach()) for k, n in tr.nodes.items() if n["type"] == "sample"}
    assert set(got) == set(expected)
    for k, want in expected.items():
        assert got[k] == pytest.approx(want, rel=1e-9, abs=1e-9), k
    assert float(m.log_joint()) == pytest.approx(sum(expected.values()), rel=1e-10)


def test_hyperprior_is_in_theta_space_without_jacobian():
    """Convention (DESIGN.md §3): log θ is only the parametrisation. Doubling one α
    changes the prior term by exactly −ln 2 (a Jacobian would cancel it to 0)."""
    audio, video = _toy(15)
    m = SGPDM(latent_dim=2, max_iter=1).fit({"audio": audio, "visual": video})
    m._log = {k: v.detach() for k, v in m._log.items()}
    m._X = m._X.detach()
    prior = lambda: float(m.trace().nodes["hyperprior"]["log_prob_sum"])
    before = prior()
    m._log["alpha/audio"] = m._log["alpha/audio"] + math.log(2.0)
    assert prior() - before == pytest.approx(-math.log(2.0), abs=1e-12)


def test_balanced_dynamics_scales_the_dynamics_term():
    audio, video = _toy(15)
    plain = SGPDM(latent_dim=2, max_iter=1).fit({"audio": audio, "visual": video})
    bal = SGPDM(latent_dim=2, max_iter=1, balanced=True)
    bal.fit({"audio": audio, "visual": video}, X_init=plain.history and None)
    # same X evaluated under both models
    bal._X = plain._X.detach().clone()
    lx_plain = float(plain.trace().nodes["X"]["log_prob_sum"])
    lx_bal = float(bal.trace().nodes["X"]["log_prob_sum"])
    assert lx_bal == pytest.approx(lx_plain * (4 + 3) / 2, rel=1e-12)


def test_map_training_increases_log_joint_monotonically():
    audio, video = _toy(40)
    m = SGPDM(latent_dim=2, max_iter=200).fit({"audio": audio, "visual": video})
    hist = np.array(m.history.log_joint)
    assert len(hist) > 3
    assert np.all(np.diff(hist) >= -1e-8 * np.abs(hist[1:]))
    assert hist[-1] > hist[0]


def test_monitor_keeps_the_best_step_and_stops_after_patience():
    audio, video = _toy(40)
    scores = iter([5.0, 3.0, 4.0, 6.0, 7.0, 1.0, 1.0])
    seen = []

    def monitor(model):
        seen.append(model.X_.copy())
        return next(scores)

    m = SGPDM(latent_dim=2, max_iter=200).fit({"audio": audio, "visual": video}, monitor=monitor,
                                               monitor_every=5, patience=3)
    assert m.history.monitor == [5.0, 3.0, 4.0, 6.0, 7.0]      # stopped 3 calls after the best
    assert m.history.best_step == 2
    assert not np.allclose(seen[1], seen[-1])                  # training did move on afterwards ...
    np.testing.assert_array_equal(m.X_, seen[1])               # ... and the best step was restored
    mu, _ = m.predict_view("visual", m.X_)
    assert np.isfinite(mu).all()
    with pytest.raises(ValueError, match="patience"):
        SGPDM(latent_dim=2).fit({"audio": audio, "visual": video}, monitor=monitor, patience=0)


def test_round_trip_training_audio_recovers_visual():
    audio, video = _toy(50, seed=5)
    m = SGPDM(latent_dim=2, max_iter=200).fit({"audio": audio, "visual": video})
    mu, var, X = predict_across(m, audio, X_init="nn", method="sequence")
    rel = np.sqrt(((mu - video) ** 2).mean(0)) / video.std(0)
    assert rel.max() < 0.15, rel
    # the optimised latents are the training latents
    assert np.abs(X - m.X_).max() < 0.1 * m.X_.std()
    assert var.shape == video.shape and np.all(var > 0)


def _affine_r2(X, Z):
    A = np.hstack([X, np.ones((len(X), 1))])
    coef, *_ = np.linalg.lstsq(A, Z, rcond=None)
    res = Z - A @ coef
    return 1 - (res ** 2).sum(0) / ((Z - Z.mean(0)) ** 2).sum(0)


def test_recovers_latent_linear_dynamical_system_up_to_affine_map(record_property):
    rng = np.random.default_rng(7)
    T, th = 120, 0.12
    A = 0.995 * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    x = np.zeros((T, 2))
    x[0] = [1.0, 0.0]
    for t in range(1, T):
        x[t] = A @ x[t - 1] + 0.01 * rng.normal(size=2)
    W1, W2 = rng.normal(size=(2, 6)), rng.normal(size=(2, 5))
    audio = np.tanh(x @ W1) + 0.01 * rng.normal(size=(T, 6))
    video = np.sin(x @ W2) + 0.01 * rng.normal(size=(T, 5))
    m = SGPDM(latent_dim=2, max_iter=300).fit({"audio": audio, "visual": video})
    r2 = _affine_r2(m.X_, x)
    record_property("affine_r2", r2.tolist())
    assert r2.min() > 0.9, r2


@pytest.mark.parametrize(
    "views,lens,kw,msg",
    [
        ({"audio": np.full((5, 3), np.nan), "visual": np.zeros((5, 2))}, None, {}, "NaN or inf"),
        ({"audio": np.zeros((5, 3)), "visual": np.zeros((6, 2))}, None, {}, "different numbers of frames"),
        ({"audio": np.ones((5, 3)), "visual": np.ones((5, 2))}, [2, 2], {}, "add up to 4"),
        ({"audio": np.ones((5, 3)), "visual": np.ones((5, 2))}, None, {"latent_dim": 3}, "latent_dim=3"),
        ({"audio": np.ones((5, 3))}, None, {"back_constraint": "mfcc", "latent_dim": 2}, "'mfcc'"),
    ],
)
def test_bad_input_raises_clear_value_error(views, lens, kw, msg):
    with pytest.raises(ValueError, match=msg):
        SGPDM(**kw).fit(views, seq_lengths=lens)


def test_jitter_escalation_is_logged_and_failure_is_clear(caplog):
    X = torch.zeros(5, 2, dtype=f64)
    K = rbf(X, X, 1.0, 1.0)  # rank one: not positive definite
    with caplog.at_level(logging.WARNING, logger="bayes_talk.gp.linalg"):
        L = cholesky(K, "test matrix")
    assert torch.allclose(L @ L.mT, K, atol=1e-5)
    assert "test matrix" in caplog.text and "jitter" in caplog.text
    with pytest.raises(CholeskyError, match="NaN"):
        cholesky(torch.full((3, 3), float("nan"), dtype=f64), "bad matrix")


def test_hmm_initialiser_emissions_and_path():
    """SGPLVM B's initialiser: its (T, M) emission table equals ln p(ŷ_t | x_j) evaluated
    pair by pair, and on training audio the Viterbi path stays near the training latents."""
    from bayes_talk.synthesis.initialisers import HMMViterbi, viterbi

    audio, video = _toy(60, seed=3)
    m = SGPDM(latent_dim=2, max_iter=100).fit({"audio": audio, "visual": video})
    init = HMMViterbi(n_states=25, seed=1)
    idx, trans = init._states(m)
    mu, var = init._emission_params(m, "audio")
    p = m.predictors_["audio"]
    Y = torch.as_tensor(audio[:7])
    S = torch.as_tensor(m.X_[idx])
    with torch.no_grad():
        pairwise = p.log_lik(Y.repeat_interleave(len(idx), 0), S.repeat(7, 1)).reshape(7, len(idx))
        table = p.log_density(Y[:, None, :], mu[None], var)
    np.testing.assert_allclose(table.numpy(), pairwise.numpy(), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(np.exp(trans).sum(1), 1.0, rtol=1e-12)
    X0 = init(m, "audio", audio)
    assert X0.shape == (60, 2)
    assert all(any(np.array_equal(x, m.X_[j]) for j in idx) for x in X0)   # every point is a state
    # hand-made 2-state chain: Viterbi follows the emissions unless switching is too costly
    emit = np.log(np.array([[0.9, 0.1], [0.4, 0.6], [0.9, 0.1]]))
    sticky = np.log(np.array([[0.99, 0.01], [0.01, 0.99]]))
    free = np.log(np.full((2, 2), 0.5))
    start = np.log([0.5, 0.5])
    assert viterbi(start, free, emit).tolist() == [0, 1, 0]
    assert viterbi(start, sticky, emit).tolist() == [0, 0, 0]


def test_fused_rbf_term_matches_torch_path_and_passes_gradcheck():
    """The fused RBF pass (gp/fused.py) against autograd through train_cov + Cholesky."""
    from bayes_talk.gp.fused import rbf_matrix_normal

    rng = np.random.default_rng(11)
    X = torch.as_tensor(rng.normal(size=(60, 3))).requires_grad_(True)
    V = torch.as_tensor(rng.normal(size=(60, 5))).requires_grad_(True)
    lg = torch.tensor([0.3, -0.8, 2.5], dtype=f64, requires_grad=True)
    fused = lambda X, V, lg: rbf_matrix_normal(X, lg[0].exp(), lg[1].exp(), lg[2].exp(), V)
    ref = lambda X, V, lg: matrix_normal_loglik(train_cov(X, lg[0].exp(), lg[1].exp(), lg[2].exp()), V)
    a, b = fused(X, V, lg), ref(X, V, lg)
    assert float(a) == pytest.approx(float(b), rel=1e-12)
    for ga, gb in zip(torch.autograd.grad(a, (X, V, lg)), torch.autograd.grad(b, (X, V, lg))):
        np.testing.assert_allclose(ga.numpy(), gb.numpy(), rtol=1e-9, atol=1e-9)
    small = (X[:8].detach().clone().requires_grad_(True), V[:8].detach().clone().requires_grad_(True), lg)
    assert torch.autograd.gradcheck(fused, small, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_fused_path_falls_back_to_jitter_when_kernel_is_singular(caplog):
    """Duplicate latent points with almost no noise: dpotrf fails, the fused pass declines
    (None) and observation_loglik takes the torch path, whose Cholesky adds logged jitter."""
    from bayes_talk.gp.fused import rbf_matrix_normal

    X = torch.zeros(6, 2, dtype=f64)
    Y = torch.as_tensor(np.random.default_rng(0).normal(size=(6, 2)))
    one = torch.tensor(1.0, dtype=f64)
    assert rbf_matrix_normal(X, one, one, torch.tensor(1e30, dtype=f64), Y) is None
    with caplog.at_level(logging.WARNING, logger="bayes_talk.gp.linalg"):
        ll = observation_loglik(Y, X, one, one, torch.tensor(1e30, dtype=f64), torch.ones(2, dtype=f64))
    assert torch.isfinite(ll) and "jitter" in caplog.text


def _both_paths(fn):
    """fn() with the fused path on, then with the torch path (settings switch ``fused`` off)."""
    from bayes_talk.base import settings

    with settings.override(fused=True):
        a = fn()
    with settings.override(fused=False):
        b = fn()
    return a, b


def test_fused_default_equals_torch_path_on_the_two_view_sgpdm_log_joint():
    """The default (fused) path against the torch path on the whole objective of a
    two-view SGPDM with learned dynamics and two sequences: value and every gradient.

    The dynamics noise is 1e-4 (β_x = 1e4), not the default 1e-6: at β_x = 1e6 the dynamics
    term itself is conditioned so that both paths are 3e-13 (fused) and 5e-13 (torch)
    relative from its 40-digit value (mpmath, session 14), and the two paths differ by
    1.1e-13 to 7.4e-13 relative at the points of 2, 3 and 5 iterations, on one thread or two;
    the 1e-13 below held there only at the point that two-thread rounding happened to
    reach. At β_x = 1e4 they differ by at most 3.6e-15 (gradients 8.4e-14) at those points."""
    from bayes_talk.base import settings

    audio, video = _toy(40)
    m = SGPDM(latent_dim=3, max_iter=3, learn_dynamics=True, dyn_beta=1e4)
    with settings.override(direct_fit=False):  # the point this comparison was written at
        m.fit({"audio": audio, "visual": video}, seq_lengths=[15, 25])
    free = m._free_tensors()

    def value_and_grads():
        for t in free:
            t.grad = None
        lj = m.log_joint()
        lj.backward()
        return float(lj), [t.grad.clone() for t in free]

    (fa, ga), (fb, gb) = _both_paths(value_and_grads)
    assert fa == pytest.approx(fb, rel=1e-13, abs=1e-10)
    for x, y in zip(ga, gb):
        np.testing.assert_allclose(x.numpy(), y.numpy(), rtol=1e-9, atol=1e-9 * float(y.abs().max()))


def test_fused_threads_providers_and_repeated_backward_agree():
    """The compiled passes on two threads (N above THREADED_MIN_N) equal the one-thread
    passes bit for bit; the whole term agrees across thread counts and with scipy's
    LAPACK to round-off; a second backward through the same graph (retain_graph) gives
    the same gradients."""
    from bayes_talk.base import settings
    from bayes_talk.gp import fused, lapack
    from bayes_talk.gp.threads import torch_threads

    rng = np.random.default_rng(12)
    N = fused.THREADED_MIN_N + 31
    Xn = rng.normal(size=(N, 3))
    X = torch.as_tensor(Xn).requires_grad_(True)
    V = torch.as_tensor(rng.normal(size=(N, 4)))
    lg = torch.tensor([0.2, -0.5, 3.0], dtype=f64, requires_grad=True)
    A = rng.normal(size=(N, 4))

    def passes():
        buf = np.empty((N, N), order="F")
        fused._build(Xn, 1.3, 0.4, 0.01, buf, fused.N_CHUNKS)
        acc, sums = fused._gradient(Xn, buf, A, 1.3, fused.N_CHUNKS)
        return buf, acc, sums

    def term():
        ll = fused.rbf_matrix_normal(X, lg[0].exp(), lg[1].exp(), lg[2].exp(), V)
        g1 = torch.autograd.grad(ll, (X, lg), retain_graph=True)
        g2 = torch.autograd.grad(ll, (X, lg))
        for a, b in zip(g1, g2):
            assert torch.equal(a, b)
        return float(ll), g1

    results = {}
    for n in (1, 2):
        with torch_threads(n):
            assert fused._threads() == min(n, os.cpu_count())
            results[n] = passes(), term()
    for a, b in zip(results[1][0], results[2][0]):
        assert np.array_equal(a, b)
    with settings.override(lapack="scipy"):
        assert lapack.provider() == "scipy"
        results["scipy"] = (None, term())
    ref_ll, ref_g = results[1][1]
    for key in (2, "scipy"):
        ll, g = results[key][1]
        assert ll == pytest.approx(ref_ll, rel=1e-13)
        for a, b in zip(g, ref_g):
            np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-10, atol=1e-10 * float(b.abs().max()))
    with pytest.raises(ValueError, match="unknown LAPACK provider"):
        lapack.set_provider("netlib")


@pytest.mark.parametrize("kw", [{"learn_dynamics": True, "balanced": True}, {"dynamics": False, "learn_w": False},
                                {"dyn_linear": 0.1}])
def test_direct_log_joint_equals_the_pyro_trace_bit_for_bit(kw, monkeypatch):
    """Issue 29: the log joint is summed without running the Pyro program; value and
    gradient must be the trace's (``sgpdm_program.trace_log_joint``), bit for bit (same
    terms, same order)."""
    import bayes_talk.models.sgpdm as sgpdm_mod
    from bayes_talk.models.sgpdm_program import sgpdm_log_joint, trace_log_joint

    audio, video = _toy(30)
    m = SGPDM(latent_dim=2, max_iter=5, **kw).fit({"audio": audio, "visual": video}, seq_lengths=[12, 18])
    grads = {}
    for path, fn in (("direct", sgpdm_log_joint), ("pyro", trace_log_joint)):
        monkeypatch.setattr(sgpdm_mod, "program_log_joint", fn)
        free = m._free_tensors()
        for t in free:
            t.grad = None
        lj = m.log_joint()
        lj.backward()
        grads[path] = (float(lj.detach()), [t.grad.clone() for t in free])
    (v1, g1), (v2, g2) = grads["direct"], grads["pyro"]
    assert v1 == v2
    assert all(torch.equal(a, b) for a, b in zip(g1, g2))


def test_fit_through_the_direct_log_joint_equals_the_pyro_fit(monkeypatch):
    """The whole L-BFGS fit gives the same hyperparameters and latents by both paths."""
    import bayes_talk.models.sgpdm as sgpdm_mod
    from bayes_talk.base import settings
    from bayes_talk.models.sgpdm_program import sgpdm_log_joint, trace_log_joint

    audio, video = _toy(40)
    fits = {}
    for path, fn in (("direct", sgpdm_log_joint), ("pyro", trace_log_joint)):
        monkeypatch.setattr(sgpdm_mod, "program_log_joint", fn)
        with settings.override(direct_fit=False):  # torch's L-BFGS through autograd of the log joint
            fits[path] = SGPDM(latent_dim=2, max_iter=40).fit({"audio": audio, "visual": video},
                                                              seq_lengths=[15, 25])
    a, b = fits["direct"], fits["pyro"]
    assert np.array_equal(a.X_, b.X_)
    assert a.history.log_joint == b.history.log_joint
    for k in a.hyper_:
        assert np.array_equal(np.asarray(a.hyper_[k]), np.asarray(b.hyper_[k])), k


def test_small_problems_run_on_one_thread_whatever_torch_is_given():
    """Below ``THREADED_MIN_N`` points a term (its LAPACK calls and compiled passes) and the
    SGPDM log joint run on one thread (session 14), so on two torch threads they give the
    one-thread numbers bit for bit (MKL's two-thread ``dpotrf`` differs in the last bits
    here); the log joint through the Pyro trace still equals the direct one bit for bit."""
    import bayes_talk.models.sgpdm as sgpdm_mod
    from bayes_talk.gp import fused
    from bayes_talk.gp.threads import THREADED_MIN_N, problem_threads, torch_threads
    from bayes_talk.models.sgpdm_program import sgpdm_log_joint, trace_log_joint

    N = 300
    assert N < THREADED_MIN_N
    rng = np.random.default_rng(3)
    Y = np.tanh(rng.normal(size=(N, 4)) @ rng.normal(size=(4, 40))) + 0.1 * rng.normal(size=(N, 40))
    m = SGPDM(latent_dim=4, dynamics=False, learn_w=False, max_iter=1).fit({"y": Y})
    X = torch.as_tensor(rng.normal(size=(N, 4))).requires_grad_(True)
    lg = torch.tensor([0.1, -0.7, 2.5], dtype=f64, requires_grad=True)
    V = torch.as_tensor(Y)

    def evaluate() -> dict[str, list]:
        ll = fused.rbf_matrix_normal(X, lg[0].exp(), lg[1].exp(), lg[2].exp(), V)
        out = {"term": [float(ll), *torch.autograd.grad(ll, (X, lg))]}
        for path, fn in (("direct", sgpdm_log_joint), ("pyro", trace_log_joint)):
            sgpdm_mod.program_log_joint = fn
            free = m._free_tensors()
            for t in free:
                t.grad = None
            lj = m.log_joint()
            lj.backward()
            out[path] = [float(lj.detach()), *(t.grad.clone() for t in free)]
        return out

    def same(a: list, b: list) -> bool:
        return len(a) == len(b) and all((x == y) if isinstance(x, float) else torch.equal(x, y) for x, y in zip(a, b))

    prev = sgpdm_mod.program_log_joint
    results = {}
    try:
        for n in (1, 2):
            with torch_threads(n):
                with problem_threads(N):
                    assert torch.get_num_threads() == 1
                with problem_threads(THREADED_MIN_N):
                    assert torch.get_num_threads() == n
                assert torch.get_num_threads() == n
                results[n] = evaluate()
    finally:
        sgpdm_mod.program_log_joint = prev
    for n in (1, 2):
        assert same(results[n]["direct"], results[n]["pyro"])
    for key in ("term", "direct", "pyro"):
        assert same(results[1][key], results[2][key]), key
