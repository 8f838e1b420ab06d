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
    return atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))


def write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    def w(tmp: str) -> None:
        with open(tmp, "w", encoding=encoding, newline="\n") as f:
            f.write(text)

    return atomic_write(path, w)


def write_json(path: str | os.PathLike, obj, sort_keys: bool = False) -> Path:
    return write_text(path, json.dumps(obj, indent=1, sort_keys=sort_keys) + "\n")


def write_npy(path: str | os.PathLike, arr: np.ndarray) -> Path:
    def w(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.save(f, np.asarray(arr), allow_pickle=False)

    return atomic_write(path, w)


def write_npz(path: str | os.PathLike, arrays: Mapping[str, np.ndarray], compress: bool = False) -> Path:
    """An ``.npz`` of the given arrays, members in the given order with a fixed timestamp
    (deflated if ``compress``): byte-identical for identical arrays. Object arrays are
    refused (they would need pickle)."""
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
                np.lib.format.write_array(buf, np.asarray(arr, order="C"), allow_pickle=False)
                zf.writestr(info, buf.getvalue())

    return atomic_write(path, w)


def write_figure(path: str | os.PathLike, fig, dpi: int = 100) -> Path:
    """A matplotlib figure as PNG at ``path`` (atomically); the figure is closed after."""
    import matplotlib.pyplot as plt

    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi), suffix=".png")
    finally:
        plt.close(fig)
