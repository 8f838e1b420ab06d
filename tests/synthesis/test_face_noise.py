"""The face's observation term (bayes_talk.synthesis.face_noise) and its held-out fit
(bayes_talk.calibration.noise_fit): the predictive (N2) is the Student-t convolution it
claims to be, the fit recovers the parameters of data drawn from (N1), the term travels
with a saved model, and the Pyro program's face sites draw the same distribution."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats

from bayes_talk.calibration.noise_fit import fit_face_noise
from bayes_talk.data.phones import PHONE_TO_VISEME
from bayes_talk.synthesis.face_noise import (
    GAUSSIAN_NU,
    MIN_COMPONENTS,
    N_CLASSES,
    FaceNoise,
    frame_classes,
    mixing_scales,
)
from bayes_talk.synthesis.result import SynthesisResult


def _noise(D, shrink=1.0, gp_scale=1.0, scale=1.0, dof=GAUSSIAN_NU, offsets=None):
    return FaceNoise(np.full(D, shrink, float), np.full(D, gp_scale, float), np.full(D, scale, float),
                     np.full(D, dof, float), np.zeros((N_CLASSES, D)) if offsets is None else offsets,
                     np.ones(D))


def test_frame_classes_are_visemes():
    g = frame_classes(["sil", "p", "aa", "m", "zz", "ah+t"])
    assert g.tolist() == [0, PHONE_TO_VISEME["p"], PHONE_TO_VISEME["aa"], PHONE_TO_VISEME["m"], 0,
                          PHONE_TO_VISEME["ah"]]


def test_gaussian_term_adds_its_variance_and_shrinks_towards_the_mean_function():
    rng = np.random.default_rng(0)
    T, D = 7, 3
    mean, var, c = rng.normal(size=(T, D)), rng.uniform(0.1, 1, (T, D)), rng.normal(size=(T, D))
    point = SynthesisResult.gaussian(mean, var, method="map", mean_function=c)
    out = _noise(D, shrink=0.4, gp_scale=2.0, scale=0.5).apply(point, ["sil"] * T)
    assert out.n_draws == MIN_COMPONENTS
    np.testing.assert_allclose(out.mean, c + 0.4 * (mean - c), rtol=1e-12)
    np.testing.assert_allclose(out.var, 2.0 * var + 0.25, rtol=1e-12)    # λ = 1: N(0, τ²) added
    with pytest.raises(ValueError, match="already carries"):
        _noise(D).apply(out, ["sil"] * T)


def test_student_t_term_has_student_t_quantiles_and_class_scales():
    T, D = 200, 2
    offsets = np.zeros((N_CLASSES, D))
    offsets[PHONE_TO_VISEME["p"]] = np.log(3.0)
    point = SynthesisResult.gaussian(np.zeros((T, D)), np.zeros((T, D)), method="map")
    labels = ["aa"] * (T // 2) + ["p"] * (T // 2)
    out = _noise(D, scale=0.7, dof=4.0, offsets=offsets).apply(point, labels)
    lo, hi = out.interval(0.9)
    want = stats.t.ppf(0.95, 4.0) * 0.7
    np.testing.assert_allclose(hi[: T // 2], want, rtol=0.03)
    np.testing.assert_allclose(hi[T // 2:], 3 * want, rtol=0.03)
    np.testing.assert_allclose(lo, -hi, rtol=1e-6)
    y = np.full((T, D), 1.3)
    np.testing.assert_allclose(out.logpdf(y)[: T // 2], stats.t.logpdf(1.3, 4.0, scale=0.7), atol=0.02)


def test_mixing_scales_are_stratified_and_seeded():
    lam = mixing_scales(np.array([3.0, GAUSSIAN_NU]), (64, 5, 2), seed=1)
    q = stats.invgamma.ppf((np.arange(64) + 0.5) / 64, 1.5, scale=1.5)
    np.testing.assert_allclose(np.sort(lam[:, 2, 0]), q)               # every entry holds every stratum
    assert np.all(lam[:, :, 1] == 1.0)
    np.testing.assert_array_equal(lam, mixing_scales(np.array([3.0, GAUSSIAN_NU]), (64, 5, 2), seed=1))
    assert not np.array_equal(lam, mixing_scales(np.array([3.0, GAUSSIAN_NU]), (64, 5, 2), seed=2))


def test_round_trip_and_bad_files():
    D = 3
    n = _noise(D, shrink=0.3, scale=0.2, dof=5.0)
    n.info = {"n_utterances": 4}
    back = FaceNoise.from_dict(n.to_dict())
    for k in ("shrink", "gp_scale", "scale", "dof", "class_offset", "control_var"):
        np.testing.assert_array_equal(getattr(back, k), getattr(n, k))
    bad = n.to_dict() | {"version": 99}
    with pytest.raises(ValueError, match="version"):
        FaceNoise.from_dict(bad)
    with pytest.raises(ValueError, match="class_offset"):
        FaceNoise.from_dict(n.to_dict() | {"class_offset": [[0.0] * D]})
    with pytest.raises(ValueError, match="scale"):
        FaceNoise(np.ones(D), np.ones(D), np.zeros(D), np.ones(D), np.zeros((N_CLASSES, D)), np.ones(D))


def _held_out(n_utt, T, D, a, tau, nu, seed):
    """Syntheses of K = 8 draws whose mean part beyond c predicts the truth with factor a, the
    rest Student-t(ν, τ); the GP variance is zero (so that τ and ν alone carry the errors)."""
    rng = np.random.default_rng(seed)
    results, truths, labels = [], [], []
    for _ in range(n_utt):
        c = rng.normal(size=(T, D))
        signal = rng.normal(size=(T, D))
        draws = c + signal / a + 0.05 * rng.normal(size=(1, 8, T, D))      # the latent path over-varies
        y = c + signal + tau * stats.t.rvs(nu, size=(T, D), random_state=rng)
        results.append(SynthesisResult("laplace", None, draws, np.zeros_like(draws), mean_function=c))
        truths.append(y)
        labels.append(["aa"] * T)
    return results, truths, labels


def test_fit_recovers_shrinkage_scale_and_heavy_tails():
    D = 2
    results, truths, labels = _held_out(20, 60, D, a=0.5, tau=0.3, nu=3.0, seed=0)
    n = fit_face_noise(results, truths, labels, frame_step=1)
    np.testing.assert_allclose(n.shrink, 0.5, atol=0.05)
    eff = n.scale * np.exp(n.class_offset[PHONE_TO_VISEME["aa"]])
    np.testing.assert_allclose(eff, 0.3, rtol=0.15)
    assert np.all(n.dof <= 7.0)                         # heavy tails found, not the Gaussian
    assert 0.86 <= n.info["coverage"]["0.9"] <= 0.94
    # held-out utterances drawn alike: the fitted term covers them at its level
    r2, t2, l2 = _held_out(10, 60, D, a=0.5, tau=0.3, nu=3.0, seed=1)
    hits = [(y >= lo) & (y <= hi) for r, y, lab in zip(r2, t2, l2) for lo, hi in [n.apply(r, lab).interval(0.9)]]
    assert 0.86 <= np.concatenate(hits).mean() <= 0.94
    # Gaussian errors: the Gaussian (or a large ν) is chosen
    results, truths, labels = _held_out(20, 60, D, a=1.0, tau=0.3, nu=1e9, seed=2)
    assert np.all(fit_face_noise(results, truths, labels, frame_step=1).dof >= 15.0)


def test_fit_with_fixed_shrinkage_and_ablations():
    results, truths, labels = _held_out(8, 40, 2, a=0.5, tau=0.3, nu=5.0, seed=3)
    n = fit_face_noise(results, truths, labels, ablations=True)
    ab = {k: FaceNoise.from_dict(v) for k, v in n.info["ablations"].items()}
    assert set(ab) == {"context-only", "unshrunk"}
    np.testing.assert_array_equal(ab["context-only"].shrink, 0.0)
    np.testing.assert_array_equal(ab["context-only"].gp_scale, 0.0)
    np.testing.assert_array_equal(ab["unshrunk"].shrink, 1.0)
    # the full model explains the truth better than either ablation, on the data it was fitted on
    assert n.info["log_score_per_entry"] > max(a.info["log_score_per_entry"] for a in ab.values())


def test_pyro_face_sites_draw_the_predictive_of_apply(toy_vlmm):
    """The face_gp / face sites of the Pyro program at a fixed path X give the distribution
    FaceNoise.apply describes for the point synthesis at X (quantiles of 4000 draws)."""
    import pyro
    from toydata import make_utterances

    from bayes_talk.posterior.sampling import visual_predictive
    from bayes_talk.synthesis.joint import face_model, make_plan

    utt = make_utterances(1, seed=7)[0]
    plan = make_plan(toy_vlmm, utt.mfcc, utt.labels)
    X = np.random.default_rng(0).normal(size=(plan.n_frames, plan.latent_dim))
    D = toy_vlmm.dims_[1]
    noise = _noise(D, shrink=0.6, gp_scale=1.5, scale=0.4, dof=4.0)
    zm, zv = visual_predictive(plan, X[None, None])
    point = SynthesisResult.gaussian(zm[0, 0], zv[0, 0], method="map", mean_function=plan.visual_offset)
    want = noise.apply(point, list(utt.labels))
    # the program's sites, traced once, then drawn 4000 times as the program draws them
    pyro.set_rng_seed(0)
    tr = pyro.poutine.trace(face_model).get_trace(plan, torch.as_tensor(X), noise, list(utt.labels))
    n = 4000
    parts = []
    for i in range(len(plan.blocks)):
        gp, obs = tr.nodes[f"face_gp_{i}"]["fn"], tr.nodes[f"face_{i}"]["fn"]
        f = gp.sample((n,))
        parts.append(type(obs.base_dist)(obs.base_dist.df, f, obs.base_dist.scale).sample())
    draws = torch.cat(parts, dim=1).numpy()
    scale = np.sqrt(want.var)
    for q in (0.05, 0.5, 0.95):
        got = np.quantile(draws, q, axis=0)
        assert np.median(np.abs(got - want.quantile(q)) / scale) < 0.06
