"""Phone segmentations: HTK ``.lab`` and Praat TextGrid I/O, and 25 Hz frame labels.

An *interval list* is ``list[tuple[float, float, str]]``: ``(start_s, end_s, label)`` with
times in seconds, ``start < end``, sorted and non-overlapping.

HTK ``.lab`` (HTK Book §6.3): one segment a line, ``start end label [score] [aux ...]``
with integer times in units of 100 ns. We write ``round(t * 1e7)`` and read ``k / 1e7``,
so a file survives read -> write byte for byte (lossless), and so do interval lists
whose times are multiples of 100 ns (``k / 1e7`` for integer k). Extra columns are
ignored on reading; HTK multiple-alternative files (``///``) are refused.

Praat TextGrid: we write the long ("ooTextFile") text format, one IntervalTier named
``phones``, times printed with Python's shortest round-trip ``repr``, so read(write(x))
== x exactly for any float64 times. We read both the long and the short text formats
(UTF-8, or UTF-16 with a BOM, as Praat writes when labels are not ASCII).

Frame labels (englebienne2008 §2: "each video frame is labelled with the phoneme that
labels most of the corresponding sound frames"): frame k covers ``[k/fps, (k+1)/fps)``;
each label scores the total time it overlaps the frame (continuous-time overlap, the
limit of counting sound frames); time not covered by any interval counts for ``sil``.
The label with the largest overlap wins; ties (within 1e-9 s) go to the label that
starts earliest inside the frame.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from bayes_talk.base.files import write_text
from bayes_talk.data.phones import SILENCE, check_phone

__all__ = [
    "Interval",
    "choose_tier",
    "frame_labels",
    "normalize_phone",
    "read_lab",
    "read_labels",
    "read_textgrid",
    "validate_intervals",
    "write_lab",
    "write_textgrid",
]

Interval = tuple[float, float, str]

_HTK_UNITS = 10_000_000  # 100 ns units per second
_TIE_TOL = 1e-9


# ---------------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------------

def validate_intervals(intervals: list[Interval], where: str = "", phones: bool = True,
                       tol: float = 0.0) -> list[Interval]:
    """Check ordering (start < end, sorted, no overlap beyond ``tol`` s); if ``phones``,
    check every label with :func:`check_phone`. Errors name ``where`` (e.g. the file)."""
    loc = f" in {where}" if where else ""
    prev_end = -np.inf
    for i, (s, e, lab) in enumerate(intervals):
        if not (np.isfinite(s) and np.isfinite(e)):
            raise ValueError(f"interval {i} ({s}, {e}, {lab!r}){loc}: times must be finite")
        if not s < e:
            raise ValueError(f"interval {i} ({s}, {e}, {lab!r}){loc}: expected start < end")
        if s < prev_end - tol:
            raise ValueError(
                f"interval {i} ({s}, {e}, {lab!r}){loc}: starts at {s} before the previous "
                f"interval ends at {prev_end} (expected sorted, non-overlapping intervals)"
            )
        if phones:
            check_phone(lab, f"{where} (interval {i}, {s:.4f}-{e:.4f} s)" if where else "")
        prev_end = e
    return intervals


_SIL_ALIASES = {"", "sil", "sp", "spn", "pau", "h#", "#", "<p>", "silence", "_"}


def normalize_phone(label: str) -> str:
    """Map common aligner spellings to the package phone set, without validating.

    Lower-case; drop ARPAbet stress digits (``AH0`` -> ``ah``); map ``ax`` -> ``ah``
    (ARPAbet 39 folds it); map silence spellings (empty, ``sp``, ``spn``, ``pau``, ``h#``,
    ``SIL``) -> ``sil``. Used by the user-corpus loader; the file readers return raw labels.
    """
    lab = label.strip().lower()
    if lab in _SIL_ALIASES:
        return SILENCE
    lab = re.sub(r"[012]$", "", lab)
    return {"ax": "ah", "axr": "er", "ix": "ih"}.get(lab, lab)


# ---------------------------------------------------------------------------------------
# HTK .lab
# ---------------------------------------------------------------------------------------

def read_lab(path: str | Path) -> list[Interval]:
    """Read an HTK label file; times in seconds (``k / 1e7``). Labels are returned as is."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read HTK label file ({exc})") from exc
    out: list[Interval] = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        if line.strip() == "///":
            raise ValueError(f"{path}:{n}: multiple-alternative HTK label files are not supported")
        f = line.split()
        if len(f) < 3:
            raise ValueError(f"{path}:{n}: expected 'start end label' (100 ns units), found {line!r}")
        try:
            s, e = int(f[0]), int(f[1])
        except ValueError:
            raise ValueError(
                f"{path}:{n}: start/end must be integers in 100 ns units, found {f[0]!r} {f[1]!r}"
            ) from None
        out.append((s / _HTK_UNITS, e / _HTK_UNITS, f[2]))
    if not out:
        raise ValueError(f"{path}: no segments found in HTK label file")
    validate_intervals(out, str(path), phones=False)
    return out


