#!/usr/bin/env bash
# Runs the client checks against the real binary on a loopback port: the curl + jq smoke test and
# the generated Python SDK's script. Needs curl, jq, python3 with openapi-python-client and httpx.
#   tests/clients.sh [PATH/TO/crestscan]   (default: target/debug/crestscan, built by `cargo test`)
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${1:-target/debug/crestscan}
work=$(mktemp -d)
server=
cleanup() { [ -n "$server" ] && kill "$server" 2>/dev/null; wait 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT

"$bin" simulate --preset ci --seed 3 --out "$work/ci" >/dev/null
tar -C "$work/ci" --exclude truth -cf "$work/ci.tar" .

start() {
  "$bin" serve --bind 127.0.0.1:0 --data-dir "$work/data-$1" --log warn --min-free-disk-mb 64 > "$work/server-$1.out" &
  server=$!
  for _ in $(seq 1 100); do
    grep -q 'listening on' "$work/server-$1.out" 2>/dev/null && break
    sleep 0.1
  done
  base=$(sed -n 's/.*listening on //p' "$work/server-$1.out")
  [ -n "$base" ] || { echo "server did not start"; exit 1; }
}

start curl
tests/curl/smoke.sh "$base" "$work/ci.tar" "$(jq -r .verdict "$work/ci/truth/truth.json")"
kill "$server"; wait "$server" || true

openapi-python-client generate --path openapi/openapi.json --config tests/sdk/generator.yaml --output-path "$work/sdk/crestscan_client" --meta none >/dev/null 2>"$work/generate.log" \
  || { cat "$work/generate.log"; exit 1; }
start sdk
PYTHONPATH="$work/sdk" python3 tests/sdk/smoke.py "$base" "$work/ci.tar"
