"""AAM search: fitting an :class:`~bayes_talk.features.aam.AAM` to new images.

The algorithm is the *project-out inverse compositional* (POIC) Lucas--Kanade fit of
Matthews & Baker, "Active Appearance Models Revisited", IJCV 60(2), 2004 (M&B below),
with the global similarity transform of their §4.3, run coarse to fine over an image
pyramid, and a fit-quality score for "lost" frames. Why not menpofit: its latest release
(0.7.1, with menpo 0.11.1) installs with Python 3.11 and numpy 2.4 but fails at import,
``ImportError: cannot import name 'simps' from 'scipy.integrate'`` (removed in SciPy
1.14; this project has 1.17), so the fit is written here against the AAM's own
piecewise-affine warp (validated against ``skimage.transform.PiecewiseAffineTransform``).

Model (M&B eqs. 1-4). The base mesh ``s0`` is the AAM's mean shape in its texture frame
(``tex_points``); the AAM's texture pixels ``x`` lie in its Delaunay triangles with fixed
barycentric coordinates ``lambda_k(x)``. A shape ``s`` (image landmarks) defines the
piecewise-affine warp ``W(x; s) = sum_k lambda_k(x) s_{v_k(x)}`` (M&B eq. 3 / §4.1.1).
The appearance, after the AAM's per-texture normalisation ``n(g) = (g - mean g)/std g``,
is ``A(x) = A0(x) + sum_i lambda_i A_i(x)`` with ``A_i`` orthonormal (the texture PCA).
Shapes are ``s = N(s0 + sum_i p_i s_i; q)``: ``s_i`` the shape PCA modes and ``N`` a 2-D
similarity (M&B §4.3). For the update the four similarity directions of the base mesh
``s*_1..4 = (s0), (-s0_y, s0_x), (1, 0), (0, 1)`` (M&B eq. 42) and the shape modes are
orthonormalised together (QR) into one basis ``B_j`` of admissible base-mesh
displacements.

Fit (M&B §4.2, project out). Minimise the part of the error image that the appearance
model cannot explain,

    || A0(W(x; dp)) - n(I(W(x; s))) ||^2  in  span(A_i)^perp                   (M&B eq. 37)

Linearising in ``dp`` around the identity warp gives the steepest-descent images

    SD_j(x) = grad A0(x) . dW/dp_j (x),   dW/dp_j(x) = sum_k lambda_k(x) B_j[v_k(x)]  (eq. 28)

projected out of the appearance subspace, ``SD_j <- SD_j - sum_i (A_i . SD_j) A_i``
(eq. 40), the Gauss--Newton Hessian ``H = SD SD^T`` (eq. 41) and the update

    dp = H^-1 SD^T E(x),   E(x) = n(I(W(x; s))) - A0(x)                         (eq. 38)

``SD`` and ``H`` depend only on the model: they are computed once per pyramid level, so an
iteration costs one bilinear warp of the image plus a (n_basis x n_pixels) product.

Inverse composition (M&B §4.1.2-4.1.3, eqs. 31-34). ``W(x; s) o W(x; dp)^-1``: the base
mesh is moved by ``-sum_j dp_j B_j`` (first-order inverse), and each moved vertex is pushed
through the current warp using the affine maps of the triangles that contain it,
averaged (eq. 34): ``s_k <- s_k - mean_{t ∋ k} A_t (sum_j dp_j B_j[k])`` with ``A_t`` the
linear part of triangle ``t``'s base-to-image affine map. The new shape is then
projected back onto the model (M&B §4.1.3: "the parameters of the closest shape"): a
similarity Procrustes alignment to the mean shape gives ``q``, the shape PCA gives ``p``,
and ``s = N(s0 + sum p_i s_i; q)`` (the same alignment and projection as
:meth:`AAM.project`). Iterations stop when no landmark moves more than ``tol`` pixels
(of that level) or after ``max_iter``.

Pyramid. Level ``l`` holds an AAM fitted on the prototype frames downscaled by
``f = 2**l`` (``skimage.transform.downscale_local_mean``, a box filter), with landmarks
mapped by ``x_l = (x - (f - 1)/2) / f`` (pixel centres at integer coordinates); the fit
runs on the coarsest level first and passes its landmarks down. A coarse level halves the
distance the fit must travel and smooths the image (basin of convergence ~2x wider).

Fit quality (score). The root mean square of the projected-out residual at the finest
level, ``rms = sqrt(mean_x (E - sum_i (A_i . E) A_i)^2)``, in units of the texture's
own standard deviation (the normalised texture has unit variance), so ``rms**2`` is the
fraction of the frame's shape-free texture that the appearance model does not explain.
A frame is **lost** when ``rms > lost_threshold``; :data:`LOST_THRESHOLD` (0.6, i.e.
36 % of the texture unexplained) is the documented default. Measured on the built-in
corpus (128x128, AAM from 4 frames per phone): tracked frames score 0.02-0.46 (median
0.03; the highest are blinks, whose closed eyes few prototypes show: the *true*
landmarks of such frames score 0.3-0.35 too), the true landmarks shifted by 1, 2 and 3 px
score 0.42, 0.72 and 0.90, a diverged fit or a frame without a face 1.0-1.3 (v1
renderer; on the anti-aliased v2 corpora tracked frames score at most 0.07 on
heldout40 and 0.37 on 100 training utterances). So 0.6 flags
fits that are off by more than ~1.5 px, not frames that merely look unusual.

This module stays above ~400 lines because the fitter is one algorithm: the per-level
appearance models, the inverse-compositional search, the pyramid and the tracker's
lost-frame rule share the precomputed Jacobians of :class:`_Level`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage.transform import downscale_local_mean
from threadpoolctl import threadpool_limits

from bayes_talk.features.aam import AAM
from bayes_talk.features.procrustes import align_to, as_complex, pose_apply
from bayes_talk.features.warp import bilinear_sample

__all__ = [
    "LOST_THRESHOLD",
    "AAMFitter",
    "FitResult",
    "FrameSizeError",
    "LandmarkCountError",
    "TooFewPrototypesError",
    "TrackResult",
    "check_prototype_support",
]

#: default fit-quality threshold: a frame whose projected-out texture residual RMS (in
#: units of the texture's standard deviation) exceeds it is "lost" (module docstring)
LOST_THRESHOLD = 0.6


class FrameSizeError(ValueError):
    """Frames of another size than those the AAM was built on."""


class LandmarkCountError(ValueError):
    """Landmarks with another number of points than the AAM's."""


