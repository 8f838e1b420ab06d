"""Many WAV files through one loaded model (``bayes-talk synth MODEL --audio-dir DIR`` or
``--audio-list FILE``)::

    WAV files [+ labels] ──load_trained, once──▶ synth(model, WAV, labels, OUT/<stem>/) per file
                         ──▶ each file's synth outputs, OUT/summary.json and OUT/summary.csv

Each file goes through :func:`bayes_talk.pipeline.talking_face.synth` given the model already
loaded, so its directory holds exactly what one ``synth`` run with the same options writes.
Labels: the ``.lab`` or ``.TextGrid`` beside the WAV (``X.lab`` first), the second column of
an audio list, else the model's phone recogniser (written to ``labels.lab``, as synth does).
A file that fails -- unreadable audio, labels that do not fit it, no speech -- is logged
with its error and recorded in the summary, and the others go on. Existing outputs are never
replaced without ``force`` (the rules of :class:`bayes_talk.base.bundle.OutputSet`), checked
for every file before any work. ``workers`` > 1 runs the files in that many worker processes
(:class:`bayes_talk.base.executor.ProcessExecutor`), each of which loads the model once.
"""
from __future__ import annotations

import contextlib
import csv
import io
import logging
import os
import shlex
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bayes_talk.base.bundle import OutputSet, check_output_dir, read_descriptor
from bayes_talk.base.executor import ProcessExecutor
from bayes_talk.base.files import write_json, write_text
from bayes_talk.base.progress import bar
from bayes_talk.pipeline.talking_face import SYNTH_OUTPUT_NAMES, synth
from bayes_talk.pipeline.trained import TrainedModel, load_trained

__all__ = ["SUMMARY_COLUMNS", "SUMMARY_NAMES", "BatchInput", "BatchResult", "inputs_from_dir", "inputs_from_list",
           "labels_beside", "summary_table", "synth_many"]

log = logging.getLogger(__name__)

#: the batch's own files in its output directory
SUMMARY_NAMES = ("summary.json", "summary.csv")
#: the columns of summary.csv, the fields of each file's entry in summary.json
SUMMARY_COLUMNS = ("file", "labels", "out", "frames", "seconds", "status", "error")
#: synth's options that apply to every file of a batch (the per-file ones -- labels, text,
#: transcript, truth -- come from the inputs or do not apply)
BATCH_OPTIONS = frozenset({"algorithm", "init", "video", "posterior", "n_draws", "seed", "tier", "calibrated",
                           "sampler_options", "lowpass_hz", "export"})
#: what the labels column says for a file labelled by the phone recogniser
RECOGNISED = "recognised"
_SUMMARY_FORMAT = "bayes_talk.synth_batch"


@dataclass(frozen=True)
class BatchInput:
    """One file of a batch: the WAV and its phone labels (``.lab`` or ``.TextGrid``; None:
    the model's phone recogniser)."""

    wav: Path
    labels: Path | None = None


@dataclass
class BatchResult:
    """What :func:`synth_many` did: one row per input, in input order (the fields of
    :data:`SUMMARY_COLUMNS`: ``status`` "ok" or "failed", ``error`` the failure's message),
    and the summary files written."""

    rows: list[dict]
    summary_json: Path
    summary_csv: Path

    @property
    def failed(self) -> list[dict]:
        """The rows of the files that failed."""
        return [r for r in self.rows if r["status"] != "ok"]


def labels_beside(wav: str | os.PathLike) -> Path | None:
    """``X.lab`` beside ``X.wav`` if it exists, else ``X.TextGrid``, else None."""
    wav = Path(wav)
    for suffix in (".lab", ".TextGrid"):
        p = wav.with_suffix(suffix)
        if p.is_file():
            return p
    return None


def inputs_from_dir(directory: str | os.PathLike) -> list[BatchInput]:
    """Every ``*.wav`` of ``directory`` (not its sub-directories), in name order, with the
    labels beside each (:func:`labels_beside`). ValueError when there is none."""
    d = Path(directory)
    if not d.is_dir():
        raise ValueError(f"--audio-dir {d}: not a directory")
    wavs = sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() == ".wav")
    if not wavs:
        raise ValueError(f"--audio-dir {d}: no .wav files in it")
    return [BatchInput(w, labels_beside(w)) for w in wavs]


