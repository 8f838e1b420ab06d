"""Articulatory speech with VocalTractLab: one vocal tract drives the voice and the face.

The ``--speech vtl`` generator of the built-in corpus (docs/data.md). espeak-ng
still gives the phone string and its durations; then, per utterance::

    ARPAbet intervals --ARPABET_TO_SAMPA--> VTL segment sequence (German SAMPA, pauses "")
      --phoneme_file_to_gesture_file--> gestural score
      --gesture_file_to_motor_file--> tract (N, 19) and glottis (N, 11) at 44100/110 Hz
      --articulatory variation (one random stream)--> tract'
      --synth_block--> 44.1 kHz audio --soxr--> corpus rate          (the voice)
      tract' LD, LP, JA sampled at the frame centres --> face jaw, aperture,
      spread, protrusion                                             (the face)

VocalTractLab (Birkholz; ``vocaltractlab-cython``, GPL-3.0) is an optional dependency:
``pip install 'bayes_talk[articulatory]'``. It ignores an unknown phone name silently, so
every name we send is checked against its phone list (:data:`VTL_PHONES`, the table of
``Sampa.cpp``) and an ARPAbet phone without a mapping is an error naming it.

Articulatory variation (all from ``rng``, drawn in this order; sizes in
:data:`VARIATION`). Let ``LD`` (lip distance, cm; <= 0 is lip contact / compression),
``JA`` (jaw angle, degrees, <= 0, more negative = more open) and ``LP`` (lip protrusion,
cm) be the tracks of the gestural score, and ``w_k(t)`` the indicator of token ``k``'s
interval low-passed by a Gaussian of sd :data:`_TOKEN_SMOOTH_S` (so ``sum_k w_k = 1``);
``s(t) = sum_{k speech} w_k(t)`` is 1 in speech and 0 in pauses:

* per utterance, effort ``log e = sd_e * z`` (hyper-/hypo-articulation): the excursion of
  lip opening and jaw;
* per token ``k``, standard normals ``(o_k, u_k, v_k, q_k)`` truncated at 2.5 sd: an
  *opening* factor ``o_k`` shared by lips and jaw (a token spoken with a wider mouth opens
  both, as jaw and lip aperture co-vary in real speech), giving the log-factors
  ``a_k = sd_ld (sqrt(rho) o_k + sqrt(1 - rho) u_k)`` (lip opening) and
  ``j_k = sd_ja (sqrt(rho) o_k + sqrt(1 - rho) v_k)`` (jaw), correlation ``rho``
  (``token_open_corr``, in [0, 1]), and an offset ``p_k = sd_lp q_k`` (protrusion, cm); pause tokens
  get none (``a_k = j_k = p_k = 0``);
* smooth noise ``n_a(t), n_j(t), n_p(t)`` (Gaussian low-pass, sd ``_NOISE_SIGMA_S``);

    LD'(t) = LD(t) * exp(s (log e + n_a) + sum_k w_k a_k)     where LD > 0, else LD
    JA'(t) = JA(t) * exp(s (log e + n_j) + sum_k w_k j_k)
    LP'(t) = LP(t) + s n_p + sum_k w_k p_k

clipped to VocalTractLab's parameter ranges. Multiplying only the *positive* lip
distance keeps lip contact exactly where the gestural score has it (a /p b m/ closure
stays closed; its compression is untouched) and the track continuous at contact. Pauses
keep the gestural score's rest posture: variation there would move the face where the
audio is silent, i.e. face-only variation no listener (and no audio model) can recover.
The per-utterance speaking rate is espeak's rate jitter (:func:`bayes_talk.data.speech.
jittered_requests`), which sets the durations both signals share.

Sizes (generator version 2; version 1 had effort 0.12, per-token 0.25/0.25/0.15 cm,
independent factors, and varied the pauses too). In VocalTractLab's gestural scores the
jaw barely moves between phones (JA -2..-5 degrees, about -3.3 in most sounds) and LD is
0.5-0.9 cm in open sounds, so the per-token variation is what the face's jaw and lip
opening carry beyond the phone identity. The sizes below, effort 0.2 and per-token 0.4
(log) with rho = 0.7, protrusion 0.2 cm, give 1 sd of about +-1.3 degrees of jaw and
+-0.3 cm of lip opening around those values, within VocalTractLab's ranges (JA -7..0,
LD -2..4, LP -1..1): on 40 corpus utterances the clip binds in 4.5 % of the states (JA at
-7, the model's widest jaw) and 1.8 % (LP at 1 cm). Measured effect: the MFCCs' R² gain
over the phone labels on the first three AAM parameters is 0.066 larger than on the
espeak corpus (version 1: 0.017; ``benchmarks/audio_information.py``, docs/benchmarks.md).

Face mapping (design units of :mod:`bayes_talk.data.face`; constants in
:data:`FACE_MAP`): ``aperture = k_a * max(LD', 0)``, ``jaw = k_j * (-JA')``,
``protrusion = k_p * (LP' - LP_rest)``, ``spread = -k_s * (LP' - LP_mid)`` (rounding is
protrusion in this tract model: lip width is not a VocalTractLab parameter), each sampled
at the frame centres ``(k + 1/2)/fps`` with no visual lead (the articulation *is* the
sound). Brows, blinks, pose, upper-lip raise and lower-lip tuck stay face-only.

Determinism: VocalTractLab is byte-identical across runs and processes
(tests/data/test_articulatory.py rebuilds a corpus and compares the bytes); the
result of an utterance is cached under :func:`cache_dir` by a hash of everything it
depends on (segment text, random-stream key, :data:`GENERATOR_VERSION`, VTL version).
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d

from bayes_talk.base import settings
from bayes_talk.data.phones import PHONES, SILENCE

__all__ = [
    "ARPABET_TO_SAMPA",
    "FACE_MAP",
    "GENERATOR_VERSION",
    "LICENCE",
    "VARIATION",
    "VTL_PHONES",
    "ArticulatoryResult",
    "articulatory_draws",
    "cache_dir",
    "face_articulators",
    "param_ranges",
    "require_vtl",
    "segment_file_text",
    "segment_sequence",
    "synthesize_articulatory",
    "vary_tract",
]

#: Bump when anything that changes the output of :func:`synthesize_articulatory` changes.
GENERATOR_VERSION = 3
LICENCE = "VocalTractLab (vocaltractlab-cython): GPL-3.0"
_INSTALL_HINT = ("--speech vtl needs VocalTractLab: pip install 'bayes_talk[articulatory]' "
                 "(the vocaltractlab-cython package, GPL-3.0)")

#: VocalTractLab's phone names (German SAMPA), the table ``Sampa::PHONEME`` of its
#: ``Sampa.cpp``; any other name in a segment file is silently ignored by the library.
VTL_PHONES: frozenset[str] = frozenset((
    "a:", "e:", "i:", "o:", "u:", "E:", "2:", "y:",
    "a", "e", "i", "o", "u", "E", "2", "y",
    "I", "O", "U", "9", "Y", "@", "6",
    "aI", "aU", "OY",
    "i:6", "i6", "I6", "y:6", "y6", "Y6", "e:6", "e6", "E6", "E:6",
    "2:6", "26", "96", "a:6", "a6", "u:6", "u6", "U6", "o:6", "o6", "O6",
    "?", "p", "b", "t", "d", "k", "g",
    "f", "v", "T", "D", "s", "z", "S", "Z", "C", "j", "x", "r", "R", "h",
    "pf", "ts", "tS", "dZ",
    "m", "n", "N", "l",
))

#: ARPAbet -> VocalTractLab SAMPA (VocalTractLab's German phone set). English /w/ has no
#: German counterpart: it is the rounded /u:/ gesture (short); /r/ and /er/ are the
#: vocalised German r ``6``. ``sil`` is a pause (empty name).
ARPABET_TO_SAMPA: dict[str, str] = {
    "aa": "a:", "ae": "E", "ah": "@", "ao": "O", "aw": "aU", "ay": "aI", "eh": "E",
    "er": "6", "ey": "e:", "ih": "I", "iy": "i:", "ow": "o:", "oy": "OY", "uh": "U",
    "uw": "u:", "b": "b", "ch": "tS", "d": "d", "dh": "D", "f": "f", "g": "g", "hh": "h",
    "jh": "dZ", "k": "k", "l": "l", "m": "m", "n": "n", "ng": "N", "p": "p", "r": "6",
    "s": "s", "sh": "S", "t": "t", "th": "T", "v": "v", "w": "u:", "y": "j", "z": "z",
    "zh": "Z",
}


def _check_table(table: dict[str, str]) -> None:
    """Every non-silence phone of :data:`PHONES` maps to a name in :data:`VTL_PHONES`."""
    missing = [p for p in PHONES if p != SILENCE and p not in table]
    if missing:
        raise ValueError(f"ARPABET_TO_SAMPA: no VocalTractLab phone for {missing}")
    bad = {a: s for a, s in table.items() if s not in VTL_PHONES}
    if bad:
        raise ValueError(f"ARPABET_TO_SAMPA: not VocalTractLab phone names: {bad}")


_check_table(ARPABET_TO_SAMPA)

#: Sizes of the articulatory variation (see the module docstring). Log-factors are
#: dimensionless (0.25 = about +-25 % of the excursion), offsets in cm, times in s.
VARIATION: dict[str, float] = {
    "effort_sd": 0.2,         # per utterance, log-factor on lip opening and jaw
    "token_ld_sd": 0.4,       # per token, log-factor on positive lip distance
    "token_ja_sd": 0.4,       # per token, log-factor on jaw angle
    "token_open_corr": 0.7,   # per token, correlation of the lip and jaw log-factors
    "token_lp_sd": 0.2,       # per token, protrusion offset, cm
    "noise_ld_sd": 0.08,      # smooth noise, log-factor
    "noise_ja_sd": 0.08,
    "noise_lp_sd": 0.04,      # cm
}
_TRUNCATE = 2.5
_TOKEN_SMOOTH_S = 0.02
_NOISE_SIGMA_S = 0.08

#: VocalTractLab tract-parameter columns (order of ``get_param_info("tract")``).
_TRACT_NAMES = ("HX", "HY", "JX", "JA", "LP", "LD", "VS", "VO", "TCX", "TCY", "TTX", "TTY",
                "TBX", "TBY", "TRX", "TRY", "TS1", "TS2", "TS3")
_JA, _LP, _LD = _TRACT_NAMES.index("JA"), _TRACT_NAMES.index("LP"), _TRACT_NAMES.index("LD")
_VTL_RATE = 44100
_STATE_SAMPLES = 110
#: The voice is synthesised from every second tract/glottis state (``synth_block`` with
#: 2 x 110 samples per state, i.e. 200 Hz; VocalTractLab interpolates the tube linearly
#: between states). Its per-state tube geometry is most of ``synth_block``'s cost: the stride
#: takes 5.7 -> 3.2-3.6 CPU-s for 2.6 s of audio, and the waveform correlates 0.9986 with the
#: 400 Hz one (docs/data.md). The face still reads every state.
_AUDIO_STATE_STRIDE = 2
#: Fixed gain from VocalTractLab's output (about +-1) to int16 (no per-utterance
#: normalisation: loudness follows the articulation).
_AUDIO_GAIN = 2.0e5

#: VocalTractLab tract -> face articulators (design units; see the module docstring).
FACE_MAP: dict[str, float] = {
    "k_aperture": 8.0,     # units per cm of lip distance (/aa/ ~0.9 cm -> 7 units; the
                           # face's 12-unit cap is LD 1.5 cm, above all but the 2-sd tails)
    "k_jaw": 1.3,          # units per degree of jaw opening (/ao/ ~5 deg -> 6.5 units)
    "k_protrusion": 1.1,   # units per cm of protrusion beyond LP_rest (/uw/ 0.85 cm -> 0.9)
    "lp_rest": 0.05,       # cm, LP of unrounded sounds
    "k_spread": 1.4,       # spread units per cm of protrusion above LP_mid (/uw/ -> -1)
    "lp_mid": 0.15,        # cm
}


def require_vtl():
    """The ``vocaltractlab_cython`` module, or RuntimeError saying how to install it."""
    try:
        import vocaltractlab_cython as vtl
    except ImportError as exc:
        raise RuntimeError(_INSTALL_HINT) from exc
    return vtl


def segment_sequence(intervals: list[tuple[float, float, str]],
                     where: str = "intervals") -> list[tuple[str, float]]:
    """``(VTL name, duration_s)`` per interval: ``sil`` -> ``""`` (a pause), else
    :data:`ARPABET_TO_SAMPA`; ValueError naming an unmapped phone (never dropped)."""
    out = []
    for k, (s, e, p) in enumerate(intervals):
        if p == SILENCE:
            name = ""
        elif p in ARPABET_TO_SAMPA:
            name = ARPABET_TO_SAMPA[p]
        else:
            raise ValueError(f"{where}[{k}]: phone {p!r} has no VocalTractLab mapping "
                             f"(ARPABET_TO_SAMPA maps {sorted(ARPABET_TO_SAMPA)})")
        if name and name not in VTL_PHONES:
            raise ValueError(f"{where}[{k}]: {name!r} (from {p!r}) is not a VocalTractLab phone")
        if not e > s:
            raise ValueError(f"{where}[{k}]: expected start < end, found ({s}, {e})")
        out.append((name, float(e) - float(s)))
    return out


def segment_file_text(segments: list[tuple[str, float]]) -> str:
    """VocalTractLab segment-sequence file: one line per segment; the first segment after
    a pause starts a syllable and a word (and carries the accent)."""
    lines = []
    after_pause = True
    for name, dur in segments:
        line = f"name = {name}; duration_s = {dur:.7f};"
        if name and after_pause:
            line += " start_of_syllable = 1; start_of_word = 1; word_accent = 1; phrase_accent = 0;"
        lines.append(line)
        after_pause = not name
    return "\n".join(lines) + "\n"


def _read_motor_file(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(tract (N, 19), glottis (N, 11)) from a VocalTractLab motor (tract sequence) file:
    comment lines, the glottis model's name, the number of states, then per state a line of
    glottis and a line of tract parameters."""
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    n = int(lines[1])
    rows = lines[2:2 + 2 * n]
    if len(rows) != 2 * n:
        raise RuntimeError(f"{path}: expected {2 * n} state lines, found {len(rows)}")
    glottis = np.array([[float(v) for v in r.split()] for r in rows[0::2]], dtype=np.float64)
    tract = np.array([[float(v) for v in r.split()] for r in rows[1::2]], dtype=np.float64)
    if tract.shape[1] != len(_TRACT_NAMES):
        raise RuntimeError(f"{path}: expected {len(_TRACT_NAMES)} tract parameters, found {tract.shape[1]}")
    return tract, glottis