class TooFewPrototypesError(ValueError):
    """The prototype set is too small for the AAM's variance target: a PCA needs every
    mode the sample allows (N - 1 for N frames) to reach it, i.e. it memorises the
    prototypes rather than modelling the variation."""


def check_prototype_support(aam: AAM, where: str = "prototype frames") -> None:
    """Raise :class:`TooFewPrototypesError` if any of the AAM's three PCAs keeps all
    ``N - 1`` modes that ``N`` training frames allow (the variance target is reached only
    by interpolating every prototype)."""
    n = int(aam.meta["n_training_frames"])
    for what, k in (("shape", aam.n_shape_modes), ("texture", aam.n_texture_modes),
                    ("combined", aam.n_combined)):
        if k >= n - 1:
            raise TooFewPrototypesError(
                f"{where}: {n} annotated frames are too few for the AAM's {aam.variance:.0%} "
                f"variance target: the {what} PCA needs {k} modes, all that {n} frames allow "
                f"(N - 1 = {n - 1}); annotate more frames (e.g. 4 per phone, deena2010 §3.2)")


@dataclass
class FitResult:
    """One fitted frame: ``landmarks`` (P, 2) image pixels (x, y); ``score`` the
    projected-out texture residual RMS (lower is better); ``n_iter`` iterations at the
    finest level; ``converged`` whether the last level met its tolerance."""

    landmarks: np.ndarray
    score: float
    n_iter: int
    converged: bool


