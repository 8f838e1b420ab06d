"""File sets that belong together: a model bundle's hash manifest and an output set's record.

Model bundle (``bayes-talk train``). After every other file of the model directory is
written, :func:`write_bundle_manifest` writes ``bundle_manifest.json``: the SHA-256 of
every file in the directory, written *last* and atomically. :func:`verify_bundle` refuses
(:class:`BundleError`, a ValueError naming the file) a directory

* without the manifest although its descriptor says it should have one -- a save that
  was interrupted (``train --force`` removes the old manifest and descriptor *first*, so an
  interrupted overwrite never looks complete), or
* with a listed file missing or whose bytes differ -- e.g. ``arrays.npz`` or ``aam.npz``
  copied from another model.

Output set (``bayes-talk synth``). :class:`OutputSet` records in ``.bayes_talk_outputs.json``
the files one run wrote into its output directory; the next run with ``--force`` removes
the files of the earlier run that it does not write itself (only files listed there,
never anything else: a directory without the record has no files of ours to remove), so
the directory always holds one run's complete output. :func:`check_output_dir` refuses,
before any work, an output path that is a file or lies where nothing can be written.
"""
from __future__ import annotations

import json
import logging
import os
import tempfile
from pathlib import Path

from bayes_talk.base.files import check_format, sha256_file, write_json

__all__ = [
    "BUNDLE_MANIFEST",
    "DESCRIPTOR",
    "DESCRIPTOR_FORMAT",
    "DESCRIPTOR_VERSION",
    "ESTIMATOR_DIR",
    "OUTPUT_RECORD",
    "BundleError",
    "OutputSet",
    "begin_bundle",
    "check_output_dir",
    "read_descriptor",
    "sha256_file",
    "verify_bundle",
    "write_bundle_manifest",
    "write_descriptor",
]

log = logging.getLogger(__name__)

#: the descriptor of a trained-model directory (what kind of model, its front end), written by
#: :func:`write_descriptor` (``bayes-talk train``) and read by :func:`read_descriptor`
DESCRIPTOR = "bayes_talk_model.json"
DESCRIPTOR_FORMAT = "bayes_talk.trained_model"
DESCRIPTOR_VERSION = 1
#: the sub-directory of a trained-model directory that holds its estimator, as
#: :meth:`bayes_talk.estimators.base.Estimator.save` writes every one
ESTIMATOR_DIR = "estimator"
BUNDLE_MANIFEST = "bundle_manifest.json"
OUTPUT_RECORD = ".bayes_talk_outputs.json"
_FORMAT = "bayes_talk.bundle_manifest"


class BundleError(ValueError):
    """A model directory whose files do not belong together or whose save is incomplete."""


def _bundle_files(directory: Path) -> list[Path]:
    return sorted(p for p in directory.rglob("*")
                  if p.is_file() and p.name != BUNDLE_MANIFEST and not p.name.startswith("."))


def check_output_dir(directory: str | Path, flag: str = "--out") -> Path:
    """``directory`` as a Path, after checking -- before any work -- that it is a directory
    or can be created as one, and that files can be created in it (a probe file, removed
    at once, in it or in its nearest existing ancestor). ValueError naming the path, the
    reason and what to do otherwise; nothing is created."""
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise ValueError(f"{flag} {d}: is a file, not a directory; choose a directory (created if missing)")
    probe = d
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise ValueError(f"{flag} {d}: {probe} is a file, so the directory cannot be created")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".bayes_talk_probe.", dir=probe)
    except OSError as exc:
        where = "into it" if probe == d else f"into {probe} to create it"
        raise ValueError(f"{flag} {d}: cannot write {where} ({exc.strerror or exc}); choose a writable "
                         "directory") from None
    os.close(fd)
    os.unlink(tmp)
    return d


def begin_bundle(directory: str | Path, descriptor: str) -> None:
    """Before (over)writing a bundle: remove its manifest, then its descriptor, so that a
    save interrupted from here on leaves a directory that refuses to load."""
    d = Path(directory)
    for name in (BUNDLE_MANIFEST, descriptor):
        p = d / name
        if p.is_file():
            p.unlink()


def write_bundle_manifest(directory: str | Path) -> Path:
    """Hash every file of ``directory`` (sub-directories included) into ``bundle_manifest.json``."""
    d = Path(directory)
    files = {p.relative_to(d).as_posix(): sha256_file(p) for p in _bundle_files(d)}
    return write_json(d / BUNDLE_MANIFEST, {"format": _FORMAT, "version": 1, "sha256": files})


