#!/usr/bin/env bash
# A batch: a folder of photos including bad ones. Each bad photo gets a one-line error and the rest
# still run; the exit status is the first failure's (here 16: coffee.jpg, first in order, has no face).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-out/examples/batch}
.venv/bin/python examples/sample_photos.py "$OUT/photos"
status=0
.venv/bin/fitme detect "$OUT"/photos/batch/* --overlay "$OUT" -o "$OUT/detect.json" || status=$?
echo "exit status $status; per-photo results and errors in $OUT/detect.json"