def inputs_from_list(path: str | os.PathLike) -> list[BatchInput]:
    """The files of an audio list: one WAV a line, optionally followed by its labels file
    (whitespace between; quote a path that holds spaces; ``#`` starts a comment; relative
    paths are relative to the list's directory). Without a labels column a WAV's labels are
    those beside it (:func:`labels_beside`). ValueError naming the line of a malformed entry."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"--audio-list {p}: cannot read it ({exc})") from None
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        try:
            fields = shlex.split(line, comments=True)
        except ValueError as exc:
            raise ValueError(f"{p}, line {n}: {exc}") from None
        if not fields:
            continue
        if len(fields) > 2:
            raise ValueError(f"{p}, line {n}: {len(fields)} fields; expected a WAV path and optionally its "
                             "labels path (quote a path that holds spaces)")
        wav, *lab = (Path(f) if Path(f).is_absolute() else p.parent / f for f in fields)
        out.append(BatchInput(wav, lab[0] if lab else labels_beside(wav)))
    if not out:
        raise ValueError(f"--audio-list {p}: no files listed")
    return out


def _check_outputs(inputs: list[BatchInput], out: Path, force: bool) -> None:
    """Refuse, before any work, two inputs that would write to one directory and (without
    ``force``) outputs of an earlier run."""
    seen: dict[str, Path] = {}
    for inp in inputs:
        if inp.wav.stem in seen:
            raise ValueError(f"{seen[inp.wav.stem]} and {inp.wav} would both write to {out / inp.wav.stem}; "
                             "rename one")
        seen[inp.wav.stem] = inp.wav
    if force:
        return
    held = [out / n for n in OutputSet(out, SUMMARY_NAMES).present()]
    held += [out / s / n for s in seen for n in OutputSet(out / s, SYNTH_OUTPUT_NAMES).present()]
    if held:
        more = f" and {len(held) - 3} more" if len(held) > 3 else ""
        raise FileExistsError(f"{out} already holds outputs ({', '.join(map(str, held[:3]))}{more}); choose "
                              "another directory or pass --force")


_LOADED: dict[str, TrainedModel] = {}


def _loaded(model: TrainedModel | str) -> TrainedModel:
    """``model`` itself, or the model of that directory, loaded once per process."""
    if isinstance(model, TrainedModel):
        return model
    if model not in _LOADED:
        _LOADED[model] = load_trained(model)
    return _LOADED[model]


@contextlib.contextmanager
def _records_named(name: str):
    """Within the block every log record (warnings included) starts with ``[name]``: which
    file of the batch a warning such as "did not converge" is about."""
    previous = logging.getLogRecordFactory()
    tag = f"[{name}] "

    def factory(*args, **kwargs):
        record = previous(*args, **kwargs)
        record.msg = (tag.replace("%", "%%") if record.args else tag) + str(record.msg)
        return record

    logging.setLogRecordFactory(factory)
    try:
        yield
    finally:
        logging.setLogRecordFactory(previous)


def _synth_one(task: tuple) -> dict:
    """One file of a batch: synth into its directory; the summary row, ``status`` "failed"
    with the error's message when it raised (an interrupt is not caught)."""
    model, inp, out, options = task
    row = {"file": str(inp.wav), "labels": str(inp.labels) if inp.labels is not None else RECOGNISED,
           "out": str(out), "frames": None, "seconds": None, "status": "ok", "error": None}
    t0 = time.perf_counter()
    with _records_named(inp.wav.name):
        try:
            written = synth(_loaded(model), inp.wav, inp.labels, out, **options)
            row["frames"] = int(np.load(written["trajectory"], mmap_mode="r").shape[0])
        except Exception as exc:  # noqa: BLE001 -- a file's failure is reported and the batch goes on
            row.update(status="failed", error=str(exc) or type(exc).__name__)
            log.error("%s (skipped; the other files go on)", row["error"])
    row["seconds"] = round(time.perf_counter() - t0, 3)
    return row


