"""Baselines (bayes_talk.estimators.baselines) on small synthetic Utterance objects."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize
import scipy.stats

from bayes_talk.base.errors import NotFittedError
from bayes_talk.data.utterance import Utterance
from bayes_talk.estimators.baselines import DPDS, REGISTRY, SLDS, HMMMean, VoicePuppetry
from bayes_talk.estimators.baselines.dpds import (
    dpds_forward,
    dpds_grad_A,
    dpds_loglik,
    dpds_profile,
    dpds_solve_mu_nu,
)
from bayes_talk.estimators.baselines.lds import make_batch, mean_trajectory
from bayes_talk.estimators.baselines.slds import kalman_smoother
from bayes_talk.estimators.baselines.voice_puppetry import (
    delta_features,
    delta_matrix,
    trajectory_solve,
)
from bayes_talk.features.phone_encoding import LabelEncoder

PH = ["aa", "m", "sil", "iy"]  # sorted by LabelEncoder to aa, iy, m, sil


# ----------------------------------------------------------------------------- data
def lds_sequences(rng, S, T, a, nu, q, r, mu0, first=None):
    """Sequences from a known label-switched LDS; labels index PH; mfcc correlated with aam."""
    D = a.shape[1]
    out = []
    for s in range(S):
        f = int(rng.integers(len(PH))) if first is None else first[s % len(first)]
        labs = [f] * int(rng.integers(2, 5))
        while len(labs) < T:
            labs += [int(rng.integers(len(PH)))] * int(rng.integers(3, 10))
        labs = np.array(labs[:T])
        x = np.empty((T, D))
        x[0] = mu0[labs[0]] + np.sqrt(q[labs[0]]) * rng.normal(size=D)
        for t in range(1, T):
            x[t] = a[labs[t]] * x[t - 1] + nu[labs[t]] + np.sqrt(q[labs[t]]) * rng.normal(size=D)
        z = x + np.sqrt(r) * rng.normal(size=(T, D))
        mfcc = z @ rng.normal(size=(D, 4)) + 0.1 * rng.normal(size=(T, 4))
        out.append(Utterance(f"lds{s}", mfcc, z, [PH[i] for i in labs]))
    return out


def true_params(rng, D=2):
    a = rng.uniform(0.5, 0.9, (len(PH), D))
    nu = rng.normal(size=(len(PH), D))
    mu0 = rng.normal(size=(len(PH), D))
    return a, nu, mu0


def reorder(enc: LabelEncoder, arr: np.ndarray) -> np.ndarray:
    """Model parameters (encoder order) -> PH order."""
    return arr[[enc.index_[p] for p in PH]]


# ----------------------------------------------------------------------------- Voice Puppetry
def test_delta_matrix_is_central_difference_with_replicated_ends():
    z = np.array([[1.0], [4.0], [9.0], [16.0]])
    want = np.array([[1.5], [4.0], [6.0], [3.5]])  # (4-1)/2, (9-1)/2, (16-4)/2, (16-9)/2
    np.testing.assert_allclose(delta_matrix(4) @ z, want, rtol=0, atol=1e-15)
    np.testing.assert_allclose(delta_features(z)[:, 1:], want, rtol=0, atol=1e-15)
    assert delta_matrix(1).nnz == 0


def _dense_W(T, D):
    """Frame-major dense observation map z (TD) -> [z_t, Δz_t]_t (2TD)."""
    Dm = delta_matrix(T).toarray()
    W = np.zeros((2 * D * T, D * T))
    for t in range(T):
        W[2 * D * t:2 * D * t + D, D * t:D * (t + 1)] = np.eye(D)
        for s in range(T):
            W[2 * D * t + D:2 * D * (t + 1), D * s:D * (s + 1)] = Dm[t, s] * np.eye(D)
    return W


@pytest.mark.parametrize("kind", ["diag", "full"])
def test_banded_trajectory_solve_equals_dense_solve(kind):
    rng = np.random.default_rng(3)
    T, D = 40, 3
    mean = rng.normal(size=(T, 2 * D))
    if kind == "diag":
        cov = rng.uniform(0.2, 3.0, size=(T, 2 * D))
        prec = [np.diag(1 / c) for c in cov]
    else:
        G = rng.normal(size=(T, 2 * D, 2 * D))
        cov = G @ G.transpose(0, 2, 1) + 0.5 * np.eye(2 * D)
        prec = [np.linalg.inv(c) for c in cov]
    W = _dense_W(T, D)
    Lam = scipy.linalg.block_diag(*prec)
    z_dense = np.linalg.solve(W.T @ Lam @ W, W.T @ Lam @ mean.ravel()).reshape(T, D)
    z = trajectory_solve(mean, cov)
    assert np.max(np.abs(z - z_dense)) <= 1e-10 * max(1.0, np.max(np.abs(z_dense)))


def test_trajectory_solve_rejects_bad_shapes():
    with pytest.raises(ValueError, match="shape"):
        trajectory_solve(np.zeros((5, 3)), np.ones((5, 3)))
    with pytest.raises(ValueError, match="cov must have shape"):
        trajectory_solve(np.zeros((5, 4)), np.ones((5, 3)))
    with pytest.raises(ValueError, match="positive"):
        trajectory_solve(np.zeros((5, 4)), -np.ones((5, 4)))


def hmm_sequences(rng, S, T, mz, my, trans, noise_z=0.3, noise_y=0.5):
    K = len(trans)
    seqs, states = [], []
    for s in range(S):
        st = [int(rng.integers(K))]
        for _ in range(1, T):
            st.append(int(rng.choice(K, p=trans[st[-1]])))
        st = np.array(st)
        z = mz[st] + noise_z * rng.normal(size=(T, mz.shape[1]))
        y = my[st] + noise_y * rng.normal(size=(T, my.shape[1]))
        seqs.append(Utterance(f"hmm{s}", y, z, ["sil"] * T))
        states.append(st)
    return seqs, states


@pytest.fixture(scope="module")
def hmm_world():
    rng = np.random.default_rng(0)
    K, Dz, Dy = 4, 3, 5
    mz = 3 * rng.normal(size=(K, Dz))
    my = mz @ rng.normal(size=(Dz, Dy)) + rng.normal(size=(K, Dy))  # audio correlated with face
    trans = np.full((K, K), 0.1 / (K - 1))
    np.fill_diagonal(trans, 0.9)
    train, _ = hmm_sequences(rng, 10, 80, mz, my, trans)
    test, test_states = hmm_sequences(rng, 5, 80, mz, my, trans)
    return {"K": K, "mz": mz, "train": train, "test": test, "states": test_states}


def test_voice_puppetry_recovers_state_path(hmm_world):
    K = hmm_world["K"]
    vp = VoicePuppetry(n_states=K, random_state=0).fit(hmm_world["train"])
    dec = np.concatenate([vp.decode_states(s) for s in hmm_world["test"]])
    true = np.concatenate(hmm_world["states"])
    conf = np.zeros((K, K))
    np.add.at(conf, (true, dec), 1)
    r, c = scipy.optimize.linear_sum_assignment(-conf)
    assert conf[r, c].sum() / true.size >= 0.9
    # the generated trajectory is close to the true state means (oracle error 0.3 = noise)
    seq, st = hmm_world["test"][0], hmm_world["states"][0]
    z = vp.predict(seq)
    assert z.shape == seq.aam.shape
    assert np.sqrt(np.mean((z - hmm_world["mz"][st]) ** 2)) < 0.3


def test_voice_puppetry_seeded_and_full_covariances(hmm_world):
    train = hmm_world["train"][:4]
    a = VoicePuppetry(n_states=3, n_iter=5, random_state=7).fit(train)
    b = VoicePuppetry(n_states=3, n_iter=5, random_state=7).fit(train)
    np.testing.assert_array_equal(a.visual_means_, b.visual_means_)
    np.testing.assert_array_equal(a.predict(train[0]), b.predict(train[0]))
    f = VoicePuppetry(n_states=3, n_iter=5, visual_covariance="full", audio_covariance="diag",
                      random_state=7).fit(train)
    assert f.visual_covars_.shape == (3, 6, 6) and f.audio_covars_.shape == (3, 10)
    assert np.all(np.isfinite(f.predict(train[1])))
    with pytest.raises(NotImplementedError):
        a.log_likelihood(train[0])
    bad = Utterance("bad", np.zeros((6, 4)), None, ["sil"] * 6)
    with pytest.raises(ValueError, match=r"expected \(T, 5\)"):
        a.predict(bad)


# ----------------------------------------------------------------------------- SLDS
def _dense_lds(A, nu, Q, R, mu0, P0, idx, y):
    """Joint Gaussian of one sequence, per dimension: log-lik, posterior mean/var/cross-cov."""
    T, D = y.shape
    mean = mean_trajectory(A, nu, mu0, idx)
    ll, pm, pv, pc = 0.0, np.empty((T, D)), np.empty((T, D)), np.zeros((T, D))
    for d in range(D):
        V = np.empty(T)
        V[0] = P0[d]
        for t in range(1, T):
            V[t] = A[idx[t], d] ** 2 * V[t - 1] + Q[idx[t], d]
        K = np.empty((T, T))
        for t in range(T):
            for s in range(t + 1):
                K[t, s] = K[s, t] = np.prod(A[idx[s + 1:t + 1], d]) * V[s]
        Ky = K + R[d] * np.eye(T)
        ll += scipy.stats.multivariate_normal(mean[:, d], Ky).logpdf(y[:, d])
        G = K @ np.linalg.inv(Ky)
        pm[:, d] = mean[:, d] + G @ (y[:, d] - mean[:, d])
        post = K - G @ K
        pv[:, d] = np.diag(post)
        pc[1:, d] = np.diag(post, -1)
    return ll, pm, pv, pc


def test_kalman_smoother_equals_dense_gaussian():
    rng = np.random.default_rng(5)
    P, D, T = 3, 2, 12
    A, nu, mu0 = rng.uniform(-0.9, 0.9, (P, D)), rng.normal(size=(P, D)), rng.normal(size=(P, D))
    Q, R, P0 = rng.uniform(0.1, 1, (P, D)), rng.uniform(0.1, 1, D), rng.uniform(0.5, 2, D)
    idx = rng.integers(P, size=T)
    y = rng.normal(size=(T, D))
    ll, pm, pv, pc = _dense_lds(A, nu, Q, R, mu0, P0, idx, y)
    # batch with a longer second sequence, so the first one is padded
    idx2, y2 = rng.integers(P, size=T + 5), rng.normal(size=(T + 5, D))
    es = kalman_smoother(make_batch([idx, idx2], [y, y2]), A, nu, Q, R, mu0, P0)
    assert es["loglik"][0] == pytest.approx(ll, abs=1e-9)
    np.testing.assert_allclose(es["m"][:T, 0], pm, rtol=0, atol=1e-9)
    np.testing.assert_allclose(es["P"][:T, 0], pv, rtol=0, atol=1e-9)
    np.testing.assert_allclose(es["C"][:T, 0], pc, rtol=0, atol=1e-9)
    assert es["loglik"][1] == pytest.approx(_dense_lds(A, nu, Q, R, mu0, P0, idx2, y2)[0], abs=1e-9)


@pytest.fixture(scope="module")
def slds_fit():
    rng = np.random.default_rng(1)
    a, nu, mu0 = true_params(rng)
    q, r = np.full((len(PH), 2), 0.05), np.full(2, 0.02)
    train = lds_sequences(rng, 20, 100, a, nu, q, r, mu0)
    model = SLDS(n_iter=40, tol=0.0).fit(train)
    return model, a, nu, train


def test_slds_em_never_decreases_likelihood(slds_fit):
    h = slds_fit[0].loglik_history_
    assert h.size == 41
    assert np.all(np.diff(h) >= -1e-9 * np.abs(h[1:]))
    assert h[-1] > h[0]


def test_slds_recovers_known_system(slds_fit):
    model, a, nu, _ = slds_fit
    # 20 x 100 frames, q = 0.05: standard errors of a, ν are ~0.01-0.02
    assert np.max(np.abs(reorder(model.encoder_, model.A_) - a)) < 0.05
    assert np.max(np.abs(reorder(model.encoder_, model.nu_) - nu)) < 0.1


def test_slds_predict_and_loglik(slds_fit):
    model, _, _, train = slds_fit
    seq = train[0]
    idx = model.encoder_.encode(seq.labels)
    np.testing.assert_allclose(model.predict(seq), mean_trajectory(model.A_, model.nu_, model.mu0_, idx))
    ll = model.log_likelihood(seq)
    ref = _dense_lds(model.A_, model.nu_, model.Q_, model.R_, model.mu0_, model.P0_, idx, seq.aam)[0]
    assert ll == pytest.approx(ref, abs=1e-8)


# ----------------------------------------------------------------------------- DPDS
@pytest.fixture(scope="module")
def small_batch():
    rng = np.random.default_rng(11)
    P, D = 3, 2
    labels = [rng.integers(P, size=n) for n in (25, 30, 18, 22)]
    for s, f in enumerate((0, 1, 2, 0)):  # every label starts a sequence: all μ identifiable
        labels[s][0] = f
    Y = [rng.normal(size=(len(l), D)) for l in labels]
    A = rng.uniform(0.3, 0.9, (P, D))
    return {"b": make_batch(labels, Y), "A": A, "nu": rng.normal(size=(P, D)),
            "mu": rng.normal(size=(P, D)), "R": rng.uniform(0.5, 2, D), "P": P, "D": D}


def test_dpds_gradient_matches_finite_differences(small_batch):
    sb = small_batch
    b, A, nu, mu, R = sb["b"], sb["A"], sb["nu"], sb["mu"], sb["R"]
    g = dpds_grad_A(A, nu, mu, R, b)
    h = 1e-6
    num = np.zeros_like(A)
    for i in np.ndindex(A.shape):
        Ap, Am = A.copy(), A.copy()
        Ap[i] += h
        Am[i] -= h
        num[i] = (dpds_loglik(Ap, nu, mu, R, b) - dpds_loglik(Am, nu, mu, R, b)) / (2 * h)
    np.testing.assert_allclose(g, num, rtol=1e-6, atol=1e-6 * np.abs(num).max())


def test_dpds_profile_gradient_matches_finite_differences(small_batch):
    sb = small_batch
    b, A = sb["b"], sb["A"]
    zero, floor = np.zeros_like(A), np.full(sb["D"], 1e-12)
    _, g, _, _, _ = dpds_profile(A, b, zero, zero, floor)
    h = 1e-6
    num = np.zeros_like(A)
    for i in np.ndindex(A.shape):
        Ap, Am = A.copy(), A.copy()
        Ap[i] += h
        Am[i] -= h
        num[i] = (dpds_profile(Ap, b, zero, zero, floor)[0] - dpds_profile(Am, b, zero, zero, floor)[0]) / (2 * h)
    np.testing.assert_allclose(g, num, rtol=1e-5, atol=1e-5 * np.abs(num).max())


def test_dpds_closed_form_mu_nu_is_the_optimum(small_batch):
    sb = small_batch
    b, A, P, D = sb["b"], sb["A"], sb["P"], sb["D"]
    zero = np.zeros((P, D))
    mu, nu = dpds_solve_mu_nu(A, b, zero, zero)

    def rss(theta):
        m, n = theta[:P * D].reshape(P, D), theta[P * D:].reshape(P, D)
        r = (b.Y - dpds_forward(A, n, m, b))[b.M]
        return np.sum(r * r)

    res = scipy.optimize.minimize(rss, np.zeros(2 * P * D), method="BFGS", options={"gtol": 1e-10})
    closed = np.concatenate([mu.ravel(), nu.ravel()])
    assert rss(closed) <= res.fun + 1e-10
    np.testing.assert_allclose(closed, res.x, rtol=0, atol=1e-5)


def test_dpds_recovers_known_system_and_generates_without_reset():
    rng = np.random.default_rng(2)
    a, nu, mu0 = true_params(rng)
    q, r = np.full((len(PH), 2), 0.0), np.full(2, 0.02)
    train = lds_sequences(rng, 12, 80, a, nu, q, r, mu0, first=[2])  # all start with "sil"
    model = DPDS().fit(train)
    assert np.all(np.diff(model.loglik_history_) >= -1e-9 * np.abs(model.loglik_history_[1:]))
    assert np.max(np.abs(reorder(model.encoder_, model.A_) - a)) < 0.02
    assert np.max(np.abs(reorder(model.encoder_, model.nu_) - nu)) < 0.05
    assert np.max(np.abs(model.mu_[model.encoder_.index_["sil"]] - mu0[2])) < 0.2
    np.testing.assert_allclose(model.R_, r, rtol=0.25)
    # generation: a new phone continues the state (x_t = A x_{t-1} + ν), no reset to μ
    seq = Utterance("gen", np.zeros((6, 4)), None, ["sil"] * 3 + ["aa"] * 3)
    z = model.predict(seq)
    i_sil, i_aa = model.encoder_.index_["sil"], model.encoder_.index_["aa"]
    x = model.mu_[i_sil]
    np.testing.assert_allclose(z[0], x)
    for t in (1, 2):
        x = model.A_[i_sil] * x + model.nu_[i_sil]
        np.testing.assert_allclose(z[t], x)
    np.testing.assert_allclose(z[3], model.A_[i_aa] * x + model.nu_[i_aa])
    # test log-likelihood: Gaussian residuals under R
    s0 = train[0]
    want = scipy.stats.norm(model.predict(s0), np.sqrt(model.R_)).logpdf(s0.aam).sum()
    assert model.log_likelihood(s0) == pytest.approx(want, abs=1e-8)


# ----------------------------------------------------------------------------- HMM mean
def test_hmm_mean_by_hand():
    z = np.array([[0.0, 1.0], [2.0, 3.0], [4.0, 5.0], [10.0, 10.0]])
    train = [Utterance("a", np.zeros((4, 2)), z, ["sil", "sil", "aa", "aa"]),
             Utterance("b", np.zeros((2, 2)), np.array([[6.0, 7.0], [1.0, 1.0]]), ["aa", "sil"])]
    m = HMMMean().fit(train)
    test = Utterance("t", np.zeros((3, 2)), np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]),
                    ["aa", "sil", "m"])
    # 'm' unseen, no phone of its viseme seen: the most frequent phone (sil and aa tie at 3
    # frames; the alphabetically first wins), the package's one unseen-phone policy
    with pytest.warns(UserWarning, match="not seen in training.*'m'->'aa'"):
        pred = m.predict(test)
    np.testing.assert_allclose(pred, [[20 / 3, 22 / 3], [1.0, 5 / 3], [20 / 3, 22 / 3]])
    # log-likelihood: per-phone diagonal Gaussians with ML variances
    sil = np.array([[0.0, 1.0], [2.0, 3.0], [1.0, 1.0]])
    want = scipy.stats.norm(sil.mean(0), sil.std(0)).logpdf([1.0, 1.0]).sum()
    aa = np.array([[4.0, 5.0], [10.0, 10.0], [6.0, 7.0]])
    want += scipy.stats.norm(aa.mean(0), aa.std(0)).logpdf([0.0, 0.0]).sum()
    one = Utterance("t2", np.zeros((2, 2)), np.array([[0.0, 0.0], [1.0, 1.0]]), ["aa", "sil"])
    assert m.log_likelihood(one) == pytest.approx(want, abs=1e-12)


# ----------------------------------------------------------------------------- interface
def test_registry_and_bad_inputs(slds_fit):
    assert set(REGISTRY) == {"voice-puppetry", "slds", "dpds", "hmm-mean", "context-ridge", "context-mlp"}
    assert all(cls.name == key for key, cls in REGISTRY.items())
    good = slds_fit[3][:2]
    no_aam = Utterance("x", np.zeros((5, 4)), None, ["sil"] * 5)
    bad_label = Utterance("y", np.zeros((5, 4)), np.zeros((5, 2)), ["sil", "sil", "qq", "sil", "sil"])
    for cls in (SLDS, DPDS, HMMMean):
        with pytest.raises(ValueError, match="at least 1"):
            cls().fit([])
        with pytest.raises(ValueError, match="aam is None"):
            cls().fit(good + [no_aam])
        with pytest.raises(ValueError, match="unknown phone label 'qq'"):
            cls().fit(good + [bad_label])
    wide = Utterance("w", np.zeros((5, 4)), np.zeros((5, 3)), ["sil"] * 5)
    with pytest.raises(ValueError, match="aam has 3 columns, expected 2"):
        HMMMean().fit(good + [wide])
    model = slds_fit[0]
    with pytest.raises(ValueError, match="unknown phone label 'qq'"):
        model.predict(bad_label)
    with pytest.raises(ValueError, match="no ground-truth aam"):
        model.log_likelihood(no_aam)
    with pytest.raises(ValueError, match=r"expected \(T, 2\)"):
        model.log_likelihood(wide)
    with pytest.raises(NotFittedError, match="not fitted"):
        DPDS().predict(no_aam)


def test_unseen_phone_replaced_by_viseme_mate(slds_fit):
    model = slds_fit[0]
    seq = Utterance("u", np.zeros((3, 4)), None, ["b", "b", "aa"])  # b ~ m (viseme p_b_m)
    with pytest.warns(UserWarning, match="'b'->'m'"):
        z = model.predict(seq)
    same = Utterance("v", np.zeros((3, 4)), None, ["m", "m", "aa"])
    np.testing.assert_allclose(z, model.predict(same))
