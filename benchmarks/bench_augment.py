"""Time `augment` per 1024² albedo map (the paper: 2.5 s) and write docs/augment_levels.png: one
synthetic albedo map re-toned to all 10 Monk Skin Tone levels, with its mask."""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from safetensors.numpy import load_file

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_augment import synthetic_albedo  # noqa: E402

from fitme_cli.io.maps import linear_to_srgb  # noqa: E402
from fitme_cli.perception.registry import ensure_models  # noqa: E402
from fitme_cli.reflectance.augment import augment_albedo  # noqa: E402
from fitme_cli.shape.regions import region_masks  # noqa: E402


def main() -> None:
    region_uv = load_file(str(ensure_models(["shape_model"]) / "shape_model.safetensors"))["region_uv"]
    a = synthetic_albedo(region_uv, 1024)
    masks = region_masks(region_uv, 1024)
    times = []
    for level in (1, 4, 7, 10, 2):
        t0 = time.perf_counter()
        augment_albedo(a, masks["forehead"], masks["mapped"], level)
        times.append(time.perf_counter() - t0)
    print(f"augment per 1024x1024 map: {statistics.median(times):.2f} s (median of 5; paper 2.5 s on its hardware)")
    small = synthetic_albedo(region_uv, 256)
    m256 = region_masks(region_uv, 256)
    tiles = [linear_to_srgb(small)]
    for level in range(1, 11):
        out, mask = augment_albedo(small, m256["forehead"], m256["mapped"], level)
        tiles.append(linear_to_srgb(out))
    tiles.append(np.repeat(mask[..., None], 3, axis=2))
    crop = [t[40:216, 48:208] for t in tiles]  # the face part of the UV layout
    row1 = np.concatenate(crop[:6], 1)
    row2 = np.concatenate(crop[6:], 1)
    img = (np.concatenate([row1, row2], 0) * 255).astype(np.uint8)
    for i, label in enumerate(["source"] + [f"MST {k}" for k in range(1, 11)] + ["mask M"]):
        cv2.putText(img, label, (4 + 160 * (i % 6), 14 + 176 * (i // 6)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    out_path = Path(__file__).resolve().parents[1] / "docs" / "augment_levels.png"
    cv2.imwrite(str(out_path), img[..., ::-1])
    print(out_path)


if __name__ == "__main__":
    main()
