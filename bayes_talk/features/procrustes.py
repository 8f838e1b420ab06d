"""Generalised Procrustes alignment of landmark shapes and the pose of each shape
(deena2010 §3.2; Cootes, Edwards & Taylor 2001), the first two steps of building an
:class:`~bayes_talk.features.aam.AAM`:

1. **Generalised Procrustes alignment** of the landmark shapes under similarity
   transforms. With shapes as complex vectors ``z`` (x + iy), the least-squares
   similarity taking a centred shape ``z_c`` onto the mean ``m`` is ``b z_c`` with
   ``b = <z_c, m> / <z_c, z_c>`` (``b = s e^{i rot}``). Iterate: align all, average,
   rescale the mean to the average training size (so the model frame is in pixels), rotate
   it onto the average raw orientation (so rotation 0 = upright), until the mean moves less
   than 1e-10 px. No tangent-space projection (head rotations are a few degrees).
2. **Pose**. Landmarks ``L = a x + t`` with ``x`` the aligned shape (centroid 0), ``t`` the
   centroid of ``L`` and ``a = 1/b``. Stored per frame as ``(tx, ty, log s, rot)``.
"""
from __future__ import annotations

import numpy as np

__all__ = ["align_to", "as_complex", "as_real", "pose_apply", "procrustes_align"]


def as_complex(shapes: np.ndarray) -> np.ndarray:
    """(..., P, 2) shapes as (..., P) complex vectors x + iy."""
    return shapes[..., 0] + 1j * shapes[..., 1]


def as_real(z: np.ndarray) -> np.ndarray:
    """(..., P) complex vectors back to (..., P, 2) shapes."""
    return np.stack([z.real, z.imag], axis=-1)


def procrustes_align(
    landmarks: np.ndarray, tol: float = 1e-10, max_iter: int = 100
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Generalised Procrustes alignment under similarity transforms.

    Parameters
    ----------
    landmarks : (N, P, 2) shapes in pixels.

    Returns
    -------
    mean : (P, 2) mean shape, centroid 0, size (Frobenius norm) = average training size,
        orientation = that of the average of the centred raw shapes.
    aligned : (N, P, 2) shapes in the mean's frame (centroid 0).
    pose : (N, 4) ``(tx, ty, log s, rot)`` with ``landmarks = s R(rot) aligned + t``.
    """
    z = as_complex(np.asarray(landmarks, dtype=np.float64))
    centroid = z.mean(axis=1)
    zc = z - centroid[:, None]
    norms = np.sqrt((np.abs(zc) ** 2).sum(axis=1))
    size = norms.mean()
    ref = zc.mean(axis=0)
    mean = zc[0] / norms[0] * size
    for _ in range(max_iter):
        b = (np.conj(zc) @ mean) / norms**2
        new = (b[:, None] * zc).mean(axis=0)
        new *= size / np.sqrt((np.abs(new) ** 2).sum())
        rot = np.vdot(new, ref)
        if abs(rot) > 0:
            new *= rot / abs(rot)
        done = np.max(np.abs(new - mean)) < tol
        mean = new
        if done:
            break
    mean, aligned, pose = align_to(mean, z)
    return as_real(mean), aligned, pose


def align_to(mean: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Align complex shapes ``z`` (N, P) onto the complex ``mean`` (P,): returns (mean,
    aligned (N, P, 2), pose (N, 4) = (tx, ty, log s, rot)) with L = s e^{i rot} x + t."""
    centroid = z.mean(axis=1)
    zc = z - centroid[:, None]
    b = (np.conj(zc) @ mean) / (np.abs(zc) ** 2).sum(axis=1)
    aligned = as_real(b[:, None] * zc)
    pose = np.stack([centroid.real, centroid.imag, -np.log(np.abs(b)), -np.angle(b)], axis=1)
    return mean, aligned, pose


def pose_apply(aligned: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Landmarks in the image from aligned shapes (N, P, 2) and poses (N, 4): L = a x + t."""
    z = as_complex(aligned)
    a = np.exp(pose[:, 2]) * np.exp(1j * pose[:, 3])
    t = pose[:, 0] + 1j * pose[:, 1]
    return as_real(a[:, None] * z + t[:, None])