def _token_weights(segments: list[tuple[str, float]], t: np.ndarray) -> np.ndarray:
    """(len(t), K) indicators of the K tokens' intervals low-passed by a Gaussian of sd
    :data:`_TOKEN_SMOOTH_S`; rows sum to 1."""
    edges = np.concatenate([[0.0], np.cumsum([d for _, d in segments])])
    idx = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, len(segments) - 1)
    ind = np.zeros((len(t), len(segments)))
    ind[np.arange(len(t)), idx] = 1.0
    dt = float(t[1] - t[0]) if len(t) > 1 else 1.0
    w = gaussian_filter1d(ind, _TOKEN_SMOOTH_S / dt, axis=0, mode="nearest")
    return w / w.sum(axis=1, keepdims=True)


def _smooth(rng: np.random.Generator, n: int, sd: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian-low-passed white noise (n, len(sd)) with stationary sd ``sd`` (variance of
    unit white noise through a normalised Gaussian of sd s samples: 1/(2 sqrt(pi) s))."""
    pad = int(np.ceil(4 * sigma))
    w = gaussian_filter1d(rng.standard_normal((n + 2 * pad, len(sd))), sigma, axis=0, mode="nearest")
    return w[pad:pad + n] * np.sqrt(2.0 * np.sqrt(np.pi) * sigma) * sd


def vary_tract(tract: np.ndarray, segments: list[tuple[str, float]], rng: np.random.Generator,
               sizes: dict[str, float] | None = None, ranges: np.ndarray | None = None) -> np.ndarray:
    """The tract (N, 19) with the articulatory variation of the module docstring applied to
    LD, JA and LP (a copy); draws from ``rng`` in the documented order. ``ranges`` (19, 2):
    the parameters' [min, max] (VocalTractLab's ``get_param_info``)."""
    v = dict(VARIATION if sizes is None else sizes)
    rho = float(v.get("token_open_corr", 0.0))
    if not 0.0 <= rho <= 1.0:
        raise ValueError(f"sizes['token_open_corr']: expected a correlation in [0, 1], found {rho}")
    n, k = tract.shape[0], len(segments)
    t = (np.arange(n) + 0.5) * _STATE_SAMPLES / _VTL_RATE
    log_effort = v["effort_sd"] * float(np.clip(rng.standard_normal(), -_TRUNCATE, _TRUNCATE))
    z = np.clip(rng.standard_normal((k, 4)), -_TRUNCATE, _TRUNCATE)   # open, lip, jaw, protrusion
    c, r = np.sqrt(rho), np.sqrt(1.0 - rho)        # corr(a_k, j_k) = c^2 = rho
    tok = np.stack([v["token_ld_sd"] * (c * z[:, 0] + r * z[:, 1]),
                    v["token_ja_sd"] * (c * z[:, 0] + r * z[:, 2]),
                    v["token_lp_sd"] * z[:, 3]], axis=1)
    speech = np.array([bool(name) for name, _ in segments])
    tok[~speech] = 0.0
    noise = _smooth(rng, n, np.array([v["noise_ld_sd"], v["noise_ja_sd"], v["noise_lp_sd"]]),
                    _NOISE_SIGMA_S * _VTL_RATE / _STATE_SAMPLES)
    w = _token_weights(segments, t)
    s_t = w[:, speech].sum(axis=1, keepdims=True)                # 1 in speech, 0 in pauses
    per_t = w @ tok + s_t * (noise + np.array([log_effort, log_effort, 0.0]))   # (n, 3)
    out = np.array(tract, dtype=np.float64, copy=True)
    ld = out[:, _LD]
    out[:, _LD] = np.where(ld > 0, ld * np.exp(per_t[:, 0]), ld)
    out[:, _JA] = out[:, _JA] * np.exp(per_t[:, 1])
    out[:, _LP] = out[:, _LP] + per_t[:, 2]
    if ranges is not None:
        out = np.clip(out, ranges[:, 0], ranges[:, 1])
    return out


def face_articulators(tract: np.ndarray, n_frames: int, fps: float) -> dict[str, np.ndarray]:
    """Face articulators (design units) ``jaw``, ``aperture``, ``protrusion``, ``spread``
    from the tract's JA, LD, LP sampled at the frame centres (:data:`FACE_MAP`)."""
    t_state = (np.arange(tract.shape[0]) + 0.5) * _STATE_SAMPLES / _VTL_RATE
    tf = (np.arange(n_frames) + 0.5) / fps
    ld, ja, lp = (np.interp(tf, t_state, tract[:, c]) for c in (_LD, _JA, _LP))
    m = FACE_MAP
    return {"jaw": m["k_jaw"] * (-ja),
            "aperture": m["k_aperture"] * np.maximum(ld, 0.0),
            "protrusion": m["k_protrusion"] * (lp - m["lp_rest"]),
            "spread": -m["k_spread"] * (lp - m["lp_mid"])}


