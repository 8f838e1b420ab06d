"""The direct SGPDM fit (issue 29): the hand-written objective and gradient of
models/sgpdm_objective.py against autograd of the log joint, the NumPy port of torch's
L-BFGS (gp/lbfgs.py) against torch's, and whole fits (single SGPDMs and a switching model
on a toy corpus) against the torch path (switch ``direct_fit`` off)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from toydata import make_utterances

from bayes_talk.base import settings
from bayes_talk.estimators.switching import SwitchingSGPDM
from bayes_talk.gp.lbfgs import LBFGS
from bayes_talk.models.sgpdm import SGPDM
from bayes_talk.models.sgpdm_objective import SGPDMObjective


def _toy(N=40, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, N)[:, None]
    audio = np.hstack([np.sin(t), np.cos(t), np.sin(2 * t), np.cos(3 * t)]) + 0.02 * rng.normal(size=(N, 4))
    video = np.hstack([np.cos(t) ** 2, np.sin(t) * np.cos(t), np.sin(3 * t)]) + 0.02 * rng.normal(size=(N, 3))
    return audio, video


@pytest.mark.parametrize("kw", [{}, {"learn_dynamics": True, "balanced": True}, {"dynamics": False, "learn_w": False},
                                {"learn_dynamics": True, "learn_w": False}, {"view_dims": {"audio": 1}}])
def test_direct_objective_and_gradient_equal_autograd_of_the_log_joint(kw):
    """−L and its gradient over the flat free parameters (log θ, log w, X) equal autograd
    of ``SGPDM.log_joint`` at a fitted (not stationary) point, to rounding."""
    audio, video = _toy(30)
    m = SGPDM(latent_dim=2, max_iter=3, **kw).fit({"audio": audio, "visual": video}, seq_lengths=[12, 1, 17])
    free = m._free_tensors()
    with torch.no_grad():  # move off the fitted point so no gradient is near zero by chance
        for j, t in enumerate(free):
            t.add_(0.05 * torch.sin(torch.arange(t.numel(), dtype=torch.float64) + j).view_as(t))
    loss = -m.log_joint()
    grads = torch.autograd.grad(loss, free)
    g_ref = torch.cat([g.reshape(-1) for g in grads]).numpy()
    obj = SGPDMObjective({v: Y.numpy() for v, Y in m._Y.items()}, m.seq_lengths_, m.config,
                         {k: tuple(t.shape) for k, t in m._log.items()},
                         {k: t.detach().numpy() for k, t in m._fixed.items()}, m._learned_thetas())
    x = torch.cat([t.detach().reshape(-1) for t in free]).numpy()
    f, g = obj(x)
    assert f == pytest.approx(float(loss.detach()), rel=1e-13)
    assert g.shape == g_ref.shape
    np.testing.assert_allclose(g, g_ref, rtol=1e-9, atol=1e-9 * np.abs(g_ref).max())


def _rosenbrock_torch(p):
    return (100.0 * (p[1:] - p[:-1] ** 2) ** 2 + (1.0 - p[:-1]) ** 2).sum()


def test_lbfgs_port_walks_torchs_path():
    """On a 6-D Rosenbrock function, blocks of 7 iterations with state carried between
    blocks (as SGPDM.fit runs them): the same iterates, iteration and evaluation counts."""
    x0 = np.array([-1.2, 1.0, -0.5, 0.8, 1.3, -0.7])
    p = torch.tensor(x0, requires_grad=True)
    opt = torch.optim.LBFGS([p], lr=1.0, max_iter=7, history_size=4, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = _rosenbrock_torch(p)
        loss.backward()
        return loss.detach()

    def fun(x):
        q = torch.tensor(x, requires_grad=True)
        loss = _rosenbrock_torch(q)
        loss.backward()
        return float(loss.detach()), q.grad.numpy()

    mine = LBFGS(x0, lr=1.0, max_iter=7, history_size=4)
    for block in range(6):
        opt.param_groups[0]["max_iter"] = mine.max_iter = 7 if block < 5 else 3
        opt.step(closure)
        mine.step(fun)
        np.testing.assert_allclose(mine.x, p.detach().numpy(), rtol=1e-9, atol=1e-12, err_msg=f"block {block}")
        assert mine.n_iter == opt.state[p]["n_iter"]
        assert mine.func_evals == opt.state[p]["func_evals"]
    assert fun(mine.x)[0] < 0.05 * fun(x0)[0]  # it did travel downhill (a path worth comparing)


def _fit(direct: bool, kw: dict, max_iter: int = 60, audio_scale: float = 1.0):
    audio, video = _toy(40)
    with settings.override(direct_fit=direct):
        return SGPDM(latent_dim=2, max_iter=max_iter, **kw).fit({"audio": audio * audio_scale, "visual": video},
                                                                 seq_lengths=[15, 25])


def _fit_distances(a, b) -> dict:
    """How far fit ``a`` is from fit ``b``: the log joint per block (relative, per element),
    the latents (relative to b's largest), each hyperparameter (relative, per element)."""
    lj_a, lj_b = np.asarray(a.history.log_joint), np.asarray(b.history.log_joint)
    out = {"log_joint": float(np.max(np.abs(lj_a - lj_b) / np.abs(lj_b))),
           "X": float(np.max(np.abs(a.X_ - b.X_)) / np.max(np.abs(b.X_)))}
    for k, v in b.hyper_.items():
        v, u = np.asarray(v), np.asarray(a.hyper_[k])
        out[k] = float(np.max(np.abs(u - v) / np.abs(v)))
    return out


#: the data perturbations that measure the torch path's own rounding sensitivity
ROUNDING_SCALES = (1 + 1e-14, 1 - 1e-14)
#: how many times that sensitivity the direct path may be from torch's fit (measured: 0.65-0.85)
SENSITIVITY_MULTIPLE = 4.0
#: below this relative distance two fits count as equal whatever the sensitivity (round-off)
ROUND_OFF = 1e-12


@pytest.mark.parametrize("kw", [{}, {"learn_dynamics": True}, {"view_dims": {"audio": 1}}])
def test_direct_fit_gives_the_torch_fit(kw):
    """A whole fit by the direct path ends where torch's L-BFGS through autograd ends, to
    within the torch fit's own sensitivity to rounding: the same iterations, and the log joint
    per block, the latents and every hyperparameter no further from torch's fit than 4× the
    distance torch's fit moves when the audio is scaled by 1 ± 1e-14 (a change of the data
    far below meaning). The two paths round differently (summation order, fused multiply-adds)
    and an unconverged L-BFGS amplifies rounding, by an amount that depends on the machine's
    arithmetic: with ``learn_dynamics`` the torch path's log joint moves by 1.3e-6 relative on
    one machine (AMD EPYC, AVX-512) and the direct path differs from it by 1.0e-6, so a fixed
    1e-6 was not a property of the code. Measured ratio direct / sensitivity: 0.65-0.85 for
    every quantity; a wrong gradient or objective puts the direct path orders of magnitude
    outside (checked by ``test_a_perturbed_direct_objective_is_caught``)."""
    _assert_direct_fit_within_rounding_of_torch(kw)


def _assert_direct_fit_within_rounding_of_torch(kw):
    a, b = _fit(True, kw), _fit(False, kw)
    assert a.history.n_iter == b.history.n_iter
    sensitivity: dict = {}
    for scale in ROUNDING_SCALES:
        moved = _fit_distances(_fit(False, kw, audio_scale=scale), b)
        sensitivity = {k: max(sensitivity.get(k, 0.0), v) for k, v in moved.items()}
    distance = _fit_distances(a, b)
    too_far = {k: (d, sensitivity[k]) for k, d in distance.items()
               if d > max(SENSITIVITY_MULTIPLE * sensitivity[k], ROUND_OFF)}
    assert not too_far, f"direct path outside {SENSITIVITY_MULTIPLE}x torch's rounding sensitivity " \
                        f"(distance, sensitivity): {too_far}"


def test_a_perturbed_direct_objective_is_caught(monkeypatch):
    """The comparison above can fail: a direct objective whose gradient is off by 1e-7
    relative (far smaller than any modelling error) ends outside the rounding band."""
    orig = SGPDMObjective.__call__

    def perturbed(self, x):
        value = orig(self, x)
        return None if value is None else (value[0], value[1] * (1 + 1e-7))

    monkeypatch.setattr(SGPDMObjective, "__call__", perturbed)
    with pytest.raises(AssertionError, match="rounding sensitivity"):
        _assert_direct_fit_within_rounding_of_torch({})


def test_direct_path_is_used_by_default_and_not_when_switched_off(monkeypatch):
    """The default fit goes through the direct objective (a fit that never calls it would
    pass the comparisons above trivially); with ``direct_fit`` off it is never called."""
    calls = []
    orig = SGPDMObjective.__call__
    monkeypatch.setattr(SGPDMObjective, "__call__", lambda self, x: calls.append(1) or orig(self, x))
    _fit(True, {}, max_iter=8)
    assert len(calls) >= 8
    calls.clear()
    _fit(False, {}, max_iter=8)
    assert calls == []


def test_switching_model_fits_the_same_states_by_both_paths():
    """Issue 29 acceptance: every state model of a switching model on a toy corpus has the
    hyperparameters and latents of the torch path (same tolerance as a single fit)."""
    train = make_utterances(6, seed=0)
    small = {"latent_dim": 3, "max_iter": 40, "min_count": 4, "max_frames_per_state": 120, "fallback_frames": 150}
    fits = {}
    for direct in (True, False):
        with settings.override(direct_fit=direct):
            fits[direct] = SwitchingSGPDM(states="phone", **small).fit(train)
    new, ref = fits[True], fits[False]
    assert new.models_.keys() == ref.models_.keys()
    for k, m in ref.models_.items():
        n = new.models_[k]
        assert n.history.n_iter == m.history.n_iter, k
        np.testing.assert_allclose(n.X_, m.X_, rtol=0, atol=1e-5 * np.abs(m.X_).max(), err_msg=str(k))
        for h, v in m.hyper_.items():
            np.testing.assert_allclose(np.asarray(n.hyper_[h]), np.asarray(v), rtol=1e-5, err_msg=f"{k} {h}")


def test_a_subclass_with_its_own_log_joint_keeps_the_torch_path(monkeypatch):
    """The sparse SGPDM overrides the log joint (an inducing-point bound): the direct
    objective, which is the exact SGPDM's, must never evaluate it."""
    from bayes_talk.models.sparse_sgpdm import SparseSGPDM

    calls = []
    orig = SGPDMObjective.__call__
    monkeypatch.setattr(SGPDMObjective, "__call__", lambda self, x: calls.append(1) or orig(self, x))
    audio, video = _toy(30)
    SparseSGPDM(latent_dim=2, n_inducing=8, max_iter=4).fit({"audio": audio, "visual": video})
    assert calls == []