@dataclass
class TrackResult:
    """A tracked sequence: ``landmarks`` (T, P, 2) (NaN rows for lost frames), ``scores``
    (T,), ``source`` per frame (``"annotated"``, ``"tracked"`` or ``"lost"``)."""

    landmarks: np.ndarray
    scores: np.ndarray
    source: list[str]

    @property
    def lost(self) -> list[int]:
        """Indices of lost frames."""
        return [t for t, s in enumerate(self.source) if s == "lost"]


def _downscale(images: np.ndarray, f: int) -> np.ndarray:
    """Box-filter downscale of (N, H, W) frames by ``f`` (cropped to multiples of f)."""
    if f == 1:
        return np.asarray(images, dtype=np.float64)
    _n, h, w = images.shape
    im = np.asarray(images, dtype=np.float64)[:, : h - h % f, : w - w % f]
    return downscale_local_mean(im, (1, f, f))


def _to_level(points: np.ndarray, f: int) -> np.ndarray:
    return (points - (f - 1) / 2.0) / f


def _from_level(points: np.ndarray, f: int) -> np.ndarray:
    return points * f + (f - 1) / 2.0


class _Level:
    """Precomputed POIC quantities of one pyramid level (see the module docstring)."""

    def __init__(self, aam: AAM, factor: int) -> None:
        a = aam._a
        self.aam = aam
        self.factor = int(factor)
        self.base = a["tex_points"]                          # (P, 2) base mesh s0
        self.tri = a["triangles"]                            # (M, 3)
        self.vert = aam._pix_vertices                        # (n_pix, 3)
        self.bary = a["pixel_bary"]                          # (n_pix, 3)
        self.mean_shape_c = as_complex(a["mean_shape"])
        self.shape_mean = aam.shape_pca.mean
        self.shape_comp = aam.shape_pca.components            # (k_s, 2P)
        self.A0 = aam.texture_pca.mean                       # (n_pix,)
        self.U = aam.texture_pca.components                  # (k_t, n_pix)
        P = self.base.shape[0]
        # update basis: similarity directions + shape modes, orthonormalised (M&B §4.3)
        s0 = self.base - self.base.mean(axis=0)
        sim = np.stack([s0, np.column_stack([-s0[:, 1], s0[:, 0]]),
                        np.tile([1.0, 0.0], (P, 1)), np.tile([0.0, 1.0], (P, 1))])
        basis = np.vstack([sim.reshape(4, -1), self.shape_comp])
        q, r = np.linalg.qr(basis.T)
        keep = np.abs(np.diag(r)) > 1e-9 * np.abs(np.diag(r)).max()
        self.B = q[:, keep].T.reshape(-1, P, 2)              # (n_b, P, 2)
        # steepest-descent images (M&B eq. 28), projected out (eq. 40)
        img = aam.texture_images(self.A0)[0]
        gy, gx = np.gradient(img)
        rows, cols = a["pixel_rows"], a["pixel_cols"]
        gx, gy = gx[rows, cols], gy[rows, cols]
        dW = np.einsum("xk,jxkd->jxd", self.bary, self.B[:, self.vert])  # (n_b, n_pix, 2)
        sd = dW[..., 0] * gx + dW[..., 1] * gy
        sd -= (sd @ self.U.T) @ self.U
        H = sd @ sd.T
        self.R = np.linalg.solve(H, sd)                      # H^-1 SD^T, (n_b, n_pix)
        # composition: inverse edge matrices of the base triangles and vertex incidence
        e = self.base[self.tri[:, 1:]] - self.base[self.tri[:, :1]]   # (M, 2, 2) rows = edges
        self.base_edges_inv = np.linalg.inv(np.transpose(e, (0, 2, 1)))  # columns = edges
        inc = np.zeros((P, self.tri.shape[0]))
        for c in range(3):
            inc[self.tri[:, c], np.arange(self.tri.shape[0])] = 1.0
        self.incidence = inc / np.maximum(inc.sum(axis=1, keepdims=True), 1.0)
        #: (n_pix, P) barycentric weights: W(x; s) = warp_matrix @ s (one BLAS product)
        self.warp_matrix = np.zeros((self.vert.shape[0], P))
        np.add.at(self.warp_matrix, (np.arange(self.vert.shape[0])[:, None], self.vert), self.bary)
        #: a step larger than this (a quarter of the frame) means the fit is diverging
        self.max_step = 0.25 * max(aam.image_shape)

    # ------------------------------------------------------------------ pieces
    def texture(self, image: np.ndarray, shape: np.ndarray) -> np.ndarray:
        """n(I(W(x; s))): the image sampled at the warped texture pixels, normalised."""
        src = self.warp_matrix @ shape
        g = bilinear_sample(image[None], None, src[:, 0], src[:, 1])
        sd = g.std()
        return (g - g.mean()) / (max(1e-06, sd))

    def residual_rms_many(self, image: np.ndarray, shapes: np.ndarray) -> np.ndarray:
        """Residual RMS (as :meth:`residual_rms`) of many shapes (K, P, 2) at once."""
        K = shapes.shape[0]
        src = self.warp_matrix @ np.transpose(shapes, (1, 0, 2)).reshape(shapes.shape[1], 2 * K)
        src = src.reshape(-1, K, 2)
        g = bilinear_sample(image[None], None, src[..., 0].T.ravel(), src[..., 1].T.ravel()).reshape(K, -1)
        sd = np.maximum(g.std(axis=1, keepdims=True), 1e-6)
        e = (g - g.mean(axis=1, keepdims=True)) / sd - self.A0
        r = e - (e @ self.U.T) @ self.U
        return np.sqrt(np.mean(r * r, axis=1))

    def residual_rms(self, image: np.ndarray, shape: np.ndarray) -> float:
        return self._rms_and_error(image, shape)[0]

    def project_shape(self, shape: np.ndarray) -> np.ndarray:
        """The closest model shape N(s0 + sum p_i s_i; q) to image landmarks ``shape``."""
        _, aligned, pose = align_to(self.mean_shape_c, as_complex(shape[None]))
        b = (aligned.reshape(1, -1) - self.shape_mean) @ self.shape_comp.T
        x = (self.shape_mean + b @ self.shape_comp).reshape(1, -1, 2)
        return pose_apply(x, pose)[0]

    def compose(self, shape: np.ndarray, dp: np.ndarray) -> np.ndarray:
        """W(x; s) o W(x; dp)^-1 (M&B eqs. 31-34), before projection onto the model."""
        delta = -np.tensordot(dp, self.B, axes=1)                       # (P, 2) base frame
        ie = shape[self.tri[:, 1:]] - shape[self.tri[:, :1]]             # (M, 2, 2)
        A = np.transpose(ie, (0, 2, 1)) @ self.base_edges_inv            # (M, 2, 2)
        Ak = (self.incidence @ A.reshape(-1, 4)).reshape(-1, 2, 2)      # (P, 2, 2)
        return shape + np.einsum("pij,pj->pi", Ak, delta)

    def _rms_and_error(self, image: np.ndarray, shape: np.ndarray) -> tuple[float, np.ndarray]:
        e = self.texture(image, shape) - self.A0
        r = e - (self.U @ e) @ self.U
        return float(np.sqrt(np.mean(r * r))), e

    def fit(self, image: np.ndarray, shape: np.ndarray, max_iter: int,
            tol: float) -> tuple[np.ndarray, int, bool]:
        """Gauss--Newton POIC iterations with step halving: a step that does not lower
        the projected-out residual is halved (up to 4 times, then the fit stops), so the
        objective never increases (a safeguard M&B do not need on their data; without it
        ~1 % of the built corpus's frames drifted into a wrong minimum)."""
        s = self.project_shape(shape)
        rms, e = self._rms_and_error(image, s)
        for it in range(1, max_iter + 1):
            dp = self.R @ e
            for _ in range(5):
                new = self.project_shape(self.compose(s, dp))
                step = float(np.max(np.abs(new - s)))
                if np.all(np.isfinite(new)) and step < self.max_step:
                    rms_new, e_new = self._rms_and_error(image, new)
                    if rms_new <= rms:
                        break
                dp = 0.5 * dp
            else:
                return s, it, step < tol        # no descent step: a (local) minimum
            s, rms, e = new, rms_new, e_new
            if step < tol:
                return s, it, True
        return s, max_iter, False


