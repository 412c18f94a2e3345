"""The Python API: load photos, detect, compare identities, draw an overlay.

    .venv/bin/python examples/python_api.py [OUT_DIR]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from fitme_cli.io import atomic_write_image, load_image
from fitme_cli.perception.detect import DetectSettings, detect
from fitme_cli.viz import draw_detection

out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/examples/api")
sys.path.insert(0, str(Path(__file__).parent))
from sample_photos import main as write_samples  # noqa: E402

write_samples(out / "photos")
settings = DetectSettings(all_faces=False)
results = {}
for name in ("astronaut", "cameraman"):
    photo = load_image(out / "photos" / "batch" / f"{name}.jpg")
    det = detect(photo.rgb, settings)
    face = det.face  # raises NoFaceFound when there is none
    pose = face.landmarks.pose
    print(f"{name}: {len(det.faces)} face(s), yaw {pose.yaw:+.1f} pitch {pose.pitch:+.1f} roll {pose.roll:+.1f}, "
          f"468 landmarks {face.landmarks.points.shape}, identity {face.identity.shape}")
    atomic_write_image(out / f"{name}.overlay.png", draw_detection(photo.rgb, det))
    results[name] = face.identity
d = float(np.linalg.norm(results["astronaut"] - results["cameraman"]))
print(f"identity distance astronaut-cameraman: {d:.3f} ({'different people' if d > 0.6 else 'same person'})")
