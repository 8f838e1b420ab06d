"""Principal component analysis as the AAM uses it (shape, texture and combined models,
deena2010 §3.2): :class:`PCAModel` keeps the smallest number of modes that explains a
given fraction of the total variance."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PCAModel"]


@dataclass
class PCAModel:
    """``X ~ mean + scores @ components``; components (k, D) orthonormal rows.

    eigenvalues : (k,) variances of the kept modes (sample covariance, N - 1);
    total_variance : trace of the sample covariance (all modes).
    """

    mean: np.ndarray
    components: np.ndarray
    eigenvalues: np.ndarray
    total_variance: float

    @classmethod
    def fit(cls, X: np.ndarray, variance: float) -> PCAModel:
        """Keep the fewest modes whose eigenvalues sum to >= ``variance`` of the total.

        Uses the eigen-decomposition of the smaller of the Gram (N x N) and covariance
        (D x D) matrices (BLAS-3 friendly; the squared condition number is harmless for
        the modes a 0.99 threshold keeps). Signs are fixed (largest-magnitude loading
        positive) so the same data always give the same model.
        """
        N, D = X.shape
        mean = X.mean(axis=0)
        Xc = X - mean
        denom = max(N - 1, 1)
        if N <= D:
            lam, U = np.linalg.eigh(Xc @ Xc.T)
            order = np.argsort(lam)[::-1]
            lam, U = np.maximum(lam[order], 0.0), U[:, order]
            keep = lam > lam[0] * 1e-12 if lam[0] > 0 else np.zeros_like(lam, dtype=bool)
            comps = (U[:, keep].T @ Xc) / np.sqrt(lam[keep])[:, None]
        else:
            lam, V = np.linalg.eigh(Xc.T @ Xc)
            order = np.argsort(lam)[::-1]
            lam, V = np.maximum(lam[order], 0.0), V[:, order]
            keep = lam > lam[0] * 1e-12 if lam[0] > 0 else np.zeros_like(lam, dtype=bool)
            comps = V[:, keep].T
        lam = lam[keep] / denom
        total = float((Xc**2).sum() / denom)
        if lam.size == 0:
            k = 0
        elif variance >= 1.0:
            k = lam.size
        else:
            k = int(np.searchsorted(np.cumsum(lam) / total, variance - 1e-12) + 1)
            k = min(k, lam.size)
        comps = comps[:k]
        flip = np.sign(comps[np.arange(k), np.argmax(np.abs(comps), axis=1)])
        comps = comps * flip[:, None]
        return cls(mean, comps, lam[:k], total)

    def project(self, X: np.ndarray) -> np.ndarray:
        """PCA coefficients of the rows of ``X``."""
        return (X - self.mean) @ self.components.T

    def reconstruct(self, b: np.ndarray) -> np.ndarray:
        """Rows reconstructed from PCA coefficients ``b``."""
        return self.mean + b @ self.components
