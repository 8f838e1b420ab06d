"""Per-frame exports of a synthesis for other tools (``bayes-talk synth --export json|csv``).

Two files, in the format asked for (docs/outputs.md gives the schemas):

* ``frames.json`` / ``frames.csv`` (:class:`FrameExport`): per 25 Hz frame its start time, the
  AAM parameters' predictive mean, standard deviation and exact 5 / 50 / 95 % quantiles (the
  synthesis result's mixture quantiles, :meth:`~bayes_talk.synthesis.result.SynthesisResult.quantile`,
  as ``bands.npz`` gets its bands), and with an AAM the landmarks of the mean (``landmarks.npy``)
  and their standard deviation: ``n_draws`` seeded draws of the predictive
  (:meth:`~bayes_talk.synthesis.result.SynthesisResult.sample`) pushed through the AAM's shape model,
  the population standard deviation of each coordinate over them. The parameters are mean-removed,
  as ``trajectory.npy`` (the JSON header carries the offset to add); the landmarks are pixels.
* ``landmarks_track.json`` / ``landmarks_track.csv`` (:func:`write_landmark_track`): the plain
  landmark track, x and y of every landmark in every frame, for a 2-D tool.

Every file is written atomically (:mod:`bayes_talk.base.files`); numbers are written with
Python's shortest round-trip representation, so :meth:`FrameExport.read` and
:func:`read_landmark_track` give back the very arrays that were written.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bayes_talk.base.files import check_format, write_text
from bayes_talk.synthesis.result import SynthesisResult

__all__ = ["EXPORT_DRAWS", "EXPORT_FORMATS", "EXPORT_QUANTILES", "FRAMES_FORMAT", "TRACK_FORMAT", "FrameExport",
           "export_file_names", "frame_export", "param_names", "read_landmark_track", "write_landmark_track"]

#: the formats ``synth --export`` writes
EXPORT_FORMATS = ("json", "csv")
#: format names and version of the two JSON documents
FRAMES_FORMAT = "bayes_talk.synth_frames"
TRACK_FORMAT = "bayes_talk.landmark_track"
_VERSION = 1
#: the exported quantile levels (column prefixes q05, q50, q95)
EXPORT_QUANTILES = (0.05, 0.5, 0.95)
#: the central band whose ends are the 5 and 95 % quantiles
_CENTRAL = 0.9
#: predictive draws pushed through the shape model for the landmarks' standard deviation
EXPORT_DRAWS = 256
_STATS = ("mean", "sd", "q05", "q50", "q95")
_COORDS = "pixels; x = column, y = row, 0-based, pixel centres at integer coordinates"


def export_file_names(fmt: str) -> dict[str, str]:
    """{"frames": "frames.<fmt>", "track": "landmarks_track.<fmt>"}; ValueError for a format
    other than :data:`EXPORT_FORMATS`."""
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"export format must be one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}")
    return {"frames": f"frames.{fmt}", "track": f"landmarks_track.{fmt}"}


def param_names(aam: Any, n_params: int) -> list[str]:
    """Names of the ``n_params`` AAM parameters: ``c1..cK`` (combined appearance modes), ``tx``,
    ``ty``, ``log_scale``, ``rotation`` (pose), ``texture_mean``, ``log_texture_std``
    (photometric) for an AAM of that size (:attr:`~bayes_talk.features.aam.AAM.param_slices`);
    ``p1..pD`` without one."""
    if aam is None or aam.n_params != n_params:
        return [f"p{k + 1}" for k in range(n_params)]
    return ([f"c{k + 1}" for k in range(aam.n_combined)]
            + ["tx", "ty", "log_scale", "rotation", "texture_mean", "log_texture_std"])


@dataclass
class FrameExport:
    """The per-frame export of one synthesis (module docstring): ``time`` (T,) seconds (frame k
    starts at k / fps and shows [k / fps, (k + 1) / fps)); ``mean``, ``sd``, ``q05``, ``q50``,
    ``q95`` (T, D) mean-removed AAM parameters; ``landmarks``, ``landmark_sd`` (T, P, 2) pixels, or
    None without an AAM; ``offset`` (D,) the model's AAM offset (add it to the parameters before
    reconstructing), or None; ``method``, ``seed`` and ``n_draws`` say how it was made."""

    fps: float
    param_names: list[str]
    time: np.ndarray
    mean: np.ndarray
    sd: np.ndarray
    q05: np.ndarray
    q50: np.ndarray
    q95: np.ndarray
    landmarks: np.ndarray | None = None
    landmark_sd: np.ndarray | None = None
    offset: np.ndarray | None = None
    method: str = ""
    seed: int = 0
    n_draws: int = 0

    @property
    def n_frames(self) -> int:
        """Frames T."""
        return int(self.mean.shape[0])

    @property
    def n_landmarks(self) -> int:
        """Landmarks per frame (0 without an AAM)."""
        return 0 if self.landmarks is None else int(self.landmarks.shape[1])

    # ------------------------------------------------------------------ writing
    def write(self, path: str | os.PathLike) -> Path:
        """Write to ``path`` (atomically) as JSON or CSV by its suffix (``.json`` / ``.csv``)."""
        p = Path(path)
        fmt = p.suffix.lower().lstrip(".")
        if fmt not in EXPORT_FORMATS:
            raise ValueError(f"{p}: an export is written as .json or .csv, not {p.suffix or 'a file without suffix'}")
        return write_text(p, self._json() if fmt == "json" else self._csv())

    def _header(self) -> dict[str, Any]:
        return {"format": FRAMES_FORMAT, "version": _VERSION, "fps": float(self.fps), "n_frames": self.n_frames,
                "n_params": len(self.param_names), "param_names": list(self.param_names),
                "n_landmarks": self.n_landmarks, "quantile_levels": list(EXPORT_QUANTILES),
                "parameters": "mean-removed AAM parameters (add aam_offset before reconstructing)",
                "aam_offset": None if self.offset is None else [float(v) for v in self.offset],
                "landmarks": (None if self.landmarks is None else
                              f"{_COORDS}; landmarks of mean + aam_offset; landmark_sd over "
                              f"{self.n_draws} seeded predictive draws"),
                "method": self.method, "seed": int(self.seed), "landmark_draws": int(self.n_draws)}

    def _frame(self, k: int) -> dict[str, Any]:
        out: dict[str, Any] = {"frame": k, "time": float(self.time[k])}
        for s in _STATS:
            out[s] = [float(v) for v in getattr(self, s)[k]]
        if self.landmarks is not None:
            out["landmarks"] = [[float(x), float(y)] for x, y in self.landmarks[k]]
            out["landmark_sd"] = [[float(x), float(y)] for x, y in self.landmark_sd[k]]
        return out

    def _json(self) -> str:
        head = json.dumps(self._header(), indent=1, allow_nan=False)
        frames = ",\n  ".join(json.dumps(self._frame(k), allow_nan=False) for k in range(self.n_frames))
        return head[:-2] + ',\n "frames": [\n  ' + frames + "\n ]\n}\n"

    def columns(self) -> list[str]:
        """The CSV columns (docs/outputs.md): ``frame``, ``time_s``, then ``mean_<name>`` for
        every parameter, likewise ``sd_``, ``q05_``, ``q50_``, ``q95_``, then (with landmarks)
        ``lm<i>_x``, ``lm<i>_y`` for every landmark i (0-based), then ``lm<i>_sd_x``, ``lm<i>_sd_y``."""
        cols = ["frame", "time_s"] + [f"{s}_{n}" for s in _STATS for n in self.param_names]
        P = range(self.n_landmarks)
        cols += [f"lm{i}_{c}" for i in P for c in ("x", "y")]
        cols += [f"lm{i}_sd_{c}" for i in P for c in ("x", "y")]
        return cols

    def _csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.columns())
        for k in range(self.n_frames):
            row: list[Any] = [k, float(self.time[k])]
            for s in _STATS:
                row += [float(v) for v in getattr(self, s)[k]]
            if self.landmarks is not None:
                row += [float(v) for v in self.landmarks[k].ravel()]
                row += [float(v) for v in self.landmark_sd[k].ravel()]
            w.writerow(row)
        return buf.getvalue()

    # ------------------------------------------------------------------ reading
    @classmethod
    def read(cls, path: str | os.PathLike) -> FrameExport:
        """Read a file written by :meth:`write` (JSON or CSV by its suffix); ValueError naming
        the file when it is not one. From a CSV, ``fps`` is recovered from the times and the
        header-only fields (offset, method, seed, draws) are empty."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ValueError(f"{p}: no such export file") from None
        if p.suffix.lower() == ".json":
            return cls._from_json(text, p)
        if p.suffix.lower() == ".csv":
            return cls._from_csv(text, p)
        raise ValueError(f"{p}: an export is read from .json or .csv")

    @classmethod
    def _from_json(cls, text: str, p: Path) -> FrameExport:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{p}: not valid JSON ({exc})") from None
        check_format(doc, FRAMES_FORMAT, _VERSION, str(p))
        frames = doc.get("frames") or []
        if len(frames) != doc.get("n_frames"):
            raise ValueError(f"{p}: header says {doc.get('n_frames')} frames, the document holds {len(frames)}")

        def stack(key: str) -> np.ndarray:
            return np.array([f[key] for f in frames], dtype=np.float64)

        has_lm = doc.get("n_landmarks", 0) > 0
        off = doc.get("aam_offset")
        return cls(float(doc["fps"]), list(doc["param_names"]), stack("time"),
                   *(stack(s).reshape(len(frames), -1) for s in _STATS),
                   landmarks=stack("landmarks") if has_lm else None,
                   landmark_sd=stack("landmark_sd") if has_lm else None,
                   offset=None if off is None else np.array(off, dtype=np.float64),
                   method=str(doc.get("method", "")), seed=int(doc.get("seed", 0)),
                   n_draws=int(doc.get("landmark_draws", 0)))

    @classmethod
    def _from_csv(cls, text: str, p: Path) -> FrameExport:
        rows = list(csv.reader(io.StringIO(text)))
        if not rows or rows[0][:2] != ["frame", "time_s"]:
            raise ValueError(f"{p}: not a frames export (its first columns must be frame, time_s)")
        head = rows[0]
        try:
            data = np.array([[float(v) for v in r] for r in rows[1:]], dtype=np.float64).reshape(len(rows) - 1,
                                                                                                  len(head))
        except ValueError as exc:
            raise ValueError(f"{p}: every row must hold {len(head)} numbers ({exc})") from None
        names = [c[len("mean_"):] for c in head if c.startswith("mean_")]
        col = {c: i for i, c in enumerate(head)}

        def block(stat: str) -> np.ndarray:
            try:
                return data[:, [col[f"{stat}_{n}"] for n in names]]
            except KeyError as exc:
                raise ValueError(f"{p}: column {exc} is missing") from None

        n_lm = sum(1 for c in head if c.startswith("lm") and c.endswith("_x") and "_sd_" not in c)
        lm = sd = None
        if n_lm:
            try:
                lm = data[:, [col[f"lm{i}_{c}"] for i in range(n_lm) for c in "xy"]].reshape(-1, n_lm, 2)
                sd = data[:, [col[f"lm{i}_sd_{c}"] for i in range(n_lm) for c in "xy"]].reshape(-1, n_lm, 2)
            except KeyError as exc:
                raise ValueError(f"{p}: column {exc} is missing") from None
        t = data[:, 1]
        fps = float(data[-1, 0] / t[-1]) if len(t) > 1 and t[-1] > 0 else float("nan")
        return cls(fps, names, t, *(block(s) for s in _STATS), landmarks=lm, landmark_sd=sd)


