#!/bin/bash
# Rebuild splatcli/viewer/static/vendor from npm: the splat renderer the viewer runs
# (Spark, MIT, World Labs) and the three.js files it imports (MIT). The built files are
# stored gzip-compressed (-n: no name or time, so the bytes are reproducible) and served
# with Content-Encoding: gzip. Usage: tools/vendor_viewer.sh   (needs npm)
set -euo pipefail
SPARK=2.2.0
THREE=0.187.0
repo=$(cd "$(dirname "$0")/.." && pwd)
out=$repo/splatcli/viewer/static/vendor
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
(cd "$tmp" && npm init -y >/dev/null && npm install --silent --no-audit --no-fund "@sparkjsdev/spark@$SPARK" "three@$THREE")
nm=$tmp/node_modules
rm -rf "$out" && mkdir -p "$out/addons/controls" "$out/addons/postprocessing"
gz() { gzip -n -9 -c "$1" > "$2.gz"; }
gz "$nm/@sparkjsdev/spark/dist/spark.module.min.js" "$out/spark.module.min.js"
gz "$nm/three/build/three.module.js" "$out/three.module.js"
gz "$nm/three/build/three.core.js" "$out/three.core.js"
gz "$nm/three/examples/jsm/controls/OrbitControls.js" "$out/addons/controls/OrbitControls.js"
gz "$nm/three/examples/jsm/postprocessing/Pass.js" "$out/addons/postprocessing/Pass.js"
{ echo "@sparkjsdev/spark $SPARK (MIT): https://www.npmjs.com/package/@sparkjsdev/spark"
  echo "three $THREE (MIT): https://www.npmjs.com/package/three"
  echo "Rebuilt by tools/vendor_viewer.sh; sha256 of the uncompressed files:"
  (cd "$out" && for f in $(find . -name '*.gz' | sort); do
     printf '%s  %s\n' "$(gunzip -c "$f" | sha256sum | cut -d' ' -f1)" "${f%.gz}"; done)
} > "$out/VERSIONS"
{ echo "== @sparkjsdev/spark $SPARK =="; cat "$nm/@sparkjsdev/spark/LICENSE"; echo
  echo "== three $THREE =="; cat "$nm/three/LICENSE"; } > "$out/LICENSES"
echo "vendored into $out:"; du -ab "$out" | sort -k2