def _score_tract(seg_text: str) -> tuple[np.ndarray, np.ndarray]:
    """(tract (N, 19), glottis (N, 11)) of a segment file: gestural score, then motor file."""
    vtl = require_vtl()
    with tempfile.TemporaryDirectory(prefix="bt-vtl-") as tmp:
        seg_f, ges_f, mot_f = (str(Path(tmp) / n) for n in ("u.seg", "u.ges", "u.tract"))
        Path(seg_f).write_text(seg_text)
        vtl.phoneme_file_to_gesture_file(seg_f, ges_f)
        vtl.gesture_file_to_motor_file(ges_f, mot_f)
        return _read_motor_file(Path(mot_f))


def param_ranges() -> np.ndarray:
    """(19, 2) [min, max] of VocalTractLab's tract parameters."""
    info = require_vtl().get_param_info("tract")
    return np.array([[p["min"], p["max"]] for p in info], dtype=np.float64)


def articulatory_draws(intervals: list[tuple[float, float, str]], n_frames: int, fps: float,
                       rngs: list[np.random.Generator], sizes: dict[str, float] | None = None,
                       where: str = "intervals") -> list[dict[str, np.ndarray]]:
    """Face articulators (:func:`face_articulators`) of fresh draws of the articulatory
    variation, one per generator in ``rngs``, for the given phones and durations: the
    gestural score is computed once and no audio is synthesised (method ``oracle``)."""
    segs = segment_sequence(intervals, where)
    base, _ = _score_tract(segment_file_text(segs))
    ranges = param_ranges()
    return [face_articulators(vary_tract(base, segs, r, sizes, ranges), n_frames, fps) for r in rngs]