def frame_export(result: SynthesisResult, fps: float, *, aam: Any = None, offset: np.ndarray | None = None,
                 seed: int = 0, n_draws: int = EXPORT_DRAWS) -> FrameExport:
    """The :class:`FrameExport` of a synthesis ``result`` at ``fps`` frames per second.

    The 5 and 95 % quantiles are the central 90 % interval of the result
    (:meth:`~bayes_talk.synthesis.result.SynthesisResult.interval`), bit for bit ``bands.npz``'s
    ``lower90`` and ``upper90``; the 50 % one its median.
    With an ``aam`` (and its ``offset``, the model's AAM offset): the landmarks of
    ``result.mean + offset`` (those ``synth`` writes to ``landmarks.npy``) and their standard
    deviation over ``n_draws`` (>= 2) draws of the predictive, ``result.sample(n_draws, seed)``,
    each pushed through the AAM's shape model (:meth:`~bayes_talk.features.aam.AAM.reconstruct_landmarks`).
    """
    if not (isinstance(fps, (int, float, np.floating)) and math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    if not isinstance(n_draws, (int, np.integer)) or n_draws < 2:
        raise ValueError(f"n_draws must be an integer >= 2 (a standard deviation needs two draws), got {n_draws!r}")
    T, D = result.n_frames, result.n_dims
    lo, hi = result.interval(_CENTRAL)            # as bands.npz: its lower90 / upper90
    qs = {"q05": lo, "q50": result.quantile(EXPORT_QUANTILES[1]), "q95": hi}
    lm = lm_sd = off = None
    if aam is not None:
        if offset is None:
            raise ValueError("an export with landmarks needs the model's AAM offset (offset=...)")
        off = np.asarray(offset, dtype=np.float64)
        if off.shape != (D,):
            raise ValueError(f"offset: expected shape ({D},) to match the {D} AAM parameters, got {off.shape}")
        lm = aam.reconstruct_landmarks(result.mean + off)
        draws = result.sample(int(n_draws), seed=int(seed)) + off            # (n, T, D)
        lm_draws = aam.reconstruct_landmarks(draws.reshape(-1, D)).reshape(int(n_draws), T, -1, 2)
        lm_sd = lm_draws.std(axis=0)
    return FrameExport(float(fps), param_names(aam, D), np.arange(T) / float(fps), result.mean,
                       np.sqrt(result.var), qs["q05"], qs["q50"], qs["q95"], landmarks=lm, landmark_sd=lm_sd,
                       offset=off, method=result.method, seed=int(seed), n_draws=int(n_draws) if aam is not None else 0)


def write_landmark_track(path: str | os.PathLike, landmarks: np.ndarray, fps: float,
                         image_shape: tuple[int, int] | None = None) -> Path:
    """The plain landmark track (T, P, 2) at ``path`` (atomically), JSON or CSV by its suffix.

    JSON: ``{"format": "bayes_talk.landmark_track", "version": 1, "fps", "n_frames",
    "n_landmarks", "image_width", "image_height", "coordinates", "frames": [[[x, y], ...], ...]}``
    (frame-major, then landmark). CSV: one row per landmark per frame, columns
    ``frame, time_s, landmark, x, y``."""
    p = Path(path)
    lm = np.asarray(landmarks, dtype=np.float64)
    if lm.ndim != 3 or lm.shape[2] != 2 or not np.all(np.isfinite(lm)):
        raise ValueError(f"landmarks: expected finite coordinates of shape (T, P, 2), got {lm.shape}")
    fmt = p.suffix.lower().lstrip(".")
    if fmt == "json":
        h, w = (None, None) if image_shape is None else (int(image_shape[0]), int(image_shape[1]))
        head = json.dumps({"format": TRACK_FORMAT, "version": _VERSION, "fps": float(fps), "n_frames": lm.shape[0],
                           "n_landmarks": lm.shape[1], "image_width": w, "image_height": h,
                           "coordinates": _COORDS}, indent=1)
        frames = ",\n  ".join(json.dumps([[float(x), float(y)] for x, y in f]) for f in lm)
        return write_text(p, head[:-2] + ',\n "frames": [\n  ' + frames + "\n ]\n}\n")
    if fmt == "csv":
        buf = io.StringIO()
        wr = csv.writer(buf, lineterminator="\n")
        wr.writerow(["frame", "time_s", "landmark", "x", "y"])
        for k, f in enumerate(lm):
            t = k / float(fps)
            wr.writerows([k, t, i, float(x), float(y)] for i, (x, y) in enumerate(f))
        return write_text(p, buf.getvalue())
    raise ValueError(f"{p}: a landmark track is written as .json or .csv, not {p.suffix or 'a file without suffix'}")


def read_landmark_track(path: str | os.PathLike) -> tuple[np.ndarray, float]:
    """(landmarks (T, P, 2), fps) of a track written by :func:`write_landmark_track`; ValueError
    naming the file when it is not one."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{p}: no such landmark track") from None
    if p.suffix.lower() == ".json":
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{p}: not valid JSON ({exc})") from None
        check_format(doc, TRACK_FORMAT, _VERSION, str(p))
        lm = np.array(doc["frames"], dtype=np.float64).reshape(doc["n_frames"], doc["n_landmarks"], 2)
        return lm, float(doc["fps"])
    if p.suffix.lower() == ".csv":
        rows = list(csv.reader(io.StringIO(text)))
        if not rows or rows[0] != ["frame", "time_s", "landmark", "x", "y"]:
            raise ValueError(f"{p}: not a landmark track (columns must be frame, time_s, landmark, x, y)")
        try:
            data = np.array([[float(v) for v in r] for r in rows[1:]], dtype=np.float64)
        except ValueError as exc:
            raise ValueError(f"{p}: every row must hold 5 numbers ({exc})") from None
        if data.ndim != 2 or data.shape[1] != 5 or data.shape[0] == 0:
            raise ValueError(f"{p}: every row must hold 5 numbers")
        T, P = int(data[:, 0].max()) + 1, int(data[:, 2].max()) + 1
        if data.shape[0] != T * P:
            raise ValueError(f"{p}: {data.shape[0]} rows, expected {T} frames x {P} landmarks")
        order = np.lexsort((data[:, 2], data[:, 0]))
        lm = data[order, 3:5].reshape(T, P, 2)
        t = data[order[::P], 1]
        fps = float((T - 1) / t[-1]) if T > 1 and t[-1] > 0 else float("nan")
        return lm, fps
    raise ValueError(f"{p}: a landmark track is read from .json or .csv")