def synth_many(model_dir: str | os.PathLike | TrainedModel, inputs: list[BatchInput], out_dir: str | os.PathLike,
               *, workers: int = 1, force: bool = False, **options) -> BatchResult:
    """Synthesise every input into ``out_dir/<WAV stem>/`` with one model load; see the module
    docstring. ``options`` are :func:`~bayes_talk.pipeline.talking_face.synth`'s that apply to
    every file (:data:`BATCH_OPTIONS`: ``posterior``, ``n_draws``, ``seed``, ``video``,
    ``export``, ...), ``force`` as synth's, for every file and for ``summary.json`` /
    ``summary.csv``. ``workers``: processes synthesising files at once (1: this process; more
    cannot be combined with sampler chains in processes, ``sampler_options["workers"]``).

    Returns the rows of the summary (file, labels, out, frames, wall seconds, status, error);
    a failed file does not raise: look at :attr:`BatchResult.failed`.
    """
    unknown = set(options) - BATCH_OPTIONS
    if unknown:
        raise ValueError(f"synth_many: {', '.join(sorted(unknown))} cannot apply to every file of a batch "
                         f"(options: {', '.join(sorted(BATCH_OPTIONS))}); labels come with the inputs")
    if int(workers) != workers or workers < 1:
        raise ValueError(f"--file-workers: expected an integer >= 1, found {workers!r}")
    chain_workers = (options.get("sampler_options") or {}).get("workers")
    if workers > 1 and chain_workers is not None and chain_workers > 1:
        raise ValueError("--file-workers and --workers both start processes: give one of them (files in "
                         "parallel, or one file's NUTS chains in parallel)")
    out = check_output_dir(out_dir)
    inputs = [BatchInput(Path(i.wav), None if i.labels is None else Path(i.labels)) for i in inputs]
    if not inputs:
        raise ValueError("synth_many: no input files")
    _check_outputs(inputs, out, force)
    if workers > 1:                           # each worker loads the model from its directory, once
        where = model_dir.directory if isinstance(model_dir, TrainedModel) else model_dir
        if where is None:
            raise ValueError("--file-workers: worker processes load the model from its directory, and this "
                             "model was not loaded from one")
        read_descriptor(where)                # a broken model fails here, not once per worker
        model = str(where)
    else:
        model = model_dir if isinstance(model_dir, TrainedModel) else load_trained(model_dir)
    tasks = [(model, inp, out / inp.wav.stem, {**options, "force": force}) for inp in inputs]
    if workers > 1:
        with ProcessExecutor(workers) as ex:
            rows = ex.map(_synth_one, tasks, desc="synth files", unit="file")
    else:
        rows = [_synth_one(t) for t in bar(tasks, total=len(tasks), desc="synth files", unit="file")]
    return _write_summary(out, rows, model_dir)


def _write_summary(out: Path, rows: list[dict], model_dir) -> BatchResult:
    """summary.json and summary.csv of ``rows`` in ``out`` (recorded as the batch's output set)."""
    n_failed = sum(r["status"] != "ok" for r in rows)
    where = model_dir.directory if isinstance(model_dir, TrainedModel) else model_dir
    js = write_json(out / SUMMARY_NAMES[0], {"format": _SUMMARY_FORMAT, "version": 1, "model": str(where),
                                             "n_files": len(rows), "n_ok": len(rows) - n_failed,
                                             "n_failed": n_failed, "files": rows})
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows({k: "" if r[k] is None else r[k] for k in SUMMARY_COLUMNS} for r in rows)
    cs = write_text(out / SUMMARY_NAMES[1], buf.getvalue())
    OutputSet(out, SUMMARY_NAMES).commit([js, cs])
    return BatchResult(rows, js, cs)


def summary_table(rows: list[dict]) -> str:
    """The summary as a plain-text table: file, frames, wall seconds, status or the error."""
    cells = [("file", "frames", "seconds", "status")]
    for r in rows:
        status = "ok" if r["status"] == "ok" else f"FAILED: {r['error']}"
        cells.append((r["file"], "-" if r["frames"] is None else str(r["frames"]),
                      "-" if r["seconds"] is None else f"{r['seconds']:.1f}", status))
    wide = [max(len(c[i]) for c in cells) for i in range(3)]
    return "\n".join(f"{c[0]:<{wide[0]}}  {c[1]:>{wide[1]}}  {c[2]:>{wide[2]}}  {c[3]}" for c in cells)