def write_lab(path: str | Path, intervals: list[Interval]) -> None:
    """Write an HTK label file (``start end label``, 100 ns integer units), atomically."""
    path = Path(path)
    validate_intervals(intervals, str(path), phones=False)
    lines = []
    for s, e, lab in intervals:
        if not lab or any(c.isspace() for c in lab):
            raise ValueError(f"{path}: HTK labels must be non-empty without spaces, found {lab!r}")
        lines.append(f"{round(s * _HTK_UNITS)} {round(e * _HTK_UNITS)} {lab}\n")
    write_text(path, "".join(lines))


# ---------------------------------------------------------------------------------------
# Praat TextGrid
# ---------------------------------------------------------------------------------------

_TG_TOKEN = re.compile(
    r'"((?:[^"]|"")*)"'                               # 1: string ("" escapes a quote)
    r"|(<exists>|<absent>)"                           # 2: flag
    r"|([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)"   # 3: number
    r"|\[[^\]\n]*\]|[A-Za-z_][\w ]*?(?=\s*[=:\[])|[=:]|![^\n]*|\S"
)


def _tg_tokens(text: str) -> list:
    toks: list = []
    for m in _TG_TOKEN.finditer(text):
        if m.group(1) is not None:
            toks.append(("s", m.group(1).replace('""', '"')))
        elif m.group(2) is not None:
            toks.append(("f", m.group(2)))
        elif m.group(3) is not None:
            toks.append(("n", m.group(3)))
    return toks


def _decode(path: Path) -> str:
    raw = path.read_bytes()
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        return raw.decode("utf-16")
    if raw.startswith(b"\xef\xbb\xbf"):
        return raw[3:].decode("utf-8")
    return raw.decode("utf-8")


def read_textgrid_tiers(path: str | Path) -> dict[str, list]:
    """All tiers of a TextGrid (long or short text format): name -> intervals or points.

    IntervalTier -> list of ``(xmin, xmax, text)``; TextTier -> list of ``(time, mark)``.
    """
    path = Path(path)
    try:
        toks = _tg_tokens(_decode(path))
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read TextGrid ({exc})") from exc
    pos = 0

    def take(kind: str, what: str):
        nonlocal pos
        if pos >= len(toks):
            raise ValueError(f"{path}: truncated TextGrid, expected {what}")
        k, v = toks[pos]
        if k != kind:
            raise ValueError(f"{path}: malformed TextGrid, expected {what}, found {v!r}")
        pos += 1
        return v

    def count(what: str) -> int:
        v = take("n", what)
        try:
            n = int(v)
        except ValueError:
            raise ValueError(f"{path}: malformed TextGrid, {what} must be a whole number, found {v!r}") from None
        if n < 0:
            raise ValueError(f"{path}: malformed TextGrid, {what} must be >= 0, found {n}")
        return n

    if take("s", "'ooTextFile'") != "ooTextFile" or take("s", "'TextGrid'") != "TextGrid":
        raise ValueError(f"{path}: not a Praat TextGrid text file (expected File type "
                         "'ooTextFile', Object class 'TextGrid')")
    take("n", "xmin")
    take("n", "xmax")
    if take("f", "<exists>") != "<exists>":
        return {}
    n_tiers = count("tier count")
    tiers: dict[str, list] = {}
    for _ in range(n_tiers):
        cls = take("s", "tier class")
        name = take("s", "tier name")
        take("n", "tier xmin")
        take("n", "tier xmax")
        n = count("item count")
        items: list = []
        for _ in range(n):
            if cls == "IntervalTier":
                s = float(take("n", "interval xmin"))
                e = float(take("n", "interval xmax"))
                items.append((s, e, take("s", "interval text")))
            elif cls == "TextTier":
                items.append((float(take("n", "point time")), take("s", "point mark")))
            else:
                raise ValueError(f"{path}: unknown tier class {cls!r}")
        if name in tiers:
            raise ValueError(f"{path}: duplicate tier name {name!r}")
        tiers[name] = items if cls == "IntervalTier" else [("point",) + p for p in items]
    return tiers


