#!/usr/bin/env bash
# Rebuilds src/export/html/viewer.min.js, the report's 3D viewer bundled with three.js into one
# classic script (the report inlines it; nothing is fetched at run time). Needs npm (the npm
# registry only); the versions are pinned, and the bundle is committed, so neither building nor
# testing crestscan runs this.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"
npm init -y >/dev/null
npm install --silent --no-audit --no-fund three@0.170.0 esbuild@0.24.0
cp "$here/viewer.js" .
npx esbuild viewer.js --bundle --minify --format=iife --target=es2020 --legal-comments=none --outfile=bundle.js
{
  echo "/* crestscan's report viewer (assets/viewer/viewer.js) with three.js r170, MIT licence, Copyright 2010-2024 three.js authors (assets/viewer/THREE-LICENSE); built by assets/viewer/build.sh */"
  cat bundle.js
} > "$here/../../src/export/html/viewer.min.js"
cp node_modules/three/LICENSE "$here/THREE-LICENSE"
echo "wrote src/export/html/viewer.min.js ($(wc -c < "$here/../../src/export/html/viewer.min.js") bytes)"
