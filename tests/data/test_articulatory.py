"""The articulatory (VocalTractLab) corpus generator: phone mapping, reproducibility, lips
closing on /p b m/ and rounding on /uw/, and one variation shared by audio and face."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from bayes_talk.data import articulatory as art
from bayes_talk.data.phones import BILABIALS, PHONES, SILENCE, VOWELS

_HAS_VTL = True
try:
    import vocaltractlab_cython  # noqa: F401
except ImportError:
    _HAS_VTL = False
needs_vtl = pytest.mark.skipif(
    not _HAS_VTL, reason="vocaltractlab-cython is not installed (pip install 'bayes_talk[articulatory]')")

#: Short sentences with bilabials and /uw/ (about 1 s of speech each: the build stays cheap).
SENTENCES = ["Bob saw the moon.", "Pam knew a blue boot.", "A big map."]
#: Rounded vowels besides /uw/ (the face model's rounded set, bayes_talk.data.face).
_ROUNDED = frozenset(("uh", "ow", "ao", "oy"))


def _files(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


# --- the mapping (no VocalTractLab needed) -------------------------------------------

def test_every_phone_maps_to_a_vtl_phone():
    for p in PHONES:
        if p != SILENCE:
            assert art.ARPABET_TO_SAMPA[p] in art.VTL_PHONES, p


def test_unmapped_phone_is_an_error_naming_it():
    with pytest.raises(ValueError, match=r"intervals\[1\]: phone 'xx' has no VocalTractLab mapping"):
        art.segment_sequence([(0.0, 0.1, "sil"), (0.1, 0.2, "xx"), (0.2, 0.3, "sil")])
    bad = dict(art.ARPABET_TO_SAMPA, w="w")   # VocalTractLab would drop "w" silently
    with pytest.raises(ValueError, match=r"not VocalTractLab phone names: \{'w': 'w'\}"):
        art._check_table(bad)
    without = {k: v for k, v in art.ARPABET_TO_SAMPA.items() if k != "zh"}
    with pytest.raises(ValueError, match=r"no VocalTractLab phone for \['zh'\]"):
        art._check_table(without)


def test_segment_sequence_keeps_every_token_and_pauses():
    iv = [(0.0, 0.2, "sil"), (0.2, 0.28, "b"), (0.28, 0.4, "uw"), (0.4, 0.6, "sil")]
    segs = art.segment_sequence(iv)
    assert [n for n, _ in segs] == ["", "b", "u:", ""]
    assert np.allclose([d for _, d in segs], [0.2, 0.08, 0.12, 0.2])
    text = art.segment_file_text(segs)
    assert text.splitlines()[1].startswith("name = b; duration_s = 0.0800000; start_of_syllable = 1")


def test_vary_tract_keeps_closures_and_ranges():
    rng = np.random.default_rng(0)
    n = 400
    tract = np.zeros((n, 19))
    tract[:, art._LD] = np.where(np.arange(n) < 200, -0.3, 1.0)
    tract[:, art._JA] = -3.0
    segs = [("b", 200 * 110 / 44100), ("a:", 200 * 110 / 44100)]
    ranges = np.tile([-1.0, 4.0], (19, 1))
    ranges[art._JA] = (-7.0, 0.0)
    big = {k: (v if k == "token_open_corr" else 3 * v) for k, v in art.VARIATION.items()}
    out = art.vary_tract(tract, segs, rng, big, ranges)
    assert np.array_equal(out[:200, art._LD], tract[:200, art._LD])      # contact untouched
    assert np.std(out[200:, art._LD]) > 0.01                           # opening varied
    assert out.min() >= -7.0 and out[:, art._JA].max() <= 0.0


def _synthetic_score(k: int, seg_s: float = 0.1, pause: bool = True):
    """A tract of ``k`` open tokens of ``seg_s`` (LD 0.8 cm, JA -3.3 deg, LP 0.1 cm),
    framed by pauses of 0.3 s."""
    segs = [("a:", seg_s)] * k
    if pause:
        segs = [("", 0.3), *segs, ("", 0.3)]
    n = round(sum(d for _, d in segs) * 44100 / 110)
    tract = np.zeros((n, 19))
    tract[:, art._LD], tract[:, art._JA], tract[:, art._LP] = 0.8, -3.3, 0.1
    return tract, segs


def test_pauses_keep_the_rest_posture():
    """No variation where the audio is silent: the pause states are the gestural score's
    (beyond the 20 ms blend into the neighbouring token), the speech states are varied."""
    tract, segs = _synthetic_score(5)
    out = art.vary_tract(tract, segs, np.random.default_rng(3))
    t = (np.arange(len(tract)) + 0.5) * 110 / 44100
    pause = (t < 0.3 - 0.09) | (t > 0.8 + 0.09)      # the blend's Gaussian reaches 4 sd
    assert np.allclose(out[pause], tract[pause], atol=1e-12, rtol=0)
    speech = (t > 0.32) & (t < 0.78)
    for c in (art._LD, art._JA, art._LP):
        assert np.std(out[speech, c]) > 0.01, c


def test_token_opening_factor_is_shared_by_lips_and_jaw():
    """Per token, the log-factors of lip distance and jaw angle correlate with
    ``token_open_corr`` (the shared opening factor); protrusion is independent."""
    tract, segs = _synthetic_score(400, seg_s=0.1, pause=False)
    sizes = dict(art.VARIATION, effort_sd=0.0, noise_ld_sd=0.0, noise_ja_sd=0.0, noise_lp_sd=0.0)
    out = art.vary_tract(tract, segs, np.random.default_rng(11), sizes)
    mid = ((np.arange(400) + 0.5) * 0.1 * 44100 / 110).astype(int)      # token centres
    a = np.log(out[mid, art._LD] / 0.8)
    j = np.log(out[mid, art._JA] / -3.3)
    p = out[mid, art._LP] - 0.1
    assert abs(np.std(a) - sizes["token_ld_sd"]) < 0.05 and abs(np.std(j) - sizes["token_ja_sd"]) < 0.05
    assert abs(np.corrcoef(a, j)[0, 1] - sizes["token_open_corr"]) < 0.1
    assert abs(np.corrcoef(a, p)[0, 1]) < 0.15
    indep = art.vary_tract(tract, segs, np.random.default_rng(11), dict(sizes, token_open_corr=0.0))
    assert abs(np.corrcoef(np.log(indep[mid, art._LD] / 0.8), np.log(indep[mid, art._JA] / -3.3))[0, 1]) < 0.15
    with pytest.raises(ValueError, match=r"token_open_corr.*found 1.5"):
        art.vary_tract(tract, segs, np.random.default_rng(0), dict(sizes, token_open_corr=1.5))


def test_missing_vtl_gives_install_hint(monkeypatch):
    import builtins

    real = builtins.__import__

    def fake(name, *a, **k):
        if name.startswith("vocaltractlab_cython"):
            raise ImportError("no module")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake)
    with pytest.raises(RuntimeError, match=r"pip install 'bayes_talk\[articulatory\]'"):
        art.require_vtl()


# --- with VocalTractLab ---------------------------------------------------------------

@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    d = tmp_path_factory.mktemp("vtl-cache")
    old = os.environ.get("BAYES_TALK_CACHE")
    os.environ["BAYES_TALK_CACHE"] = str(d)
    yield d
    if old is None:
        os.environ.pop("BAYES_TALK_CACHE", None)
    else:
        os.environ["BAYES_TALK_CACHE"] = old


@pytest.fixture(scope="module")
def corpus(tmp_path_factory, cache) -> Path:
    from bayes_talk.corpus import build_corpus

    return build_corpus(tmp_path_factory.mktemp("vtl") / "c", n_utterances=3, seed=0,
                        sentences=SENTENCES, speech="vtl", n_workers=1)


@needs_vtl
def test_rebuild_is_byte_identical_uncached_and_with_workers(corpus, tmp_path, monkeypatch):
    from bayes_talk.corpus import build_corpus

    # a fresh cache: everything is synthesised again, in 2 worker processes
    monkeypatch.setenv("BAYES_TALK_CACHE", str(tmp_path / "fresh-cache"))
    again = build_corpus(tmp_path / "again", n_utterances=3, seed=0, sentences=SENTENCES,
                         speech="vtl", n_workers=2, executor="processes")
    assert len(list((tmp_path / "fresh-cache" / "vtl").glob("*.npz"))) == 3
    a, b = _files(corpus), _files(again)
    differing = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    assert not differing, f"files differ between identical builds: {differing}"


@needs_vtl
def test_manifest_names_generator_and_licence(corpus):
    import json

    m = json.loads((corpus / "manifest.json").read_text())
    assert m["speech"] == "vtl"
    assert "GPL-3.0" in m["articulatory"]["licence"]
    assert m["articulatory"]["variation"] == art.VARIATION


def _intervals(corpus: Path, k: int):
    from bayes_talk.data.labels import read_lab

    return read_lab(corpus / "utterances" / f"utt{k:04d}.lab")


@needs_vtl
def test_lips_close_on_bilabials_and_round_on_uw(corpus):
    import soundfile as sf

    ld_bil, ld_vow, lp_uw, lp_other = [], [], [], []
    for k in range(len(SENTENCES)):
        iv = _intervals(corpus, k)
        y, sr = sf.read(corpus / "utterances" / f"utt{k:04d}.wav", dtype="int16")
        res = art.synthesize_articulatory(iv, len(y), sr, (0, k, 3))
        assert res.cached and np.array_equal(res.audio, y)     # the corpus audio is this tract's
        t = (np.arange(len(res.tract)) + 0.5) * 110 / 44100
        for s, e, p in iv:
            mid = (t > s + 0.3 * (e - s)) & (t < e - 0.3 * (e - s))
            ld, lp = res.tract[mid, art._LD], res.tract[mid, art._LP]
            if p in BILABIALS:
                # the closure may begin before the labelled plosive (espeak labels only the
                # release of an utterance-initial /p/): the lips meet within 30 ms before
                ld_bil.append(res.tract[(t > s - 0.03) & (t < e), art._LD].min())
            elif p == "uw":
                lp_uw.append(lp.mean())
            elif p in VOWELS:
                ld_vow.append(ld.mean())
                if p not in _ROUNDED:   # /ow ao uh oy/ round too (per-token offsets sd 0.2 cm)
                    lp_other.append(lp.mean())
    assert len(ld_bil) >= 4 and len(lp_uw) >= 2
    assert max(ld_bil) <= 0.0, ld_bil            # lips meet (LD <= 0 is contact) in every closure
    # and are apart in vowels: >= 1 mm (a closure is <= 0.4 mm; a hypo-articulated token at
    # the version-2 sizes may have a third of the score's 0.5-0.9 cm)
    assert min(ld_vow) > 0.1, ld_vow
    assert min(lp_uw) > max(lp_other) + 0.2, (lp_uw, lp_other)


@needs_vtl
def test_face_lips_follow_the_tract(corpus):
    from bayes_talk.corpus import load_npz
    from bayes_talk.data.face import inner_lip_aperture

    closed, open_ = [], []
    for k in range(len(SENTENCES)):
        iv = _intervals(corpus, k)
        lm = load_npz(corpus / "utterances" / f"utt{k:04d}.landmarks.npz", ("landmarks",))["landmarks"]
        ap = inner_lip_aperture(lm)
        tc = (np.arange(len(ap)) + 0.5) / 25.0
        for s, e, p in iv:
            idx = np.flatnonzero((tc >= s) & (tc < e))
            if p in BILABIALS:
                near = np.flatnonzero((tc >= s - 0.03) & (tc < e + 0.02))
                closed.append(ap[near].min())
            elif p in VOWELS and p not in ("uw", "uh", "ow", "w") and len(idx):
                open_.append(ap[idx].max())
    assert closed and open_
    assert max(closed) < 0.5, closed                  # pixels: the lips touch on /p b m/
    assert np.median(open_) > 2.0, open_


@needs_vtl
def test_audio_and_face_share_the_variation(cache):
    """Only the per-token lip-distance factor changes between two syntheses: the audio and
    the face's lip aperture both change, in the perturbed vowel."""
    sr, fps = 22050, 25.0
    iv = [(0.0, 0.2, "sil"), (0.2, 0.28, "b"), (0.28, 0.52, "aa"), (0.52, 0.6, "m"),
          (0.6, 0.84, "aa"), (0.84, 1.2, "sil")]
    n = int(1.2 * sr)
    base = {k: 0.0 for k in art.VARIATION}
    moved = dict(base, token_ld_sd=0.3)
    a = art.synthesize_articulatory(iv, n, sr, (5, 0, 3), sizes=base, use_cache=False)
    b = art.synthesize_articulatory(iv, n, sr, (5, 0, 3), sizes=moved, use_cache=False)
    fa, fb = art.face_articulators(a.tract, 30, fps), art.face_articulators(b.tract, 30, fps)
    # jaw and protrusion unchanged, lip aperture changed in the vowels
    assert np.array_equal(fa["jaw"], fb["jaw"]) and np.array_equal(fa["protrusion"], fb["protrusion"])
    vowel = slice(int(0.32 * fps), int(0.48 * fps))
    assert np.abs(fa["aperture"][vowel] - fb["aperture"][vowel]).max() > 0.3
    seg = slice(int(0.3 * sr), int(0.5 * sr))
    diff = np.abs(a.audio[seg].astype(float) - b.audio[seg].astype(float)).mean()
    assert diff > 0.05 * np.abs(a.audio[seg].astype(float)).mean()
    # silence stays silent in both (nothing but the lips moved)
    assert np.array_equal(a.audio[: int(0.1 * sr)], b.audio[: int(0.1 * sr)])


