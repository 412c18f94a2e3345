#!/usr/bin/env bash
# Several photos of one person: landmarks, pose and identity for each, one JSON file for all.
# (`fitme fit` will fit one avatar to all of them; for now this shows what it will start from.)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-out/examples/several}
.venv/bin/python examples/sample_photos.py "$OUT/photos"
.venv/bin/fitme detect "$OUT"/photos/person/*.jpg --overlay "$OUT" -o "$OUT/detect.json"
.venv/bin/python - "$OUT/detect.json" <<'PY'
import json, sys
import numpy as np
photos = json.load(open(sys.argv[1]))["photos"]
ids = [np.array(p["faces"][p["chosen"]]["identity"]) for p in photos]
for p, e in zip(photos, ids):
    print(f'{p["path"]}: identity distance to the first photo {np.linalg.norm(e - ids[0]):.3f} (same person < 0.6)')
PY