class AAMFitter:
    """Project-out inverse-compositional AAM search over an image pyramid.

    Build with :meth:`from_prototypes` (annotated frames) or :meth:`from_aam` (an existing
    AAM for the finest level; coarser levels are fitted on ``images``/``landmarks``).
    :meth:`fit` fits one frame from an initial shape; :meth:`track` fits a sequence,
    each frame initialised from the previous frame's fit.
    """

    def __init__(self, aams: list[AAM], lost_threshold: float = LOST_THRESHOLD,
                 max_iter: int = 30, tol: float = 0.01) -> None:
        if not aams:
            raise ValueError("aams: expected at least one AAM (the finest level)")
        if not (np.isfinite(lost_threshold) and lost_threshold > 0):
            raise ValueError(f"lost_threshold: expected a positive number, found {lost_threshold!r}")
        self.levels = [_Level(a, 2**i) for i, a in enumerate(aams)]
        #: a tracked frame scoring above this gets a second chance (:meth:`_refit`)
        self.retry_threshold = 0.1
        #: (N, P, 2) aligned shapes of the annotated frames (restart points), or None
        self.prototype_shapes: np.ndarray | None = None
        self.lost_threshold = float(lost_threshold)
        self.max_iter = int(max_iter)
        self.tol = float(tol)

    @property
    def aam(self) -> AAM:
        """The finest level's AAM (the one features are projected through)."""
        return self.levels[0].aam

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) of the frames the fitter expects."""
        return self.aam.image_shape

    @property
    def n_landmarks(self) -> int:
        """Number of landmarks fitted per frame."""
        return self.aam.n_landmarks

    @classmethod
    def from_aam(cls, aam: AAM, images: np.ndarray, landmarks: np.ndarray, n_levels: int = 2,
                 **kwargs) -> AAMFitter:
        """Use ``aam`` as the finest level; fit levels 1..n_levels-1 on the prototype
        ``images`` (N, H, W) and ``landmarks`` (N, P, 2) downscaled by 2**l, with the
        finest AAM's variance target and texture inset."""
        images = np.asarray(images)
        landmarks = np.asarray(landmarks, dtype=np.float64)
        aams = [aam]
        with threadpool_limits(limits=1):
            for lev in range(1, int(n_levels)):
                f = 2**lev
                aams.append(AAM.fit(_downscale(images, f), _to_level(landmarks, f),
                                    variance=aam.variance,
                                    texture_inset=float(aam.meta.get("texture_inset", 0.0))))
            fitter = cls(aams, **kwargs)
            lv = fitter.levels[0]
            fitter.prototype_shapes = np.stack([
                align_to(lv.mean_shape_c, as_complex(lv.project_shape(x)[None]))[1][0]
                for x in landmarks])
        return fitter

    @classmethod
    def from_prototypes(cls, images: np.ndarray, landmarks: np.ndarray, n_levels: int = 2,
                        variance: float = 0.99, texture_inset: float = 1.0, **kwargs) -> AAMFitter:
        """Build the AAM (finest level) and its pyramid from annotated frames; raises
        :class:`TooFewPrototypesError` when the frames cannot support ``variance``."""
        n = len(images)
        if n < 3:
            raise TooFewPrototypesError(f"prototype frames: {n} annotated frames are too few to "
                                        "build an AAM (at least 3; e.g. 4 per phone, deena2010 §3.2)")
        with threadpool_limits(limits=1):   # as the corpus builds its AAM: same model bits
            aam = AAM.fit(images, landmarks, variance=variance, texture_inset=texture_inset)
        check_prototype_support(aam)
        return cls.from_aam(aam, images, landmarks, n_levels=n_levels, **kwargs)

    # ------------------------------------------------------------------ checks
    def _check_frames(self, frames: np.ndarray, where: str) -> np.ndarray:
        frames = np.asarray(frames)
        if frames.ndim == 2:
            frames = frames[None]
        if frames.ndim != 3:
            raise FrameSizeError(f"{where}: expected frames (T, H, W), found shape {frames.shape}")
        if tuple(frames.shape[1:]) != tuple(self.image_shape):
            raise FrameSizeError(
                f"{where}: frames are {frames.shape[1]}x{frames.shape[2]} pixels (H x W), but the "
                f"annotated frames the AAM was built on are {self.image_shape[0]}x{self.image_shape[1]}")
        return frames

    def _check_shape(self, shape: np.ndarray, where: str) -> np.ndarray:
        shape = np.asarray(shape, dtype=np.float64)
        if shape.ndim != 2 or shape.shape[1] != 2:
            raise LandmarkCountError(f"{where}: expected landmarks (P, 2), found shape {shape.shape}")
        if shape.shape[0] != self.n_landmarks:
            raise LandmarkCountError(f"{where}: {shape.shape[0]} landmarks, but the AAM has "
                                     f"{self.n_landmarks}")
        if not np.all(np.isfinite(shape)):
            raise ValueError(f"{where}: landmarks must be finite, found NaN or inf")
        return shape

    # ------------------------------------------------------------------ fitting
    def _pyramid(self, image: np.ndarray) -> list[np.ndarray]:
        return [_downscale(image[None], lv.factor)[0] for lv in self.levels]

    def _fit_pyramid(self, pyr: list[np.ndarray], init: np.ndarray,
                     levels: range | None = None) -> FitResult:
        s = init
        n_it, conv = 0, False
        for li in (levels if levels is not None else range(len(self.levels) - 1, -1, -1)):
            lv = self.levels[li]
            s_l, n_it, conv = lv.fit(pyr[li], _to_level(s, lv.factor), self.max_iter,
                                     self.tol / lv.factor)
            s = _from_level(s_l, lv.factor)
        score = self.levels[0].residual_rms(pyr[0], s) if np.all(np.isfinite(s)) else np.inf
        return FitResult(landmarks=s, score=float(score), n_iter=n_it, converged=conv)

    def fit(self, image: np.ndarray, init: np.ndarray) -> FitResult:
        """Fit one frame (H, W) from initial landmarks ``init`` (P, 2), coarse to fine."""
        image = self._check_frames(image, "image")[0].astype(np.float64)
        init = self._check_shape(init, "init")
        with threadpool_limits(limits=1):
            return self._fit_pyramid(self._pyramid(image), init)

    def score(self, image: np.ndarray, landmarks: np.ndarray) -> float:
        """Fit-quality score (residual RMS) of given landmarks, without fitting."""
        image = self._check_frames(image, "image")[0].astype(np.float64)
        return self.levels[0].residual_rms(image, self._check_shape(landmarks, "landmarks"))

    def _refit(self, pyr: list[np.ndarray], prev: np.ndarray, first: FitResult,
               n_best: int = 3) -> FitResult:
        """Second chance for a poorly fitting frame (fast motion, e.g. a blink): fit coarse
        to fine from ``prev``, and from the ``n_best`` prototype shapes (the annotated
        frames' aligned shapes placed at ``prev``'s pose) whose residual at the start is
        lowest; keep the best-scoring fit."""
        best = first
        cands = [self._fit_pyramid(pyr, prev)]
        if self.prototype_shapes is not None:
            lv = self.levels[0]
            _, _, pose = align_to(lv.mean_shape_c, as_complex(prev[None]))
            starts = pose_apply(self.prototype_shapes, np.repeat(pose, len(self.prototype_shapes), 0))
            start_rms = lv.residual_rms_many(pyr[0], starts)
            for i in np.argsort(start_rms)[:n_best]:
                cands.append(self._fit_pyramid(pyr, starts[i], levels=range(1)))
        for c in cands:
            if c.score < best.score:
                best = c
        return best

    def mean_pose_shape(self) -> np.ndarray:
        """The AAM's mean shape at the prototypes' mean pose (initialisation without an
        annotated frame)."""
        aam = self.aam
        pose = aam.mean_params[aam.param_slices["pose"]]
        x = aam.shape_pca.mean.reshape(1, -1, 2)
        return pose_apply(x, pose[None])[0]

    def track(self, frames: np.ndarray, annotations: dict[int, np.ndarray] | None = None,
              where: str = "video", search_stride: int = 10) -> TrackResult:
        """Fit the AAM to every frame of a video, each frame starting from the previous fit."""
        with threadpool_limits(limits=1):   # small products: 2 BLAS threads only contend
            return self._track(frames, annotations, where, search_stride)

    def _track(self, frames: np.ndarray, annotations: dict[int, np.ndarray] | None,
               where: str, search_stride: int) -> TrackResult:
        """Fit every frame of a sequence (T, H, W).

        ``annotations`` maps frame indices to known landmarks (P, 2): those frames keep
        them (source ``"annotated"``) and are the anchors. From each anchor the fit runs
        forward to the next anchor, and backwards from the first anchor to frame 0, each
        frame initialised from the previous frame's fit (the last one that was not lost),
        on the finest level only (inter-frame motion is small). A frame whose score
        exceeds ``lost_threshold`` is refitted coarse to fine from the same start; if it
        is still above, it is ``"lost"`` (landmarks NaN). With no annotation (``{}`` or
        None), every ``search_stride``-th frame is searched from :meth:`mean_pose_shape`
        coarse to fine and the best-scoring one becomes the anchor.
        """
        frames = self._check_frames(frames, where)
        T = frames.shape[0]
        ann = {}
        for t, lm in (annotations or {}).items():
            if not (0 <= int(t) < T):
                raise ValueError(f"{where}: annotated frame {t} outside 0..{T - 1}")
            ann[int(t)] = self._check_shape(lm, f"{where} frame {t}")
        out = np.full((T, self.n_landmarks, 2), np.nan)
        scores = np.full(T, np.inf)
        source = ["lost"] * T
        pyrs: dict[int, list[np.ndarray]] = {}

        def pyr(t: int) -> list[np.ndarray]:
            if t not in pyrs:
                pyrs[t] = self._pyramid(frames[t].astype(np.float64))
            return pyrs[t]

        if not ann:
            best = None
            for t in range(0, T, max(1, int(search_stride))):
                r = self._fit_pyramid(pyr(t), self.mean_pose_shape())
                if best is None or r.score < best[1].score:
                    best = (t, r)
            t0, r0 = best
            if r0.score <= self.lost_threshold:
                out[t0], scores[t0], source[t0] = r0.landmarks, r0.score, "tracked"
                anchors = [t0]
            else:
                scores[t0] = r0.score
                return TrackResult(out, scores, source)
        else:
            for t, lm in ann.items():
                out[t], source[t] = lm, "annotated"
                scores[t] = self.levels[0].residual_rms(pyr(t)[0], lm)
            anchors = sorted(ann)
        runs = [range(anchors[0] - 1, -1, -1)]
        for i, a in enumerate(anchors):
            end = anchors[i + 1] if i + 1 < len(anchors) else T
            runs.append(range(a + 1, end))
        for run in runs:
            if len(run) == 0:
                continue
            prev = out[run[0] - run.step]
            for t in run:
                p = pyr(t)
                r = self._fit_pyramid(p, prev, levels=range(1))
                if r.score > self.retry_threshold:
                    r = self._refit(p, prev, r)
                scores[t] = r.score
                if r.score <= self.lost_threshold:
                    out[t], source[t] = r.landmarks, "tracked"
                    prev = r.landmarks
                pyrs.pop(t, None)
        return TrackResult(out, scores, source)