@needs_vtl
def test_default_sizes_stay_in_vtl_ranges_and_keep_closures(corpus):
    """At the documented sizes on real gestural scores: before clipping, at most a few
    per cent of the states leave VocalTractLab's ranges (the clip binds only in the tails:
    JA at the model's widest jaw, -7 degrees), and every lip contact stays a contact."""
    ranges = art.param_ranges()
    outside, contact_kept, n_states = 0, [], 0
    for k in range(len(SENTENCES)):
        segs = art.segment_sequence(_intervals(corpus, k))
        base, _ = art._score_tract(art.segment_file_text(segs))
        for d in range(10):
            raw = art.vary_tract(base, segs, np.random.default_rng([k, d]), None, None)
            outside += int(np.sum((raw < ranges[:, 0]) | (raw > ranges[:, 1])))
            n_states += raw.shape[0]
            closed = base[:, art._LD] <= 0
            contact_kept.append(np.array_equal(raw[closed, art._LD], base[closed, art._LD]))
            clipped = art.vary_tract(base, segs, np.random.default_rng([k, d]), None, ranges)
            assert np.all(clipped >= ranges[:, 0]) and np.all(clipped <= ranges[:, 1])
    assert all(contact_kept)
    assert outside / n_states < 0.08, outside / n_states


