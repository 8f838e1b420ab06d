"""Figure: a ``--speech vtl`` utterance's lip distance, jaw angle and lip protrusion against
its phone labels, and its frames at a bilabial closure, an /uw/ and an open vowel
(issue 25; docs/data.md).

    PYTHONPATH=. .venv/bin/python benchmarks/analysis/articulatory_tracks.py CORPUS_DIR
        [--utterance 0] [--out docs/figures/articulatory_tracks.png]

CORPUS_DIR is a corpus built with ``--speech vtl``; the tract is re-synthesised (from the
synthesis cache when the build's is present) and checked against the corpus's audio.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import soundfile as sf

    from bayes_talk.data import articulatory as art
    from bayes_talk.corpus import load_npz
    from bayes_talk.data.labels import read_lab
    from bayes_talk.data.phones import BILABIALS, SILENCE
    from bayes_talk.base.files import write_figure

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("corpus")
    ap.add_argument("--utterance", type=int, default=0)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[2] / "docs" / "figures"
                                         / "articulatory_tracks.png"))
    a = ap.parse_args()
    root = Path(a.corpus)
    man = json.loads((root / "manifest.json").read_text())
    if man.get("speech") != "vtl":
        raise SystemExit(f"{root}: not a --speech vtl corpus (speech: {man.get('speech', 'espeak')})")
    seq = man["sequences"][a.utterance]
    iv = read_lab(root / seq["lab"])
    y, sr = sf.read(root / seq["wav"], dtype="int16")
    res = art.synthesize_articulatory(iv, len(y), sr, (int(man["seed"]), a.utterance, 3))
    if not np.array_equal(res.audio, y):
        raise SystemExit(f"{root / seq['wav']}: re-synthesised audio differs from the corpus")
    frames = load_npz(root / seq["frames"], ("frames",))["frames"]
    t = (np.arange(len(res.tract)) + 0.5) * 110 / 44100

    fig = plt.figure(figsize=(10, 6.5))
    gs = fig.add_gridspec(4, 3, height_ratios=[1, 1, 1, 1.6])
    tracks = [("LD lip distance (cm)", art._LD), ("JA jaw angle (deg)", art._JA),
              ("LP lip protrusion (cm)", art._LP)]
    axes = [fig.add_subplot(gs[r, :]) for r in range(3)]
    for ax, (name, col) in zip(axes, tracks, strict=True):
        ax.plot(t, res.tract[:, col], lw=1.2)
        for s, e, p in iv:
            ax.axvline(s, color="0.8", lw=0.5)
            if ax is axes[0] and p != SILENCE:
                ax.text(0.5 * (s + e), 1.02, p, transform=ax.get_xaxis_transform(), ha="center",
                        fontsize=7, color="C3" if p in BILABIALS else ("C2" if p == "uw" else "k"))
            if p in BILABIALS:
                ax.axvspan(s, e, color="C3", alpha=0.12)
            elif p == "uw":
                ax.axvspan(s, e, color="C2", alpha=0.12)
        ax.set_ylabel(name, fontsize=8)
        ax.set_xlim(0, t[-1])
    axes[0].axhline(0, color="C3", lw=0.6, ls="--")
    axes[-1].set_xlabel("time (s)")
    picks = []   # the most closed bilabial, the most protruded /uw/, the most open vowel
    for want, col, sign in ((lambda p: p in BILABIALS, art._LD, -1), (lambda p: p == "uw", art._LP, 1),
                            (lambda p: p in ("aa", "ae", "ao", "ah", "aw", "ay"), art._LD, 1)):
        best = None
        for s, e, p in iv:
            m = (t >= s) & (t < e)
            if want(p) and m.any():
                k = int(np.argmax(sign * res.tract[m, col]))
                score = sign * res.tract[m, col][k]
                if best is None or score > best[0]:
                    best = (score, p, min(int(t[m][k] * 25), len(frames) - 1))
        if best is not None:
            picks.append(best[1:])
    for j, (p, f) in enumerate(picks):
        ax = fig.add_subplot(gs[3, j])
        ax.imshow(frames[f], cmap="gray", vmin=0, vmax=255)
        ax.set_title(f"/{p}/ frame {f}", fontsize=8)
        ax.axis("off")
    fig.suptitle(f"{seq['name']}: {seq['text']}", fontsize=9)
    fig.tight_layout()
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    write_figure(a.out, fig)
    print(a.out)


if __name__ == "__main__":
    main()