@dataclass
class ArticulatoryResult:
    """audio: (n_samples,) int16 at ``sample_rate``; tract: (N, 19) varied tract at
    44100/110 Hz; cached: whether it came from the cache."""

    audio: np.ndarray
    sample_rate: int
    tract: np.ndarray
    cached: bool = False


def cache_dir() -> Path:
    """``$BAYES_TALK_CACHE/vtl``, else ``$XDG_CACHE_HOME/bayes_talk/vtl``, else
    ``~/.cache/bayes_talk/vtl``."""
    root = settings.get("cache")
    if root:
        return Path(root) / "vtl"
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "bayes_talk" / "vtl"


def _cache_key(seg_text: str, stream: tuple[int, ...], sizes: dict[str, float], n_samples: int,
               sample_rate: int, vtl_version: str) -> str:
    blob = json.dumps({"v": GENERATOR_VERSION, "seg": seg_text, "stream": list(stream),
                       "sizes": sizes, "n": n_samples, "sr": sample_rate, "vtl": vtl_version,
                       "gain": _AUDIO_GAIN}, sort_keys=True)
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def synthesize_articulatory(intervals: list[tuple[float, float, str]], n_samples: int,
                            sample_rate: int, stream: tuple[int, ...], *,
                            sizes: dict[str, float] | None = None, use_cache: bool = True,
                            where: str = "intervals") -> ArticulatoryResult:
    """Audio (``n_samples`` int16 at ``sample_rate``) and the varied tract of one utterance.

    ``intervals`` cover ``[0, n_samples / sample_rate]``; the variation is drawn from
    ``np.random.default_rng(stream)`` (:func:`vary_tract`). Cached (see :func:`cache_dir`).
    """
    import librosa

    from bayes_talk.base.files import write_npz

    vtl = require_vtl()
    sizes = dict(VARIATION if sizes is None else sizes)
    segs = segment_sequence(intervals, where)
    seg_text = segment_file_text(segs)
    key = _cache_key(seg_text, tuple(int(s) for s in stream), sizes, int(n_samples),
                     int(sample_rate), str(vtl.get_version()))
    path = cache_dir() / f"{key}.npz"
    if use_cache and path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                return ArticulatoryResult(z["audio"].copy(), int(sample_rate), z["tract"].copy(), True)
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache entry is recomputed and rewritten
    tract, glottis = _score_tract(seg_text)
    tract = vary_tract(tract, segs, np.random.default_rng(list(stream)), sizes, param_ranges())
    k = _AUDIO_STATE_STRIDE
    wave = np.asarray(vtl.synth_block(np.ascontiguousarray(tract[::k]), np.ascontiguousarray(glottis[::k]),
                                      _STATE_SAMPLES * k), dtype=np.float64)
    if int(sample_rate) != _VTL_RATE:
        wave = librosa.resample(wave, orig_sr=_VTL_RATE, target_sr=int(sample_rate), res_type="soxr_hq")
    out = np.zeros(int(n_samples))
    m = min(len(wave), int(n_samples))
    out[:m] = wave[:m]
    audio = np.clip(np.round(out * _AUDIO_GAIN), -32768, 32767).astype(np.int16)
    if use_cache:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_npz(path, {"audio": audio, "tract": tract})
        except OSError:
            pass  # a read-only cache only costs time
    return ArticulatoryResult(audio, int(sample_rate), tract, False)
