"""Write the sample photos the examples and `make demo` use, into DIR. They come at run time from real
photos shipped inside PyPI packages (scikit-image's astronaut and cameraman, matplotlib's Grace
Hopper); none is committed.

    python examples/sample_photos.py DIR

DIR/astronaut.jpg                 one frontal face (scikit-image's astronaut)
DIR/person/astronaut_{1,2,3}.jpg  three "photos" of one person: original, mirrored crop, rotated darker
DIR/batch/                        a batch: three people, a photo with no face, a truncated JPEG, a text file
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
from skimage import data

from fitme_cli.io import available_samples, sample_photo


def _write(path: Path, rgb: np.ndarray, quality: int = 92) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(buf.tobytes())
    tmp.replace(path)


def main(out: Path) -> None:
    astronaut = sample_photo("astronaut").rgb
    _write(out / "astronaut.jpg", astronaut)

    person = out / "person"
    _write(person / "astronaut_1.jpg", astronaut)
    _write(person / "astronaut_2.jpg", np.ascontiguousarray(astronaut[10:330, 60:380][:, ::-1]))
    m = cv2.getRotationMatrix2D((225, 127), 12, 1.0)
    _write(person / "astronaut_3.jpg", (cv2.warpAffine(astronaut, m, (512, 512)) * 0.7).astype(np.uint8))

    batch = out / "batch"
    _write(batch / "astronaut.jpg", astronaut)
    _write(batch / "cameraman.jpg", sample_photo("camera").rgb)
    if "grace_hopper" in available_samples():  # needs matplotlib (a test extra)
        _write(batch / "grace_hopper.jpg", sample_photo("grace_hopper").rgb)
    _write(batch / "coffee.jpg", data.coffee())
    full = (batch / "astronaut.jpg").read_bytes()
    (batch / "truncated.jpg").write_bytes(full[: len(full) // 2])
    (batch / "notes.txt").write_text("not a photo\n")
    print(f"sample photos in {out}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(Path(sys.argv[1]))
