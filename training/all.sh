#!/usr/bin/env sh
# The whole training run from a clean machine: a virtual environment, the renders (random
# stations, seeds disjoint from every test and benchmark), the pairs, the MLP, the depth U-Nets,
# their cards.
#
#   training/all.sh          # about 2 h on 2 cores, most of it rendering
set -eu
cd "$(dirname "$0")/.."
venv=${TRAINING_VENV:-training/.venv}
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
"$venv/bin/pip" install --quiet --disable-pip-version-check -r training/requirements.txt
cargo build --release --locked
"$venv/bin/python" training/render.py --split heldout --max 8
"$venv/bin/python" training/render.py --split train --max 24
"$venv/bin/python" training/pairs.py
"$venv/bin/python" training/profile_mlp.py
"$venv/bin/python" training/depth_cnn.py
