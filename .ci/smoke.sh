#!/usr/bin/env bash
# The other-Python ends of CI (issue 28): a fresh venv of the given Python version,
# `pip install .` with the pins of constraints.txt, then the smoke path from outside the
# repository with the installed package -- a tiny corpus, train, synth, evaluate --quick.
#
#   .ci/smoke.sh 3.13                  # python3.13 from PATH (or SMOKE_PYTHON=/path/to/python)
#   .ci/smoke.sh 3.12                  # likewise python3.12
#   SMOKE_DIR=/tmp/s .ci/smoke.sh 3.12 # keep the venv and outputs there (default: a temp dir, removed)
#   SMOKE_PIP_ARGS='--extra-index-url https://download.pytorch.org/whl/cpu' .ci/smoke.sh 3.13
#
# Under pyenv, `PYENV_VERSION=3.12.1` picks the interpreter behind the python3.12 shim.
#
# Not run by .ci/run unless BAYES_TALK_SMOKE313=1: PyPI's Linux torch wheel is the CUDA
# build, so the install fetches ~3 GB (torch 527 MB, nvidia-* and triton) and makes a 5.6 GB
# venv (measured; README.md, "Installing the package").
set -euo pipefail
cd "$(dirname "$0")/.."
REPO=$PWD
VERSION=${1:?usage: .ci/smoke.sh PYTHON_VERSION (e.g. 3.12 or 3.13)}
PY=${SMOKE_PYTHON:-python$VERSION}
"$PY" -c "import sys; v = '.'.join(map(str, sys.version_info[:2])); assert v == '$VERSION', f'$PY is Python {v}, not $VERSION'"
if [[ -n "${SMOKE_DIR:-}" ]]; then
    WORK=$SMOKE_DIR; mkdir -p "$WORK"
else
    WORK=$(mktemp -d); trap 'rm -rf "$WORK"' EXIT
fi
N=${SMOKE_UTTERANCES:-16}
t0=$SECONDS
step() { echo "[smoke$VERSION $((SECONDS - t0)) s] $*"; }

if [[ ! -x "$WORK/venv/bin/bayes-talk" ]]; then
    step "venv with $("$PY" --version) in $WORK/venv; pip install . -c constraints.txt"
    "$PY" -m venv "$WORK/venv"
    # shellcheck disable=SC2086
    "$WORK/venv/bin/python" -m pip install --quiet --disable-pip-version-check \
        -c "$REPO/constraints.txt" ${SMOKE_PIP_ARGS:-} "$REPO"
fi
BT="$WORK/venv/bin/bayes-talk"
cd "$WORK"                              # the installed package, not the source tree
rm -rf corpus model synth eval.json eval.md eval_trajectories.png
"$BT" --version
step "corpus build ($N utterances, 64 px)"
"$BT" -q corpus build corpus --n-utterances "$N" --seed 0 --image-size 64
step "train (default model, no calibration, no aligner)"
"$BT" -q train corpus --out model --no-calibrate-bands --no-alignment --holdout 2
last=$(printf 'utt%04d' $((N - 1)))
step "synth $last (Laplace posterior, video)"
"$BT" -q synth model --audio "corpus/utterances/$last.wav" --labels "corpus/utterances/$last.lab" --out synth
test -s synth/trajectory.npy && test -s synth/posterior.nc && test -s synth/face.mp4
step "evaluate --quick (scaled to the corpus)"
"$BT" -q evaluate --protocol deena2010 --corpus corpus --quick --min-utterances "$N" \
    --methods zero,hmm-mean,ssgpdm-vlmm-predict --no-figures --json eval.json
"$WORK/venv/bin/python" - <<'EOF'
import json
r = json.load(open("eval.json"))
assert set(r["methods"]) == {"zero", "hmm-mean", "ssgpdm-vlmm-predict"}, r["methods"].keys()
print("evaluate:", {k: v["headline"] for k, v in r["methods"].items()})
EOF
step "passed"