_PHONE_TIER_NAMES = ("phones", "phone", "Phones", "phonemes")


def _interval_tiers(path: Path) -> dict[str, list]:
    tiers = {k: v for k, v in read_textgrid_tiers(path).items()
             if not (v and v[0][0] == "point")}
    if not tiers:
        raise ValueError(f"{path}: TextGrid has no IntervalTier")
    return tiers


def _all_phones(items: list) -> bool:
    from bayes_talk.data.phones import PHONES

    return bool(items) and all(normalize_phone(str(t)) in PHONES for _, _, t in items)


def choose_tier(path: str | Path, tiers: dict[str, list], tier: str | None = None,
                phones: bool = False) -> str:
    """The name of the tier to read: ``tier`` if given; else one named ``phones``/``phone``/
    ``Phones``/``phonemes``; else (``phones=True``) the first IntervalTier whose labels are
    all known phones; else the first IntervalTier."""
    if tier is not None:
        if tier not in tiers:
            raise ValueError(f"{path}: no IntervalTier named {tier!r}; found {sorted(tiers)}")
        return tier
    named = next((t for t in _PHONE_TIER_NAMES if t in tiers), None)
    if named is not None:
        return named
    if phones:
        ok = [t for t, items in tiers.items() if _all_phones(items)]
        if ok:
            return ok[0]
    return next(iter(tiers))


def read_textgrid(path: str | Path, tier: str | None = None) -> list[Interval]:
    """Intervals of one IntervalTier (see :func:`choose_tier`). Labels are returned as is
    (``""`` included); a tier without intervals is an error naming it."""
    path = Path(path)
    tiers = _interval_tiers(path)
    name = choose_tier(path, tiers, tier)
    return _tier_intervals(path, tiers, name)


def _tier_intervals(path: Path, tiers: dict[str, list], name: str) -> list[Interval]:
    if not tiers[name]:
        raise ValueError(f"{path}: tier {name!r} has no intervals (tiers: {sorted(tiers)})")
    out = [(float(s), float(e), str(t)) for s, e, t in tiers[name]]
    validate_intervals(out, f"{path} (tier {name!r})", phones=False, tol=1e-9)
    return out


def _fmt(x: float) -> str:
    r = repr(float(x))
    return r.removesuffix(".0")


def write_textgrid(path: str | Path, intervals: list[Interval], tier: str = "phones") -> None:
    """Write a one-tier TextGrid in Praat's long text format (UTF-8), atomically."""
    path = Path(path)
    validate_intervals(intervals, str(path), phones=False)
    xmin, xmax = intervals[0][0], intervals[-1][1]
    q = lambda s: '"' + s.replace('"', '""') + '"'
    lines = [
        'File type = "ooTextFile"', 'Object class = "TextGrid"', "",
        f"xmin = {_fmt(xmin)} ", f"xmax = {_fmt(xmax)} ", "tiers? <exists> ", "size = 1 ",
        "item []: ", "    item [1]:", '        class = "IntervalTier" ',
        f"        name = {q(tier)} ", f"        xmin = {_fmt(xmin)} ", f"        xmax = {_fmt(xmax)} ",
        f"        intervals: size = {len(intervals)} ",
    ]
    for i, (s, e, lab) in enumerate(intervals, 1):
        lines += [f"        intervals [{i}]:", f"            xmin = {_fmt(s)} ",
                  f"            xmax = {_fmt(e)} ", f"            text = {q(lab)} "]
    write_text(path, "\n".join(lines) + "\n")


