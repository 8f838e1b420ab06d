"""MLP back-constraint X = g(Y; φ) (deena2009 §2.1, eq. 4–5).

One tanh hidden layer and a linear output,

    g(y) = W₂ · tanh(W₁ y + b₁) + b₂,

so that training optimises φ = (W₁, b₁, W₂, b₂) instead of the latent points. Inputs are
standardised with the training mean and standard deviation (kept with the weights).
"""
from __future__ import annotations

import numpy as np
import torch


class MLPBackConstraint:
    """The back-constraint network; parameters are plain float64 tensors."""

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 20, seed: int = 0):
        gen = torch.Generator().manual_seed(seed)
        s1, s2 = 1.0 / np.sqrt(in_dim), 1.0 / np.sqrt(hidden)
        self.W1 = (torch.randn(hidden, in_dim, generator=gen, dtype=torch.float64) * s1)
        self.b1 = torch.zeros(hidden, dtype=torch.float64)
        self.W2 = (torch.randn(out_dim, hidden, generator=gen, dtype=torch.float64) * s2)
        self.b2 = torch.zeros(out_dim, dtype=torch.float64)
        self.in_mean = torch.zeros(in_dim, dtype=torch.float64)
        self.in_std = torch.ones(in_dim, dtype=torch.float64)

    # parameters optimised by training, in a fixed order
    def parameters(self) -> list[torch.Tensor]:
        """The trainable tensors (W1, b1, W2, b2)."""
        return [self.W1, self.b1, self.W2, self.b2]

    def set_input_scaling(self, Y: np.ndarray | torch.Tensor) -> None:
        """Fix the input standardisation from the training inputs ``Y``."""
        Y = torch.as_tensor(Y, dtype=torch.float64)
        self.in_mean = Y.mean(0)
        self.in_std = Y.std(0).clamp_min(1e-12)

    def __call__(self, Y: torch.Tensor, params: list[torch.Tensor] | None = None) -> torch.Tensor:
        W1, b1, W2, b2 = params if params is not None else self.parameters()
        H = torch.tanh(((Y - self.in_mean) / self.in_std) @ W1.mT + b1)
        return H @ W2.mT + b2

    def fit_to(self, Y: torch.Tensor, X: torch.Tensor, iters: int = 300) -> float:
        """Least-squares fit of g(Y) to target latents X (used to start from a PCA init)."""
        params = [p.clone().requires_grad_(True) for p in self.parameters()]
        opt = torch.optim.LBFGS(params, max_iter=iters, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            loss = ((self(Y, params) - X) ** 2).mean()
            loss.backward()
            return loss

        opt.step(closure)
        self.W1, self.b1, self.W2, self.b2 = (p.detach() for p in params)
        return float(((self(Y) - X) ** 2).mean())

    def state(self) -> dict[str, np.ndarray]:
        """The weights and scaling as named arrays (saved with the model)."""
        names = ("W1", "b1", "W2", "b2", "in_mean", "in_std")
        return {n: getattr(self, n).detach().numpy().copy() for n in names}

    @classmethod
    def from_state(cls, arrays: dict[str, np.ndarray]) -> MLPBackConstraint:
        """A back-constraint restored from :meth:`state`."""
        W1, W2 = arrays["W1"], arrays["W2"]
        obj = cls(W1.shape[1], W2.shape[0], W1.shape[0])
        for n in ("W1", "b1", "W2", "b2", "in_mean", "in_std"):
            setattr(obj, n, torch.as_tensor(np.asarray(arrays[n]), dtype=torch.float64))
        return obj
