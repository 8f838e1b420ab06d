"""What ``synth`` shows of the uncertainty: ``posterior.nc``, ``bands.png`` and ``uncertainty.mp4``.

All three are drawn from the one synthesis result
(:class:`bayes_talk.synthesis.result.SynthesisResult`), so they show exactly the bands that
``bands.npz`` holds and that ``evaluate`` scores (its exact mixture quantiles).

* :func:`write_posterior_netcdf` — the result's ArviZ InferenceData as netCDF (h5netcdf,
  which ArviZ itself depends on), written atomically: ``az.from_netcdf("posterior.nc")``
  then ``az.summary`` / ``az.plot_trace`` / ``az.plot_ppc``.
* :func:`plot_bands` — the first AAM parameters over time: the mean, the central 50 % and
  90 % bands, and the ground truth when given.
* :func:`uncertainty_frames` — the mean face beside a per-pixel standard-deviation panel:
  ``n_draws`` draws of the AAM predictive (the mixture) are rendered and the grey-level
  standard deviation of each pixel over them is shown, white = ``SD_FULL_SCALE`` grey levels
  or more, black = none.
* :func:`render_frames` — an AAM trajectory rendered in chunks, each chunk advancing the open
  progress stage (:func:`bayes_talk.base.progress.current`); :func:`uncertainty_frames`
  renders through it too.
"""
from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from bayes_talk.base import progress
from bayes_talk.base.files import atomic_write, write_figure
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["BAND_LEVELS", "PLOT_PARAMS", "SD_FULL_SCALE", "VIDEO_DRAWS", "plot_bands", "read_truth",
           "render_frames", "uncertainty_frames", "write_posterior_netcdf"]

#: the central bands synth writes and draws
BAND_LEVELS = (0.5, 0.9)
#: AAM parameters drawn in bands.png
PLOT_PARAMS = 4
#: predictive draws rendered per frame for the standard-deviation panel
VIDEO_DRAWS = 16
#: grey-level standard deviation shown as white in the panel
SD_FULL_SCALE = 24.0


def write_posterior_netcdf(path: str | os.PathLike, result: SynthesisResult,
                           truth: np.ndarray | None = None) -> Path:
    """``result.to_inference_data(truth)`` as netCDF at ``path``, written atomically."""
    idata = result.to_inference_data(truth=truth)
    return atomic_write(path, lambda tmp: idata.to_netcdf(tmp), suffix=".nc")


def read_truth(path: str | os.PathLike, shape: tuple[int, int]) -> np.ndarray:
    """The ground-truth AAM parameters (T, D) from a ``.npy`` file, in the space of
    ``trajectory.npy`` (mean-removed). ValueError naming the file and the expected shape."""
    p = Path(path)
    try:
        z = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{p}: cannot read the truth as a .npy array ({exc})") from None
    if z.shape != tuple(shape):
        raise ValueError(f"{p}: expected AAM parameters of shape {tuple(shape)} (frames, parameters), "
                         f"found {z.shape}")
    z = np.asarray(z, dtype=np.float64)
    if not np.all(np.isfinite(z)):
        raise ValueError(f"{p}: the truth holds NaN or inf")
    return z


def plot_bands(path: str | os.PathLike, result: SynthesisResult, truth: np.ndarray | None = None,
               n_params: int = PLOT_PARAMS, fps: float = 25.0, title: str | None = None) -> Path:
    """PNG (Agg) of the first ``n_params`` AAM parameters over time: mean, 50 % and 90 %
    bands (:meth:`SynthesisResult.interval`), and ``truth`` (T, D) when given."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    n = max(1, min(int(n_params), result.n_dims))
    t = np.arange(result.n_frames) / fps
    mean = result.mean
    bands = {q: result.interval(q) for q in BAND_LEVELS}
    fig, axes = plt.subplots(n, 1, figsize=(7.5, 1.6 * n + 0.8), sharex=True, squeeze=False)
    for j, ax in enumerate(axes[:, 0]):
        for q, alpha in zip(sorted(BAND_LEVELS, reverse=True), (0.18, 0.38)):
            lo, hi = bands[q]
            ax.fill_between(t, lo[:, j], hi[:, j], color="tab:blue", alpha=alpha, lw=0,
                            label=f"{q:.0%} band")
        ax.plot(t, mean[:, j], color="tab:blue", lw=1.2, label="mean")
        if truth is not None:
            ax.plot(t, truth[:, j], color="k", lw=1.0, label="truth")
        ax.set_ylabel(f"AAM {j + 1}")
    axes[0, 0].legend(fontsize=7, loc="upper right", ncol=4)
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle(title or f"{result.method}: mean and central bands ({result.n_draws} component"
                 f"{'s' if result.n_draws > 1 else ''})", fontsize=9)
    fig.tight_layout()
    return write_figure(path, fig, dpi=100)


def render_frames(aam, params: np.ndarray, chunk: int = 64) -> Iterator[np.ndarray]:
    """``aam.render(params)`` ``chunk`` frames at a time: a generator of (≤ chunk, H, W) uint8
    arrays (what :func:`~bayes_talk.base.video.write_video` streams, so memory does not grow
    with the length), each chunk advancing the open progress stage by its frames
    (:func:`bayes_talk.base.progress.current`)."""
    params = np.atleast_2d(np.asarray(params, dtype=np.float64))
    for a in range(0, params.shape[0], int(chunk)):
        frames = aam.render(params[a:a + int(chunk)])
        progress.current().advance(frames.shape[0])
        yield frames


def uncertainty_frames(aam, result: SynthesisResult, offset: np.ndarray, n_draws: int = VIDEO_DRAWS,
                       seed: int | None = None, chunk: int = 64) -> Iterator[np.ndarray]:
    """The frames (T, H, 2W + gap) uint8 of the mean face | the per-pixel standard deviation
    over ``n_draws`` rendered draws of the AAM predictive (``result.sample``), scaled so that
    ``SD_FULL_SCALE`` grey levels are white, as a generator of ``chunk``-frame arrays (memory
    flat in the length; :func:`~bayes_talk.base.video.write_video` streams them). ``offset`` is
    added to every parameter vector before rendering (the model's AAM offset)."""
    from bayes_talk.base.video import side_by_side

    if int(n_draws) < 2:
        raise ValueError(f"n_draws must be >= 2 for a standard deviation, got {n_draws}")
    offset = np.asarray(offset, dtype=np.float64)
    mean = result.mean + offset
    draws = result.sample(int(n_draws), seed=seed) + offset  # (n, T, D)
    n = float(n_draws)
    for a in range(0, result.n_frames, int(chunk)):
        b = min(a + int(chunk), result.n_frames)
        mean_frames = aam.render(mean[a:b])
        s1 = np.zeros(mean_frames.shape, dtype=np.float64)
        s2 = np.zeros(mean_frames.shape, dtype=np.float64)
        for k in range(int(n_draws)):
            f = aam.render(draws[k, a:b]).astype(np.float64)
            s1 += f
            s2 += f * f
        progress.current().advance((b - a) * (1 + int(n_draws)))
        sd = np.sqrt(np.maximum(s2 / n - (s1 / n) ** 2, 0.0) * n / (n - 1))
        panel = np.clip(np.rint(sd * (255.0 / SD_FULL_SCALE)), 0, 255).astype(np.uint8)
        yield side_by_side(mean_frames, panel)
