#!/usr/bin/env sh
# The learned parts judged side by side (docs/models.md, "Side by side"): classic or U-Net depth,
# each with the profile-correction MLP off and on, on the station suite's first six stations
# (101-106) and the accuracy suite; one binary, one sequence; then the tables.
#
#   training/side_by_side.sh [BINARY]     # about 1 h 40 min on 2 cores, most of it rendering
set -eu
cd "$(dirname "$0")/.."
bin=${1:-target/release/crestscan}
[ -x "$bin" ] || cargo build --release --locked
stations=bc-black-2@station101-101,bc-black-3@station102-102,bc-arc-over-25@station103-103,lc-round-black@station104-104,lc-accept@station105-105,bc-polished@station106-106
mkdir -p out
run() { # name suite depth correction [only]
  [ -s "out/side-$1.json" ] && return 0
  if [ -n "${5:-}" ]; then only="--only $5"; else only=""; fi
  # shellcheck disable=SC2086
  "$bin" bench --suite "$2" --depth "$3" --profile-correction "$4" $only --json "out/side-$1.json" --quiet > "out/side-$1.txt"
}
run stations-classic-off stations classic off "$stations"
run stations-cnn-off stations cnn off "$stations"
run stations-classic-on stations classic on "$stations"
run stations-cnn-on stations cnn on "$stations"
run accuracy-classic-off accuracy classic off
run accuracy-classic-on accuracy classic on
run accuracy-cnn-off accuracy cnn off
run accuracy-cnn-on accuracy cnn on
for suite in stations accuracy; do
  python3 training/compare.py classic="out/side-$suite-classic-off.json" classic+MLP="out/side-$suite-classic-on.json" \
    U-Nets="out/side-$suite-cnn-off.json" U-Nets+MLP="out/side-$suite-cnn-on.json"
done
