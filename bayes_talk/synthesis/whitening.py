"""The synthesis posterior in whitened coordinates (docs/uncertainty.md).

Every sampler of :mod:`bayes_talk.posterior.sampling` moves in z with X = X_MAP + L z, L Lᵀ
the Laplace covariance (−∇² ln p)⁻¹ at a mode (:func:`whitening`): an affine map, so the
target is unchanged, and close to N(0, I) where the Laplace approximation is good.
:class:`Whitened` is ln p(X_MAP + L z) with its gradient from the numpy twin
(:class:`~bayes_talk.synthesis.joint.UtteranceDensity`), as a torch function for Pyro.
"""
from __future__ import annotations

import numpy as np
import torch

from bayes_talk.synthesis.joint import UtteranceDensity
from bayes_talk.synthesis.joint_map import MapResult


def whitening(mp: MapResult) -> tuple[np.ndarray, np.ndarray]:
    """L with L Lᵀ = (−∇² ln p)⁻¹ at the mode and its inverse L⁻¹, dense: L = R⁻ᵀ from the
    banded Cholesky factor R of the Laplace precision (:meth:`MapResult.laplace_factor`)."""
    return mp.laplace_factor().dense_scale()


class Potential(torch.autograd.Function):
    """ln p(X_MAP + L z) and its gradient Lᵀ∇ln p from the numpy twin, as a torch function."""

    @staticmethod
    def forward(ctx, z, fn):
        """ln p at z by ``fn`` (numpy: value and gradient); the gradient is kept for backward."""
        f, g = fn(z.detach().numpy())
        ctx.save_for_backward(torch.as_tensor(g))
        return torch.as_tensor(f, dtype=torch.float64)

    @staticmethod
    def backward(ctx, grad_out):
        """The kept gradient times the incoming one (z only; ``fn`` has none)."""
        (g,) = ctx.saved_tensors
        return grad_out * g, None


class Whitened:
    """z ↦ (ln p(X_MAP + L z), Lᵀ ∇ ln p) for the samplers."""

    def __init__(self, dens: UtteranceDensity, x_map: np.ndarray, L: np.ndarray):
        self.dens, self.x_map, self.L = dens, x_map.reshape(-1), L

    def numpy(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """(ln p(X_MAP + L z), Lᵀ ∇ ln p) for one z (n,), in numpy."""
        f, g = self.dens(self.x_map + self.L @ z)
        return f, self.L.T @ g.reshape(-1)

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        if z.ndim == 2:  # a batch of walkers (emcee)
            return torch.stack([self(zz) for zz in z])
        return Potential.apply(z, self.numpy)

    def batch_numpy(self, Z: np.ndarray) -> np.ndarray:
        """ln p(X_MAP + L z) for a batch Z (W, n) in one :meth:`UtteranceDensity.values` call
        (emcee's walkers: no gradient needed)."""
        return self.dens.values(self.to_x(np.asarray(Z, dtype=np.float64)))

    def to_x(self, Z: np.ndarray) -> np.ndarray:
        """X_MAP + L z for every row of Z (..., n): whitened draws back to latents."""
        return self.x_map + Z @ self.L.T


__all__ = ["Potential", "Whitened", "whitening"]