def read_labels(path: str | Path, tier: str | None = None) -> list[Interval]:
    """Read ``.lab`` or ``.TextGrid`` by extension, normalise with :func:`normalize_phone`,
    and validate every phone (errors name the file, and for a TextGrid the tier read).

    ``tier``: the TextGrid tier holding the phones (default: see :func:`choose_tier`,
    which skips a leading ``words`` tier by picking the first tier of known phones).
    An empty label file or tier is an error.
    """
    path = Path(path)
    ext = path.suffix.lower()
    where = str(path)
    if ext == ".lab":
        if tier is not None:
            raise ValueError(f"{path}: --tier applies to TextGrid files; an HTK .lab file has one tier")
        raw = read_lab(path)
    elif ext == ".textgrid":
        tiers = _interval_tiers(path)
        name = choose_tier(path, tiers, tier, phones=True)
        raw = _tier_intervals(path, tiers, name)
        where = f"{path} (tier {name!r} of {sorted(tiers)}; choose another with --tier NAME)"
    else:
        raise ValueError(f"{path}: unknown label format {path.suffix!r}; expected .lab or .TextGrid")
    out = [(s, e, normalize_phone(lab)) for s, e, lab in raw]
    validate_intervals(out, where, phones=True, tol=1e-9)
    return out


# ---------------------------------------------------------------------------------------
# frame labels
# ---------------------------------------------------------------------------------------

def frame_labels(intervals: list[Interval], n_frames: int, fps: float = 25.0) -> list[str]:
    """Majority-vote phone label of each video frame (see module docstring).

    Frame k covers ``[k/fps, (k+1)/fps)``. Score of label L in frame k = total overlap (s)
    of L's intervals with the frame; uncovered time scores for ``sil``. Winner: largest
    score; ties within 1e-9 s -> the label whose first overlap starts earliest in the
    frame (uncovered time "starts" where its first gap starts).
    """
    if n_frames < 0:
        raise ValueError(f"n_frames: expected >= 0, found {n_frames}")
    if fps <= 0:
        raise ValueError(f"fps: expected > 0, found {fps}")
    if n_frames == 0:
        return []
    k = np.arange(n_frames, dtype=np.float64)
    f0, f1 = k / fps, (k + 1) / fps
    scores: dict[str, np.ndarray] = {}
    first: dict[str, np.ndarray] = {}
    covered = np.zeros(n_frames)
    # earliest uncovered instant per frame: track the gaps explicitly
    gap_start = np.full(n_frames, np.inf)
    cursor = f0.copy()  # end of coverage so far, per frame (intervals are sorted)
    for s, e, lab in intervals:
        lo, hi = np.maximum(f0, s), np.minimum(f1, e)
        ov = np.clip(hi - lo, 0.0, None)
        hit = ov > 0
        if not hit.any():
            continue
        sc = scores.setdefault(lab, np.zeros(n_frames))
        fs = first.setdefault(lab, np.full(n_frames, np.inf))
        sc += ov
        fs[hit] = np.minimum(fs[hit], lo[hit])
        covered += ov
        gap = hit & (lo > cursor + _TIE_TOL)
        gap_start[gap] = np.minimum(gap_start[gap], cursor[gap])
        cursor[hit] = np.maximum(cursor[hit], hi[hit])
    tail = cursor < f1 - _TIE_TOL
    gap_start[tail] = np.minimum(gap_start[tail], cursor[tail])
    uncovered = np.clip((f1 - f0) - covered, 0.0, None)
    if np.any(uncovered > _TIE_TOL):
        sc = scores.setdefault(SILENCE, np.zeros(n_frames))
        fs = first.setdefault(SILENCE, np.full(n_frames, np.inf))
        m = uncovered > _TIE_TOL
        sc[m] += uncovered[m]
        fs[m] = np.minimum(fs[m], gap_start[m])
    names = list(scores)
    S = np.stack([scores[n] for n in names])          # (L, T)
    F = np.stack([first[n] for n in names])           # (L, T)
    best = S.max(axis=0)
    cand = S >= best - _TIE_TOL
    F = np.where(cand, F, np.inf)
    win = np.argmin(F, axis=0)
    return [names[i] for i in win]
