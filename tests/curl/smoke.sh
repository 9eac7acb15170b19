#!/usr/bin/env bash
# The service from a CI script's point of view, with curl and jq only:
# submit a bundle, poll, fetch the report, the threads CSV and the mesh, upload CMM data and read
# the comparison, and check one error's problem+json.
#   tests/curl/smoke.sh BASE_URL BUNDLE.tar TRUE_VERDICT   (accept or reject: the bundle's truth)
set -euo pipefail
base=${1:?base URL, e.g. http://127.0.0.1:8080}
bundle=${2:?bundle archive (.tar or .zip)}
want_verdict=${3:?the true verdict of the bundle, accept or reject}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
fail() { echo "smoke: FAIL: $*" >&2; exit 1; }

# Submit: 202, Location, queued.
code=$(curl -sS -o "$work/created.json" -D "$work/headers" -w '%{http_code}' \
  -H 'Content-Type: application/x-tar' -H 'Idempotency-Key: curl-smoke-1' \
  --data-binary @"$bundle" "$base/v1/inspections?client_reference=curl-smoke")
[ "$code" = 202 ] || fail "submit answered $code: $(cat "$work/created.json")"
location=$(grep -i '^location:' "$work/headers" | tr -d '\r' | cut -d' ' -f2)
id=$(jq -r .id "$work/created.json")
[ "$location" = "/v1/inspections/$id" ] || fail "Location $location"
echo "smoke: submitted $id"

# Wait without polling: the event stream ends after the terminal state (5 min at most).
curl -sS -f -N --max-time 300 "$base$location/events" > "$work/events" || fail "event stream: $(cat "$work/events")"
status=$(grep '^data:' "$work/events" | tail -1 | cut -c6- | jq -r .status)
grep -q '"status":"running"' "$work/events" || fail "no running state in the event stream"
[ "$status" = succeeded ] || fail "inspection ended $status: $(curl -sS "$base$location" | jq -c .error)"

# Report.
verdict=$(curl -sS -f "$base$location/report" | jq -r .verdict)
[ "$verdict" = "$want_verdict" ] || fail "verdict $verdict, truth $want_verdict"
decision=$(curl -sS -f "$base$location/report" | jq -r .decision)
case $decision in conforms|does_not_conform|indeterminate) ;; *) fail "decision $decision" ;; esac
echo "smoke: verdict $verdict, decision $decision"

# Threads as CSV: the header and one row per thread and angle bin.
curl -sS -f -H 'Accept: text/csv' "$base$location/threads" -o "$work/threads.csv"
[ "$(head -1 "$work/threads.csv")" = "thread,angle_deg,height_mm,uncertainty_mm" ] || fail "CSV header: $(head -1 "$work/threads.csv")"
rows=$(($(wc -l < "$work/threads.csv") - 1))
[ "$rows" -gt 0 ] || fail "empty threads CSV"

# Mesh, all three formats.
curl -sS -f "$base$location/mesh?format=ply" -o "$work/mesh.ply"
[ "$(head -c 4 "$work/mesh.ply")" = "ply" ] || [ "$(head -c 3 "$work/mesh.ply")" = "ply" ] || fail "not a PLY"
curl -sS -f -H 'Accept: model/stl' "$base$location/mesh" -o "$work/mesh.stl"
[ "$(stat -c %s "$work/mesh.stl")" -gt 84 ] || fail "STL too small"
curl -sS -f -H 'Accept: model/gltf-binary' "$base$location/mesh" -o "$work/mesh.glb"
[ "$(head -c 4 "$work/mesh.glb")" = "glTF" ] || fail "not a GLB"

# CMM: crestscan's own measured heights + 3 µm → the comparison's bias is exactly -3 µm.
awk -F, 'NR > 1 && $3 != "" { printf "%s,%s,%.6f\n", $1, $2, $3 + 0.003 }' "$work/threads.csv" > "$work/cmm.body"
{ echo "thread,angle_deg,height_mm"; cat "$work/cmm.body"; } > "$work/cmm.csv"
points=$(wc -l < "$work/cmm.body")
code=$(curl -sS -o /dev/null -w '%{http_code}' -X PUT -H 'Content-Type: text/csv' --data-binary @"$work/cmm.csv" "$base$location/cmm")
[ "$code" = 200 ] || fail "CMM upload answered $code"
curl -sS -f "$base$location/cmm-comparison" -o "$work/cmp.json"
jq -e --argjson n "$points" '.agreement.compared == $n and (.agreement.bias_mm + 0.003 | fabs) < 1e-5 and .agreement.within_tolerance' "$work/cmp.json" >/dev/null \
  || fail "comparison: $(jq -c .agreement "$work/cmp.json")"
echo "smoke: CMM comparison over $points points: $(jq -c '.agreement | {bias_mm, rms_mm, max_abs_deviation_mm}' "$work/cmp.json")"

# An error is problem+json with a stable code.
code=$(curl -sS -o "$work/problem.json" -D "$work/problem.headers" -w '%{http_code}' -H 'Content-Type: text/plain' --data 'x' "$base/v1/inspections")
[ "$code" = 415 ] || fail "wrong content type answered $code"
grep -qi '^content-type: application/problem+json' "$work/problem.headers" || fail "not problem+json"
[ "$(jq -r .code "$work/problem.json")" = unsupported_media_type ] || fail "code $(jq -r .code "$work/problem.json")"

# Health and readiness.
curl -sS -f "$base/healthz" >/dev/null
[ "$(curl -sS -f "$base/readyz" | jq -r .status)" = ready ] || fail "not ready"
echo "smoke: OK ($rows height rows, verdict $verdict)"
