"""Combined Active Appearance Model (deena2010 §3.2; Cootes, Edwards & Taylor 2001).

Building (:meth:`AAM.fit`):

1. **Generalised Procrustes alignment** of the landmark shapes under similarity transforms
   and 2. **pose** ``(tx, ty, log s, rot)`` per frame: :mod:`bayes_talk.features.procrustes`.
3. **Texture frame**: the mean shape shifted to a pixel grid with a 1-px margin; its
   Delaunay triangulation (``scipy.spatial.Delaunay``) covers the convex hull, and every
   grid pixel centre inside it is a texture pixel, with a fixed triangle and barycentric
   coordinates precomputed once. Warping a frame *to the mean shape* then costs one
   weighted sum of its three landmarks per pixel and a bilinear sample (fast path,
   validated against ``skimage.transform.warp`` + ``PiecewiseAffineTransform``).
4. **Texture normalisation**: each shape-free texture ``g`` (grey levels 0-255) is
   standardised, ``g_n = (g - mu) / sigma`` (per-texture mean and standard deviation);
   ``(mu, log sigma)`` are kept as two photometric parameters so the original grey levels
   are recoverable. This removes global brightness/contrast changes from the texture
   modes, as in Cootes' AAM, without the iterative mean-texture alignment.
5. **PCA** of the aligned shapes ``x = x_bar + P_s b_s``, of the normalised textures
   ``g_n = g_bar + P_g b_g``, then of the concatenation ``[W_s b_s; b_g] = Q c`` (combined
   AAM), each keeping the smallest number of modes that explains ``variance`` of its total
   variance (0.99 as in deena2010, which gave 33 parameters on LIPS). ``W_s = r I`` with
   ``r^2 = (total texture variance) / (total shape variance)`` (traces of the two sample
   covariances) makes a unit of shape change comparable to a unit of texture change.

Parameter vector (:attr:`AAM.param_slices`)::

    [ c (n_combined) | tx, ty, log_scale, rotation | mu, log_sigma ]

Pose and photometric parameters are kept *outside* the combined PCA (the standard
parameterisation of Cootes et al.: appearance ``c``, pose ``t``, texture transform ``u``)
because they are nuisance variation uncorrelated with shape-free appearance. They are part
of the vector so that :meth:`AAM.reconstruct` returns landmarks in image coordinates and
grey levels; models of speech-related motion can drop them with ``param_slices``. After
per-sequence mean removal (:func:`remove_sequence_mean`) add :attr:`AAM.mean_params`
back before reconstructing.

Fitting to new frames. In the built-in corpus the landmarks are known, so
:meth:`AAM.project` needs no AAM search: it aligns the given landmarks, warps the given
pixels and projects. Real video needs the landmarks from a tracker or the AAM search of
:mod:`bayes_talk.features.aam_fit` (``bayes-talk corpus track``) first.

Procrustes alignment and pose are in :mod:`bayes_talk.features.procrustes`, PCA in
:mod:`bayes_talk.features.pca`, the piecewise-affine warp in :mod:`bayes_talk.features.warp`.
This module stays above ~400 lines because :class:`AAM` is one object: its build,
projection, reconstruction, rendering and file format share the texture frame's arrays.

Files: :meth:`AAM.save` writes ``<base>.npz`` (arrays) and ``<base>.json`` (format
version, sizes and the SHA-256 of the .npz), each atomically (temporary file +
``os.replace``). :meth:`AAM.load` raises ``ValueError`` for a missing, truncated or
modified file or a different format version; nothing is pickled.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import Delaunay

from bayes_talk.base.files import check_format, write_bytes
from bayes_talk.features.pca import PCAModel
from bayes_talk.features.procrustes import (
    align_to,
    as_complex,
    pose_apply,
    procrustes_align,
)
from bayes_talk.features.warp import bilinear_sample, warp_piecewise_affine

__all__ = ["AAM", "FORMAT_VERSION", "remove_sequence_mean"]

FORMAT_VERSION = 1
_FORMAT_NAME = "bayes_talk.aam"
_N_POSE = 4
_N_PHOTO = 2
_CHUNK = 128  # frames warped together


def _check_images_landmarks(images, landmarks, image_shape=None, n_landmarks=None):
    images = np.asarray(images)
    landmarks = np.asarray(landmarks, dtype=np.float64)
    if images.ndim != 3:
        raise ValueError(f"images: expected shape (N, H, W), found {images.shape}")
    if not (np.issubdtype(images.dtype, np.integer) or np.issubdtype(images.dtype, np.floating)):
        raise ValueError(f"images: expected uint8 (or real) grey levels, found dtype {images.dtype}")
    if landmarks.ndim != 3 or landmarks.shape[2] != 2 or landmarks.shape[0] != images.shape[0]:
        raise ValueError(
            f"landmarks: expected shape ({images.shape[0]}, P, 2) to match the images, "
            f"found {landmarks.shape}"
        )
    if not np.all(np.isfinite(landmarks)):
        raise ValueError("landmarks: expected finite coordinates, found NaN or inf")
    if image_shape is not None and tuple(images.shape[1:]) != tuple(image_shape):
        raise ValueError(f"images: expected frames of shape {tuple(image_shape)}, found {images.shape[1:]}")
    if n_landmarks is not None and landmarks.shape[1] != n_landmarks:
        raise ValueError(f"landmarks: expected {n_landmarks} points per frame, found {landmarks.shape[1]}")
    return images, landmarks


def _base_path(path: str | os.PathLike) -> Path:
    p = Path(path)
    return p.with_suffix("") if p.suffix in (".json", ".npz") else p


# --------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------
_ARRAYS = (
    "mean_shape", "tex_points", "triangles", "pixel_rows", "pixel_cols", "pixel_tri",
    "pixel_bary", "nearest_pixel", "mean_image", "mean_params",
    "shape_mean", "shape_components", "shape_eigenvalues",
    "texture_mean", "texture_components", "texture_eigenvalues",
    "combined_mean", "combined_components", "combined_eigenvalues",
)


class AAM:
    """A fitted combined appearance model; construct with :meth:`fit` or :meth:`load`."""

    def __init__(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        self._a = {k: np.asarray(v) for k, v in arrays.items()}
        self.meta = dict(meta)
        a = self._a
        self.image_shape: tuple[int, int] = tuple(int(v) for v in meta["image_shape"])
        self.texture_shape: tuple[int, int] = tuple(int(v) for v in meta["texture_shape"])
        self.shape_texture_weight = float(meta["shape_texture_weight"])
        self.variance = float(meta["variance"])
        self.shape_pca = PCAModel(a["shape_mean"], a["shape_components"], a["shape_eigenvalues"],
                                  float(meta["shape_total_variance"]))
        self.texture_pca = PCAModel(a["texture_mean"], a["texture_components"],
                                    a["texture_eigenvalues"], float(meta["texture_total_variance"]))
        self.combined_pca = PCAModel(a["combined_mean"], a["combined_components"],
                                     a["combined_eigenvalues"], float(meta["combined_total_variance"]))
        self._pix_vertices = a["triangles"][a["pixel_tri"]]  # (n_pix, 3)

    # ---------------------------------------------------------------- properties
    @property
    def n_params(self) -> int:
        """Length of a parameter vector: combined modes + 4 pose + 2 photometric."""
        return self.n_combined + _N_POSE + _N_PHOTO

    @property
    def n_combined(self) -> int:
        """Number of combined appearance parameters."""
        return int(self.combined_pca.components.shape[0])

    @property
    def n_shape_modes(self) -> int:
        """Number of shape PCA modes."""
        return int(self.shape_pca.components.shape[0])

    @property
    def n_texture_modes(self) -> int:
        """Number of texture PCA modes."""
        return int(self.texture_pca.components.shape[0])

    @property
    def n_landmarks(self) -> int:
        """Number of landmarks of the shape model."""
        return int(self._a["mean_shape"].shape[0])

    @property
    def n_pixels(self) -> int:
        """Number of texture pixels (grid pixels inside the mean shape's convex hull)."""
        return int(self._a["pixel_rows"].size)

    @property
    def param_slices(self) -> dict[str, slice]:
        """Blocks of the parameter vector: ``combined``, ``pose``, ``photometric``."""
        k = self.n_combined
        return {"combined": slice(0, k), "pose": slice(k, k + _N_POSE),
                "photometric": slice(k + _N_POSE, k + _N_POSE + _N_PHOTO)}

    @property
    def mean_params(self) -> np.ndarray:
        """Average training parameter vector (c = 0, mean pose and photometrics); add it
        back to per-sequence mean-removed parameters before reconstructing."""
        return self._a["mean_params"].copy()

    @property
    def mean_shape(self) -> np.ndarray:
        """(P, 2) mean shape in the model frame (centroid 0, pixels)."""
        return self._a["mean_shape"].copy()

    @property
    def triangles(self) -> np.ndarray:
        """(M, 3) Delaunay triangulation of the mean shape."""
        return self._a["triangles"].copy()

    # ---------------------------------------------------------------- fitting
    @classmethod
    def fit(
        cls,
        images: np.ndarray,
        landmarks: np.ndarray,
        variance: float = 0.99,
        shape_texture_weight: float | None = None,
        texture_inset: float = 0.0,
    ) -> AAM:
        """Build the model from frames (N, H, W) and their landmarks (N, P, 2).

        ``variance`` in (0, 1] is the fraction kept by each of the three PCAs;
        ``shape_texture_weight`` is ``W_s`` (default ``sqrt(total texture var / total
        shape var)``). ``texture_inset`` (pixels, default 0): texture pixels are the grid
        pixel centres at least this far inside the mean shape's convex hull; 1 keeps the
        bilinear support of every sample inside the face, so the outermost ring, which
        straddles the face outline and mixes in the moving background, is left out (on
        the built-in corpus it held most of the texture variance beyond the first ~20
        modes). Memory and time grow with N x n_pixels: fit on prototype frames
        (deena2010 used 184; a few hundred to a few thousand suffice), then
        :meth:`project` every frame.
        """
        images, landmarks = _check_images_landmarks(images, landmarks)
        N, H, W = images.shape
        P = landmarks.shape[1]
        if N < 2:
            raise ValueError(f"images: expected at least 2 frames to fit an AAM, found {N}")
        if P < 3:
            raise ValueError(f"landmarks: expected at least 3 points per frame, found {P}")
        if not (0.0 < float(variance) <= 1.0):
            raise ValueError(f"variance: expected a fraction in (0, 1], found {variance!r}")
        if not (np.isfinite(texture_inset) and texture_inset >= 0):
            raise ValueError(f"texture_inset: expected a distance >= 0 pixels, found {texture_inset!r}")
        if shape_texture_weight is not None and not (np.isfinite(shape_texture_weight) and shape_texture_weight > 0):
            raise ValueError(f"shape_texture_weight: expected a positive number or None, found {shape_texture_weight!r}")

        mean_shape, aligned, pose = procrustes_align(landmarks)
        margin = 1.0
        tex_points = mean_shape - mean_shape.min(axis=0) + margin
        th = int(np.ceil(tex_points[:, 1].max() + margin)) + 1
        tw = int(np.ceil(tex_points[:, 0].max() + margin)) + 1
        tri = Delaunay(tex_points)
        rows, cols = np.mgrid[0:th, 0:tw]
        centres = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float64)
        simplex = tri.find_simplex(centres)
        inside = simplex >= 0
        if texture_inset > 0:
            inside &= _hull_depth(tex_points, centres) >= float(texture_inset)
            if not inside.any():
                raise ValueError(f"texture_inset: {texture_inset} px leaves no texture pixel "
                                 "inside the mean shape")
        T = tri.transform[simplex[inside]]
        b2 = np.einsum("nij,nj->ni", T[:, :2], centres[inside] - T[:, 2])
        bary = np.column_stack([b2, 1.0 - b2.sum(axis=1)])
        mask = inside.reshape(th, tw)
        # For each grid pixel, the flat index (into texture pixels) of the nearest one;
        # used to extend textures beyond the hull so bilinear sampling at the border
        # does not blend in zeros.
        _, (ir, ic) = distance_transform_edt(~mask, return_indices=True)
        pix_index = -np.ones((th, tw), dtype=np.int64)
        pix_index[mask] = np.arange(int(mask.sum()))
        nearest = pix_index[ir, ic].ravel()

        arrays = {
            "mean_shape": mean_shape,
            "tex_points": tex_points,
            "triangles": tri.simplices.astype(np.int64),
            "pixel_rows": rows.ravel()[inside].astype(np.int64),
            "pixel_cols": cols.ravel()[inside].astype(np.int64),
            "pixel_tri": simplex[inside].astype(np.int64),
            "pixel_bary": bary,
            "nearest_pixel": nearest,
        }
        model = cls.__new__(cls)
        model._a = arrays
        model._pix_vertices = arrays["triangles"][arrays["pixel_tri"]]
        textures = model.warp_to_mean(images, landmarks)
        g_norm, photo = _normalise_textures(textures)

        shape_pca = PCAModel.fit(aligned.reshape(N, 2 * P), variance)
        texture_pca = PCAModel.fit(g_norm, variance)
        if shape_texture_weight is None:
            if shape_pca.total_variance <= 0:
                raise ValueError("landmarks: all shapes are identical after alignment; cannot weight shape vs texture")
            shape_texture_weight = float(np.sqrt(texture_pca.total_variance / shape_pca.total_variance))
        b = np.hstack([shape_texture_weight * shape_pca.project(aligned.reshape(N, 2 * P)),
                       texture_pca.project(g_norm)])
        combined_pca = PCAModel.fit(b, variance)
        c = combined_pca.project(b)

        params = np.hstack([c, pose, photo])
        arrays.update(
            mean_image=images.astype(np.float64).mean(axis=0),
            mean_params=params.mean(axis=0),
            shape_mean=shape_pca.mean, shape_components=shape_pca.components,
            shape_eigenvalues=shape_pca.eigenvalues,
            texture_mean=texture_pca.mean, texture_components=texture_pca.components,
            texture_eigenvalues=texture_pca.eigenvalues,
            combined_mean=combined_pca.mean, combined_components=combined_pca.components,
            combined_eigenvalues=combined_pca.eigenvalues,
        )
        meta = {
            "format": _FORMAT_NAME,
            "version": FORMAT_VERSION,
            "image_shape": [H, W],
            "texture_shape": [th, tw],
            "n_landmarks": P,
            "variance": float(variance),
            "shape_texture_weight": float(shape_texture_weight),
            "shape_total_variance": shape_pca.total_variance,
            "texture_total_variance": texture_pca.total_variance,
            "combined_total_variance": combined_pca.total_variance,
            "n_training_frames": N,
            "texture_inset": float(texture_inset),
            "texture_normalisation": "per-texture standardisation (g - mean) / std; params (mean, log std)",
            "param_layout": "combined | tx, ty, log_scale, rotation | texture_mean, log_texture_std",
        }
        return cls(arrays, meta)

    # ---------------------------------------------------------------- warping
    def warp_to_mean(self, images: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
        """Shape-free textures (N, n_pixels) float64 grey levels: each frame warped
        piecewise-affinely from its landmarks onto the mean shape (bilinear sampling)."""
        images = np.asarray(images)
        landmarks = np.asarray(landmarks, dtype=np.float64)
        bary = self._a["pixel_bary"]
        out = np.empty((images.shape[0], self.n_pixels))
        for s in range(0, images.shape[0], _CHUNK):
            e = min(images.shape[0], s + _CHUNK)
            v = landmarks[s:e][:, self._pix_vertices]               # (n, pix, 3, 2)
            src = np.einsum("pk,npkd->npd", bary, v)
            n = e - s
            frame = np.repeat(np.arange(n), self.n_pixels)
            out[s:e] = bilinear_sample(images[s:e].astype(np.float64), frame,
                                       src[..., 0].ravel(), src[..., 1].ravel()).reshape(n, -1)
        return out

    def texture_images(self, textures: np.ndarray, fill: float | None = None) -> np.ndarray:
        """Textures (N, n_pixels) as images (N, th, tw) of the mean-shape frame; pixels
        outside the hull get ``fill``, or (None) the nearest texture pixel's value."""
        textures = np.atleast_2d(np.asarray(textures, dtype=np.float64))
        th, tw = self.texture_shape
        if fill is None:
            return textures[:, self._a["nearest_pixel"]].reshape(-1, th, tw)
        out = np.full((textures.shape[0], th, tw), float(fill))
        out[:, self._a["pixel_rows"], self._a["pixel_cols"]] = textures
        return out

    # ---------------------------------------------------------------- parameters
    def project(self, images: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
        """AAM parameters (N, n_params) of frames with known landmarks (no AAM search)."""
        images, landmarks = _check_images_landmarks(images, landmarks, self.image_shape, self.n_landmarks)
        N = images.shape[0]
        _, aligned, pose = align_to(as_complex(self._a["mean_shape"]), as_complex(landmarks))
        g_norm, photo = _normalise_textures(self.warp_to_mean(images, landmarks))
        b = np.hstack([self.shape_texture_weight * self.shape_pca.project(aligned.reshape(N, -1)),
                       self.texture_pca.project(g_norm)])
        return np.hstack([self.combined_pca.project(b), pose, photo])

    def _check_params(self, params: np.ndarray) -> np.ndarray:
        p = np.asarray(params, dtype=np.float64)
        if p.ndim == 1:
            p = p[None]
        if p.ndim != 2 or p.shape[1] != self.n_params:
            raise ValueError(f"params: expected shape (N, {self.n_params}), found {np.shape(params)}")
        if not np.all(np.isfinite(p)):
            raise ValueError("params: expected finite values, found NaN or inf")
        return p

    def reconstruct(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Landmarks (N, P, 2) in image pixels and shape-free textures (N, n_pixels) in
        grey levels from parameter vectors (N, n_params)."""
        p = self._check_params(params)
        sl = self.param_slices
        b = self.combined_pca.reconstruct(p[:, sl["combined"]])
        k_s = self.n_shape_modes
        x = self.shape_pca.reconstruct(b[:, :k_s] / self.shape_texture_weight)
        landmarks = pose_apply(x.reshape(p.shape[0], -1, 2), p[:, sl["pose"]])
        g = self.texture_pca.reconstruct(b[:, k_s:])
        photo = p[:, sl["photometric"]]
        textures = photo[:, :1] + np.exp(photo[:, 1:2]) * g
        return landmarks, textures

    def reconstruct_landmarks(self, params: np.ndarray) -> np.ndarray:
        """Landmarks (N, P, 2) in image pixels from parameter vectors (N, n_params): the
        shape half of :meth:`reconstruct` alone (the combined modes' shape rows, the shape
        PCA, the pose), without the cost of the textures."""
        p = self._check_params(params)
        sl = self.param_slices
        k_s = self.n_shape_modes
        c = self.combined_pca
        b_s = c.mean[:k_s] + p[:, sl["combined"]] @ c.components[:, :k_s]
        x = self.shape_pca.reconstruct(b_s / self.shape_texture_weight)
        return pose_apply(x.reshape(p.shape[0], -1, 2), p[:, sl["pose"]])

    def render(self, params: np.ndarray) -> np.ndarray:
        """Frames (N, H, W) uint8: reconstructed textures warped from the mean shape to the
        reconstructed landmarks; outside the face, the mean training image."""
        landmarks, textures = self.reconstruct(params)
        tex_img = self.texture_images(textures)
        frames, _ = warp_piecewise_affine(tex_img, self._a["tex_points"], landmarks,
                                          self._a["triangles"], self.image_shape,
                                          fill=self._a["mean_image"])
        return np.clip(np.rint(frames), 0, 255).astype(np.uint8)

    # ---------------------------------------------------------------- files
    def save(self, path: str | os.PathLike) -> tuple[Path, Path]:
        """Write ``<base>.npz`` then ``<base>.json`` atomically; returns both paths.

        ``path`` may be given with or without a ``.json``/``.npz`` suffix.
        """
        base = _base_path(path)
        npz_path, json_path = base.with_name(base.name + ".npz"), base.with_name(base.name + ".json")
        import io

        buf = io.BytesIO()
        np.savez(buf, **{k: self._a[k] for k in _ARRAYS})
        data = buf.getvalue()
        meta = dict(self.meta)
        meta["npz_file"] = npz_path.name
        meta["npz_sha256"] = hashlib.sha256(data).hexdigest()
        meta["arrays"] = {k: list(self._a[k].shape) for k in _ARRAYS}
        write_bytes(npz_path, data)
        write_bytes(json_path, (json.dumps(meta, indent=1, sort_keys=True) + "\n").encode())
        return npz_path, json_path

    @classmethod
    def load(cls, path: str | os.PathLike) -> AAM:
        """Read a model written by :meth:`save` (``ValueError`` on any inconsistency)."""
        base = _base_path(path)
        npz_path, json_path = base.with_name(base.name + ".npz"), base.with_name(base.name + ".json")
        try:
            meta = json.loads(json_path.read_text())
        except FileNotFoundError:
            raise ValueError(f"AAM file {json_path}: not found") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"AAM file {json_path}: not valid JSON (truncated?): {exc}") from None
        check_format(meta, _FORMAT_NAME, FORMAT_VERSION, f"AAM file {json_path}")
        try:
            data = npz_path.read_bytes()
        except FileNotFoundError:
            raise ValueError(f"AAM file {npz_path}: not found") from None
        digest = hashlib.sha256(data).hexdigest()
        if digest != meta.get("npz_sha256"):
            raise ValueError(
                f"AAM file {npz_path}: SHA-256 expected {meta.get('npz_sha256')}, found {digest} "
                "(truncated or modified)"
            )
        import io
        import zipfile

        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                arrays = {k: z[k] for k in _ARRAYS}
        except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"AAM file {npz_path}: unreadable arrays: {exc}") from None
        for k, shape in meta.get("arrays", {}).items():
            if k in arrays and list(arrays[k].shape) != list(shape):
                raise ValueError(f"AAM file {npz_path}: array {k!r} shape expected {shape}, found {list(arrays[k].shape)}")
        return cls(arrays, meta)


def _hull_depth(points: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distance of each point ``xy`` (n, 2) inside the convex hull of ``points`` to the
    hull's boundary (negative outside): min over hull edges of the signed distance."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(points)
    # equations: unit outward normal n and offset c with n.x + c <= 0 inside
    return np.min(-(xy @ hull.equations[:, :2].T + hull.equations[:, 2]), axis=1)


def _normalise_textures(textures: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mu = textures.mean(axis=1, keepdims=True)
    sd = np.maximum(textures.std(axis=1, keepdims=True), 1e-6)
    return (textures - mu) / sd, np.hstack([mu, np.log(sd)])


def remove_sequence_mean(params):
    """Per-sequence mean removal of AAM parameters (deena2010 §3.2).

    For one sequence (T, D), subtract the mean over its frames from every column: each
    mode of variation is centred on zero within the sequence, which removes the sequence's
    average pose, lighting and (unavoidably) average mouth shape. Accepts one (T, D)
    array, or a list of them (returns a list). Returns new arrays.
    """
    if isinstance(params, (list, tuple)):
        return [remove_sequence_mean(p) for p in params]
    p = np.asarray(params, dtype=np.float64)
    if p.ndim != 2 or p.shape[0] < 1:
        raise ValueError(f"params: expected one sequence of shape (T, D) with T >= 1, found {p.shape}")
    return p - p.mean(axis=0, keepdims=True)
