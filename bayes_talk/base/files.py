"""Safe file output: every file the package writes goes through :func:`atomic_write`.

A file is written to a temporary name in its own directory and moved into place with
``os.replace``, so a reader (or a crash) never sees half a file and an existing file is
only ever replaced whole. Arrays are stored as ``.npy``/``.npz`` readable with
``allow_pickle=False``; ``.npz`` members get a fixed timestamp so the same arrays always
give the same bytes.
"""
from __future__ import annotations

import io
import json
import os
import tempfile
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

_ZIP_DATE = (1980, 1, 1, 0, 0, 0)
_UMASK = os.umask(0)
os.umask(_UMASK)


def atomic_write(path: str | os.PathLike, write: Callable[[str], None], suffix: str = ".tmp") -> Path:
    """Call ``write(tmp_path)`` then move the temporary file onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual mode
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes (read in 1 MiB chunks)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))


def write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically."""
    def w(tmp: str) -> None:
        with open(tmp, "w", encoding=encoding, newline="\n") as f:
            f.write(text)

    return atomic_write(path, w)


def write_json(path: str | os.PathLike, obj, sort_keys: bool = False) -> Path:
    """Write ``obj`` as JSON to ``path`` atomically."""
    return write_text(path, json.dumps(obj, indent=1, sort_keys=sort_keys) + "\n")


def write_npy(path: str | os.PathLike, arr: np.ndarray) -> Path:
    """Write one array as ``.npy`` to ``path`` atomically."""
    def w(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.save(f, np.asarray(arr), allow_pickle=False)

    return atomic_write(path, w)


def write_npz(path: str | os.PathLike, arrays: Mapping[str, np.ndarray], compress: bool = False) -> Path:
    """An ``.npz`` of the given arrays, members in the given order with a fixed timestamp
    (deflated if ``compress``): byte-identical for identical arrays. A Fortran-ordered array
    is stored and read back Fortran-ordered, so that a loaded model computes exactly as the
    saved one (BLAS rounds a product by the operands' layout). Object arrays are refused
    (they would need pickle)."""
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED

    def w(tmp: str) -> None:
        with zipfile.ZipFile(tmp, "w", compression=method) as zf:
            for name, arr in arrays.items():
                arr = np.asanyarray(arr)
                if arr.dtype.hasobject:
                    raise ValueError(f"{path}: array {name!r} has dtype object; refusing to pickle")
                info = zipfile.ZipInfo(name + ".npy", date_time=_ZIP_DATE)
                info.compress_type = method
                info.external_attr = 0o644 << 16
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.asarray(arr, order="K"), allow_pickle=False)
                zf.writestr(info, buf.getvalue())

    return atomic_write(path, w)


def write_model_files(jpath: str | os.PathLike, npath: str | os.PathLike, meta: dict,
                      arrays: Mapping[str, np.ndarray]) -> Path:
    """Write a JSON + NPZ model pair: the NPZ first, then the JSON with the NPZ's name and
    SHA-256 (``npz_file``, ``npz_sha256``), each atomically; returns the JSON path.
    :func:`read_model_files` refuses an NPZ whose hash differs."""
    npath = write_npz(npath, arrays)
    return write_json(jpath, {**meta, "npz_file": npath.name, "npz_sha256": sha256_file(npath)})


def read_model_files(jpath: Path, npath: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a JSON + NPZ model pair, turning every kind of damage into a ValueError naming
    the file: a truncated or non-JSON JSON, a truncated NPZ, or an NPZ that is not the one
    the JSON was saved with (``npz_sha256``, :func:`write_model_files`)."""
    jpath, npath = Path(jpath), Path(npath)
    for p in (jpath, npath):
        if not p.exists():
            raise FileNotFoundError(f"model file {p} does not exist")
    try:
        meta = json.loads(jpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"model file {jpath} is truncated or not JSON ({exc})") from None
    try:
        with np.load(npath, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as exc:
        raise ValueError(f"model file {npath} is truncated or corrupt ({exc})") from None
    want = meta.get("npz_sha256") if isinstance(meta, dict) else None
    if want is not None and sha256_file(npath) != want:
        raise ValueError(f"model file {npath}: SHA-256 differs from the one {jpath.name} recorded when the "
                         "model was saved (copied from another model, or changed since)")
    return meta, arrays


def check_format(meta: object, name: str, version: int, where: str) -> dict:
    """The one check of a saved file's ``format`` and ``version`` fields: ValueError naming
    ``where`` (the file or what it should hold) and the expected and found values."""
    if not isinstance(meta, dict):
        raise ValueError(f"{where}: expected a JSON object, found {type(meta).__name__}")  # noqa: TRY004
    if meta.get("format") != name:
        raise ValueError(f"{where}: format expected {name!r}, found {meta.get('format')!r}")
    if meta.get("version") != version:
        raise ValueError(f"{where}: version expected {version}, found {meta.get('version')!r} (of format "
                         f"{name!r}; this bayes_talk reads version {version} only)")
    return meta


def write_figure(path: str | os.PathLike, fig, dpi: int = 100) -> Path:
    """A matplotlib figure as PNG at ``path`` (atomically); the figure is closed after."""
    import matplotlib.pyplot as plt

    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi), suffix=".png")
    finally:
        plt.close(fig)


def check_writable_json(path: str | Path) -> Path:
    """Fail fast (ValueError) unless a file can be created at ``path`` (and beside it)."""
    p = Path(path)
    if p.suffix.lower() != ".json":
        raise ValueError(f"--json path must end in .json, got {str(p)!r}")
    if p.is_dir():
        raise ValueError(f"cannot write {p}: it is a directory")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"cannot write {p}: directory {parent} does not exist")
    if p.exists() and not os.access(p, os.W_OK):
        raise ValueError(f"cannot write {p}: file is not writable")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".probe", dir=parent)
    except OSError as exc:
        raise ValueError(f"cannot write {p}: {exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(tmp)
    return p
