"""The SGPDM's MAP objective and its gradient in NumPy, without autograd.

:func:`~bayes_talk.models.sgpdm_program.sgpdm_log_joint` is the objective; this module
evaluates the same sum

    L = λ·ln p(X) + Σ_v [ln HalfNormal(w_v) + N·Σ_m ln w_vm + ℓ(X; α_v, γ_v, β_v, Y_v W_v)] − Σ_θ ln θ

(deena2010 eq. 7 and eq. 5, the w prior and the 1/θ factor; docs/model.md) over the flat
vector of free parameters that torch's L-BFGS sees — log θ and log w of each view in the
order of ``SGPDM._log``, then the latents X row by row — and writes the gradient by hand:
the RBF matrix-normal terms ℓ and their derivatives come from the compiled passes of
:func:`bayes_talk.gp.fused.rbf_matrix_normal_grad` (the passes autograd runs through on
the default path), and the rest is the chain rule

    ∂L/∂ln θ = θ·∂L/∂θ,   ∂ℓ/∂w_m = −Σ_n Y_nm A_nm,   ∂(N ln w_m)/∂w_m = N/w_m,
    ∂ ln HalfNormal(w_m)/∂w_m = −w_m/κ²,   ∂(−ln θ)/∂θ = −1/θ,
    ∂ ln p(X)/∂X: the kernel term at X_in, −A at X_out, −x₁ at each first frame,

with A = K⁻¹V of each term. At the few dozen to few hundred frames of a switching state
autograd's bookkeeping cost as much as the algebra; :class:`SGPDMObjective` returns the
value and gradient with one Python call per term.

It covers the configurations the switching model trains (no back-constraint, no linear
dynamics term, the fused path on): :func:`supports` says which. When a kernel matrix is
not numerically positive definite the evaluation returns None and the caller evaluates
that point through the torch path, which adds jitter and logs it.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch

from bayes_talk.base import settings
from bayes_talk.gp.fused import rbf_matrix_normal_grad
from bayes_talk.gp.lbfgs import LBFGS
from bayes_talk.gp.terms import LOG_2PI, W_PRIOR_VARIANCE, dynamics_split
from bayes_talk.models.sgpdm_program import FitHistory, SGPDMConfig, view_latents

__all__ = ["SGPDMObjective", "fit_direct", "supports"]


def supports(cfg: SGPDMConfig) -> bool:
    """Whether :class:`SGPDMObjective` evaluates this configuration: no back-constraint, no
    linear dynamics term, and the compiled GP passes on (switch ``fused``) as well as the
    direct fit itself (switch ``direct_fit`` of :mod:`bayes_talk.base.settings`)."""
    return (cfg.back_constraint is None and cfg.dyn_linear is None and bool(settings.get("fused"))
            and bool(settings.get("direct_fit")))


class SGPDMObjective:
    """−L and −∂L/∂(free parameters) at a flat parameter vector.

    views: name → centred (N, D_v) float64 arrays (the training data of the fit).
    log_params: name → shape of each free log-parameter, in the optimiser's order
        (``alpha/<v>``, ``gamma/<v>``, ``beta/<v>``, ``w/<v>``, and ``alpha/dyn``, ...
        when the dynamics are learned); the latents X (N×d) follow them.
    fixed: name → value of every hyperparameter that is not learned.
    learned: the kernel hyperparameters that carry the 1/θ prior.
    """

    def __init__(self, views: Mapping[str, np.ndarray], seq_lengths: Sequence[int], cfg: SGPDMConfig,
                 log_params: Mapping[str, tuple[int, ...]], fixed: Mapping[str, np.ndarray | float],
                 learned: Sequence[str]):
        self.views = {v: np.ascontiguousarray(Y, dtype=np.float64) for v, Y in views.items()}
        self.cfg = cfg
        self.N = next(iter(self.views.values())).shape[0]
        self.d = cfg.latent_dim
        self.slices: dict[str, slice] = {}
        self.shapes: dict[str, tuple[int, ...]] = {}
        off = 0
        for k, shape in log_params.items():
            n = int(np.prod(shape, dtype=np.int64))
            self.slices[k], self.shapes[k] = slice(off, off + n), tuple(shape)
            off += n
        self.x_slice = slice(off, off + self.N * self.d)
        self.size = off + self.N * self.d
        self.fixed = {k: np.asarray(v, dtype=np.float64) for k, v in fixed.items()}
        self.learned = list(learned)
        i_in, i_out, i_first = dynamics_split(seq_lengths)
        self.i_in, self.i_out, self.i_first = i_in.numpy(), i_out.numpy(), i_first.numpy()
        self.lam = (sum(Y.shape[1] for Y in self.views.values()) / self.d if cfg.balanced else 1.0)

    def _hyper(self, p: np.ndarray) -> dict[str, np.ndarray]:
        h = {k: np.exp(p[s]).reshape(self.shapes[k]) for k, s in self.slices.items()}
        h.update(self.fixed)
        return h

    def __call__(self, p: np.ndarray) -> tuple[float, np.ndarray] | None:
        """(−L, −∂L/∂p) at ``p``, or None when a kernel matrix needs jitter."""
        cfg, N, d = self.cfg, self.N, self.d
        X = p[self.x_slice].reshape(N, d)
        h = self._hyper(p)
        gh: dict[str, np.ndarray | float] = {}     # ∂L/∂θ per hyperparameter
        gX = np.zeros((N, d))
        total = 0.0
        if cfg.dynamics:
            X1 = X[self.i_first]
            lx = -0.5 * float((X1 * X1).sum()) - 0.5 * X1.shape[0] * d * LOG_2PI
            gX[self.i_first] -= self.lam * X1
            if len(self.i_in) > 0:
                a, gm, b = float(h["alpha/dyn"]), float(h["gamma/dyn"]), float(h["beta/dyn"])
                r = rbf_matrix_normal_grad(X[self.i_in], a, gm, b, X[self.i_out])
                if r is None:
                    return None
                ll, g_in, ga, gg, gb, g_out = r
                lx = lx + ll
                gX[self.i_in] += self.lam * g_in      # each index list has no repeats
                gX[self.i_out] += self.lam * g_out
                gh.update({"alpha/dyn": self.lam * ga, "gamma/dyn": self.lam * gg, "beta/dyn": self.lam * gb})
            total = total + (lx if self.lam == 1.0 else lx * self.lam)
        else:
            total = total + (-0.5 * float((X * X).sum()) - 0.5 * N * d * LOG_2PI)
            gX -= X
        scale = math.sqrt(W_PRIOR_VARIANCE)
        for v, Y in self.views.items():
            w = h[f"w/{v}"]
            gw = np.zeros_like(w)
            if cfg.learn_w:
                lp = -(w * w) / (2 * scale**2) - math.log(scale) - math.log(math.sqrt(2 * math.pi)) + math.log(2)
                total = total + float(lp.sum())
                gw -= w / scale**2
            a, gm, b = float(h[f"alpha/{v}"]), float(h[f"gamma/{v}"]), float(h[f"beta/{v}"])
            Xv = view_latents(X, cfg, v)            # the columns the view's GP reads (SGPDMConfig.view_dims)
            k = Xv.shape[1]
            r = rbf_matrix_normal_grad(Xv, a, gm, b, Y * w)
            if r is None:
                return None
            ll, gx_v, ga, gg, gb, gV = r
            total = total + (N * float(np.log(w).sum()) + ll)
            gX[:, :k] += gx_v
            gw += N / w + (Y * gV).sum(0)
            gh.update({f"alpha/{v}": ga, f"gamma/{v}": gg, f"beta/{v}": gb, f"w/{v}": gw})
        if self.learned:
            total = total + -sum(math.log(float(h[k])) for k in self.learned)
            for k in self.learned:
                gh[k] = gh.get(k, 0.0) - 1.0 / h[k]
        grad = np.empty(self.size)
        for k, s in self.slices.items():
            grad[s] = -(np.asarray(gh.get(k, 0.0)) * h[k]).reshape(-1)
        grad[self.x_slice] = -gX.reshape(-1)
        return -total, grad


def fit_direct(obj: SGPDMObjective, free: Sequence[torch.Tensor], log_joint: Callable[[], torch.Tensor],
               cfg: SGPDMConfig, step_iter: int) -> FitHistory:
    """MAP fit of the model whose free parameter tensors are ``free`` (the order ``obj``
    flattens) as ``SGPDM._optimise`` runs torch's L-BFGS without a monitor:
    :class:`~bayes_talk.gp.lbfgs.LBFGS` (history 50, strong Wolfe) in blocks of
    ``step_iter`` iterations, ``cfg.max_iter`` in all, ``log_joint()`` recorded after each
    block and the fit stopped when a block improves it by at most ``cfg.tol``·max(1, |L|).
    Where ``obj`` declines (a kernel matrix that needs jitter) the point is evaluated by
    autograd of ``log_joint``. Returns the history; ``free`` hold the final point."""
    sizes = [t.numel() for t in free]

    def set_free(x: np.ndarray) -> None:
        with torch.no_grad():
            for t, chunk in zip(free, np.split(x, np.cumsum(sizes)[:-1])):
                t.copy_(torch.from_numpy(chunk).view_as(t))

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        out = obj(x)
        if out is not None:
            return out
        set_free(x)
        with torch.enable_grad():
            loss = -log_joint()
            grads = torch.autograd.grad(loss, free)
        return float(loss.detach()), torch.cat([g.reshape(-1) for g in grads]).numpy()

    def log_joint_at(x: np.ndarray) -> float:
        set_free(x)
        with torch.no_grad():
            return float(log_joint())

    opt = LBFGS(torch.cat([t.detach().reshape(-1) for t in free]).numpy(), lr=1.0, max_iter=step_iter,
                history_size=50)
    history = FitHistory([log_joint_at(opt.x)])
    for step in range(1, max(1, math.ceil(cfg.max_iter / step_iter)) + 1):
        opt.max_iter = min(step_iter, max(1, cfg.max_iter - (step - 1) * step_iter))
        opt.step(fun)
        cur = log_joint_at(opt.x)
        if not math.isfinite(cur):
            raise RuntimeError("the SGPDM objective became non-finite during training")
        prev = history.log_joint[-1]
        history.log_joint.append(cur)
        if abs(cur - prev) <= cfg.tol * max(1.0, abs(cur)):
            break
    history.n_iter = opt.n_iter
    return history
