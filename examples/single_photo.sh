#!/usr/bin/env bash
# One photo: detect the face, write an overlay to look at and the results as JSON.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-out/examples/single}
.venv/bin/python examples/sample_photos.py "$OUT/photos"
.venv/bin/fitme detect "$OUT/photos/astronaut.jpg" --overlay "$OUT" -o "$OUT/detect.json"
echo "look at $OUT/astronaut.overlay.png"