def verify_bundle(directory: str | Path) -> dict[str, str]:
    """Check every file listed in the manifest against its hash; BundleError naming the
    first file that is missing or differs (or the missing manifest itself)."""
    d = Path(directory)
    mp = d / BUNDLE_MANIFEST
    if not mp.is_file():
        raise BundleError(f"{mp} is missing: the model's save was interrupted (or the directory was "
                          "assembled by hand); train the model again")
    try:
        m = json.loads(mp.read_text(encoding="utf-8"))
        files = dict(m["sha256"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BundleError(f"{mp}: unreadable bundle manifest ({exc}); train the model again") from None
    for rel, digest in sorted(files.items()):
        p = d / rel
        if ".." in Path(rel).parts or not p.is_file():
            raise BundleError(f"{p}: listed in {mp.name} but missing; the model directory is incomplete")
        if sha256_file(p) != digest:
            raise BundleError(f"{p}: does not belong to this model (its SHA-256 differs from the one "
                              f"recorded in {mp.name} when the model was saved -- copied from another "
                              "model, or changed since); train the model again or restore the file")
    return files


def write_descriptor(directory: str | Path, fields: dict) -> Path:
    """Write the trained-model descriptor (:data:`DESCRIPTOR`) of ``directory``: ``fields``
    (the model's kind, corpus, front end, ...) under its format name and version, and
    ``bundle_manifest: true`` (the directory is hashed; :func:`write_bundle_manifest`)."""
    return write_json(Path(directory) / DESCRIPTOR, {"format": DESCRIPTOR_FORMAT, "version": DESCRIPTOR_VERSION,
                                                     **fields, "bundle_manifest": True})


def read_descriptor(directory: str | Path) -> dict:
    """The descriptor of a trained-model directory, after checking its format and, when it
    was saved with one, every file against the manifest (:func:`verify_bundle`).
    FileNotFoundError when there is none (saying when the save was interrupted); ValueError
    naming the file when it is truncated or of another format; :class:`BundleError` when
    the files do not belong together."""
    d = Path(directory)
    p = d / DESCRIPTOR
    if not p.exists():
        extra = (" -- its save was interrupted; train it again" if (d / ESTIMATOR_DIR).exists() else "")
        raise FileNotFoundError(f"{d} is not a bayes_talk model directory (no {DESCRIPTOR}){extra}")
    try:
        desc = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p} is truncated or not JSON ({exc})") from None
    check_format(desc, DESCRIPTOR_FORMAT, DESCRIPTOR_VERSION, str(p))
    if desc.get("bundle_manifest") or (d / BUNDLE_MANIFEST).exists():
        verify_bundle(d)
    else:
        log.warning("%s has no %s (saved before bundles were hashed): its files cannot be checked "
                    "to belong together", d, BUNDLE_MANIFEST)
    return desc


class OutputSet:
    """The files one run writes into ``directory``; see the module docstring."""

    def __init__(self, directory: str | Path, known: tuple[str, ...] = ()) -> None:
        self.directory = Path(directory)
        self.record = self.directory / OUTPUT_RECORD
        self.known = tuple(known)

    def previous(self) -> list[str]:
        """Files the previous run recorded (relative names). Without a record: none -- a file
        named like one of the tool's outputs (``known``) may be the user's, so it is never
        removed (it is only overwritten when this run writes that name, with ``--force``)."""
        try:
            files = json.loads(self.record.read_text(encoding="utf-8"))["files"]
        except (OSError, ValueError, KeyError, TypeError):
            return []
        return [f for f in files if isinstance(f, str) and ".." not in Path(f).parts and "/" not in f]

    def present(self) -> list[str]:
        """The tool's output names (``known``) and the recorded files that exist now: what a
        run without ``--force`` must not overwrite."""
        return sorted({n for n in (*self.known, *self.previous()) if (self.directory / n).exists()})

    def commit(self, written: list[str | Path]) -> list[str]:
        """After a run wrote ``written``: remove the earlier run's files it did not rewrite,
        then record the new set. Returns the names removed."""
        names = sorted({Path(w).name for w in written})
        removed = []
        for old in self.previous():
            p = self.directory / old
            if old not in names and p.is_file():
                p.unlink()
                removed.append(old)
        if removed:
            log.info("%s: removed %s of the earlier run", self.directory, ", ".join(removed))
        write_json(self.record, {"files": names})
        return removed