@needs_vtl
def test_oracle_draws_use_the_corpus_generator(corpus):
    """A draw with the corpus's own stream reproduces the corpus's face articulators; fresh
    streams vary the lip opening but keep the closures closed."""
    import soundfile as sf

    iv = _intervals(corpus, 1)
    y, sr = sf.read(corpus / "utterances" / "utt0001.wav", dtype="int16")
    T = len(y) * 25 // sr
    res = art.synthesize_articulatory(iv, len(y), sr, (0, 1, 3))
    want = art.face_articulators(res.tract, T, 25.0)
    same, *fresh = art.articulatory_draws(iv, T, 25.0, [np.random.default_rng([0, 1, 3]),
                                                       np.random.default_rng([7, 1]), np.random.default_rng([7, 2])])
    for k in want:
        assert np.array_equal(same[k], want[k]), k
    assert np.abs(fresh[0]["aperture"] - fresh[1]["aperture"]).max() > 0.5
    tc = (np.arange(T) + 0.5) / 25.0
    for s, e, p in iv:
        if p in BILABIALS:
            near = (tc >= s - 0.03) & (tc < e + 0.02)
            for d in fresh:
                assert d["aperture"][near].min() < 1.0, (p, s)   # design units; open vowels ~6-8


@needs_vtl
def test_loaded_vtl_corpus_names_its_generator(corpus):
    from bayes_talk.corpus import load_corpus
    from bayes_talk.evaluation.ceiling import corpus_generator

    c = load_corpus(corpus, n_workers=1)
    assert c.sequences[0].meta["speech"] == "vtl"
    assert corpus_generator(c.manifest) == "vtl"
    assert corpus_generator({"kind": "built"}) == "espeak"
    assert corpus_generator({"kind": "user"}) == "user"
    # the oracle follows the corpus's generator: its mean is closer to the truth than the
    # same oracle run with the phone-driven (espeak) face
    from bayes_talk.estimators.ceiling import OracleModel

    err = {"vtl": 0.0, "espeak": 0.0}
    for u in c.sequences:
        for gen in err:
            u.meta["speech"] = gen
            mean, var, _bias = OracleModel(n_draws=3).moments(u)
            assert mean.shape == u.aam.shape and np.all(var > 0)
            err[gen] += float(np.mean((mean - u.aam) ** 2))
    assert err["vtl"] < 0.8 * err["espeak"], err
