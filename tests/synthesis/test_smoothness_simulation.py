"""The smoothness factor as a pseudo-observation (bayes_talk/synthesis/joint.py, (S)): the
simulated joint (X, audio, u) is the density the samplers target with smoothness on, so
simulation-based calibration can run with smoothness on (issue 24, item 6)."""
from __future__ import annotations

import numpy as np
import pyro
import pytest
import torch
from toydata import make_utterances

from bayes_talk.evaluation.sbc import scaled_laplace, synthesis_sbc
from bayes_talk.gp.numpy_gp import numpy_gp
from bayes_talk.posterior.particle_gibbs import FrameFactors
from bayes_talk.posterior.predictive_checks import prior_predictive
from bayes_talk.synthesis.joint import UtteranceDensity, make_plan, synthesis_model


@pytest.fixture(scope="module")
def toy(toy_vlmm):
    model = toy_vlmm
    labels = list(make_utterances(1, seed=1, mean_len=20)[0].labels[:20])
    plan = make_plan(model, np.zeros((20, model.dims_[0])), labels, smoothness="frame")
    assert sum(b.smooth for b in plan.blocks) >= 2, "the test needs smoothness factors"
    return model, labels, plan


def _trace_log_joint(plan, X, audio, U) -> torch.Tensor:
    """ln p(X, audio, u) of the simulating program (every site conditioned on the simulation)."""
    data = {"X": torch.as_tensor(X)}
    for i, b in enumerate(plan.blocks):
        data[f"audio_{i}"] = torch.as_tensor(audio[b.start:b.stop])
        if b.smooth:
            data[f"smooth_{i}"] = torch.as_tensor(U[b.start])
    tr = pyro.poutine.trace(pyro.poutine.condition(synthesis_model, data=data)).get_trace(plan, None)
    sites = [s for s in tr.nodes.values() if s["type"] == "sample"]
    assert len(sites) == 1 + len(plan.blocks) + sum(b.smooth for b in plan.blocks)
    return tr.log_prob_sum()


def test_simulated_joint_is_the_density_the_samplers_target(toy):
    """At every simulated (X, audio, u): ln p(X, audio, u) of the simulating program equals
    UtteranceDensity (and the particle-Gibbs frame factors) of the plan with audio and u, to
    1e-10 relative, gradient against autograd; u = 0 gives the product of the papers, and the
    simulated u changes the density (so it is not ignored)."""
    model, labels, plan = toy
    X, A, U = prior_predictive(plan, 4, seed=2, with_smoothness=True)
    assert np.any(U != 0)
    for s in range(4):
        p = make_plan(model, A[s], labels, "frame", audio_view=True, smooth_shift=U[s])
        dens = UtteranceDensity(p)
        f, g = dens(X[s])
        Xt = torch.tensor(X[s], requires_grad=True)
        ft = _trace_log_joint(p, Xt, A[s], U[s])
        ft.backward()
        assert abs(f - float(ft.detach())) <= 1e-10 * abs(f), (f, float(ft.detach()))
        np.testing.assert_allclose(g, Xt.grad.numpy(), rtol=1e-6, atol=1e-6 * np.abs(g).max())
        assert abs(FrameFactors(dens).total(X[s]) - f) <= 1e-10 * abs(f)
        f0 = UtteranceDensity(make_plan(model, A[s], labels, "frame", audio_view=True))(X[s])[0]
        fz = UtteranceDensity(make_plan(model, A[s], labels, "frame", audio_view=True,
                                        smooth_shift=np.zeros_like(U[s])))(X[s])[0]
        assert fz == f0 and abs(f - f0) > 1e-3


def test_simulated_pseudo_observations_follow_their_conditional(toy):
    """u_a | X ~ N(μ_Z^π(x_a) − μ_Z^{π'}(x_{a−1}), σ²_Z^π(x_a)/w² + s²_Δ), checked with the
    numpy GP predictives: standardised residuals have mean 0 and sd 1."""
    _, _, plan = toy
    X, _, U = prior_predictive(plan, 200, seed=5, with_smoothness=True)
    z = []
    for i, b in enumerate(plan.blocks):
        if not b.smooth:
            continue
        a = b.start
        prev, vis = numpy_gp(plan.blocks[i - 1].model.predictors_["visual"]), numpy_gp(b.model.predictors_["visual"])
        mu_p, _ = prev.mean_var(X[:, a - 1])
        mu, var = vis.mean_var(X[:, a])
        v = var[:, None] / vis.w2[None] + plan.motion_var[None]
        z.append((U[:, a] - (mu - mu_p)) / np.sqrt(v))
    starts = [b.start for b in plan.blocks if b.smooth]
    assert np.all(np.delete(U, starts, axis=1) == 0)   # no pseudo-observation where there is no factor
    z = np.concatenate([x.ravel() for x in z])
    assert z.size >= 400 and abs(z.mean()) < 0.1 and abs(z.std() - 1) < 0.05, (z.mean(), z.std())


def test_smooth_shift_of_the_wrong_shape_is_a_clear_error(toy):
    model, labels, _ = toy
    with pytest.raises(ValueError, match=r"smooth_shift: expected .*\(20, "):
        make_plan(model, np.zeros((20, model.dims_[0])), labels, smooth_shift=np.zeros((19, 3)))


def test_sbc_with_smoothness_on_rejects_laplace_with_halved_variance(toy):
    """SBC with smoothness on (the default) simulates u and conditions on it; the control
    (Laplace with its covariance halved) is rejected by the combined verdict."""
    model, labels, _ = toy
    res = synthesis_sbc(model, labels[:8], scaled_laplace(0.5, n_draws=40), n_sims=40, n_draws=19, seed=0)
    assert res.info["smoothness"] == "frame" and res.info["n_smoothness_factors"] >= 1, res.info
    assert not res.verdict["passed"] and res.verdict["dispersion_t"] > 0, res.verdict
