"""Figures for docs/skin_data.md: docs/skin_data_samples.png (samples x [albedo, specular, normals] and
a 512² nose/cheek crop) and docs/skin_data_mst.png (forehead albedo over the melanin range against the
Monk Skin Tone swatches).  Run: .venv/bin/python benchmarks/skin_data_figures.py"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from fitme_cli.io.maps import linear_to_srgb
from fitme_cli.perception.registry import ensure_models
from fitme_cli.reflectance.augment import MONK_SRGB, monk_albedo
from fitme_cli.reflectance.biophysical import skin_rgb
from fitme_cli.reflectance.skin_data import SkinDataSettings, generate_sample, skin_layout

DOCS = Path(__file__).resolve().parent.parent / "docs"


def to8(x):
    return np.round(np.clip(x, 0, 1) * 255).astype(np.uint8)


def label(img, text, scale=0.45):
    cv2.putText(img, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def tiles(sample):
    a = to8(linear_to_srgb(sample.albedo))
    s = to8(np.repeat(sample.specular[..., None], 3, -1) * 2.0)  # x2 so the range 0..0.5 is visible
    n = to8(sample.normals * 0.5 + 0.5)
    return a, s, n


def samples_figure(models, seed=0, n=8, indices=None):
    lay = skin_layout(models, 256)
    rows = []
    indices = indices or list(range(n))
    for i in indices:
        smp = generate_sample(lay, seed, i, SkinDataSettings(size=256))
        a, s, nn = tiles(smp)
        p = smp.params
        txt = f"#{i} mel {p['melanin']:.2f} age {p['age']:.2f}" + (" beard" if p["beard"] else "") + (" freckles" if p["freckles"] else "")
        rows.append(np.concatenate([label(a.copy(), txt, 0.4), label(s, "specular x2"), label(nn, "normals")], 1))
    # zoomed crops at 512: nose/cheek of a light, an old and a dark sample
    lay5 = skin_layout(models, 512)
    crops = []
    for i in indices[:3]:
        smp = generate_sample(lay5, seed, i, SkinDataSettings(size=512))
        c = lay5.lm[205]
        x0, y0 = int(c[0]) - 40, int(c[1]) - 64
        for t in tiles(smp):
            cr = t[y0 : y0 + 128, x0 : x0 + 128]
            crops.append(cv2.resize(cr, (256, 256), interpolation=cv2.INTER_NEAREST))
    crop_rows = [np.concatenate(crops[k : k + 3], 1) for k in range(0, len(crops), 3)]
    crop_rows[0] = label(crop_rows[0].copy(), "512^2 crops of the right cheek / nose (2x nearest)")
    grid = np.concatenate(rows + crop_rows, 0)
    h = grid.shape[0]
    half = (len(rows) + len(crop_rows) + 1) // 2 * 256
    left, right = grid[:half], grid[half:]
    if right.shape[0] < left.shape[0]:
        right = np.concatenate([right, np.full((left.shape[0] - right.shape[0],) + right.shape[1:], 255, np.uint8)], 0)
    fig = np.concatenate([left, np.full((left.shape[0], 8, 3), 255, np.uint8), right], 1)
    del h
    cv2.imwrite(str(DOCS / "skin_data_samples.png"), fig[..., ::-1])


def mst_figure():
    ms = np.linspace(0, 1, 21)
    rgb = skin_rgb(ms, 0.2)
    w = 40
    top = np.concatenate([np.full((60, w, 3), to8(linear_to_srgb(c)), np.uint8) for c in rgb], 1)
    sw = []
    for level in range(1, len(MONK_SRGB) + 1):
        sw.append(np.full((60, 84, 3), to8(linear_to_srgb(monk_albedo(level))), np.uint8))
    bottom = np.concatenate(sw, 1)
    W = max(top.shape[1], bottom.shape[1])
    pad = lambda im: np.concatenate([im, np.full((im.shape[0], W - im.shape[1], 3), 255, np.uint8)], 1)  # noqa: E731
    head = lambda t: label(np.full((20, W, 3), 255, np.uint8), t)  # noqa: E731
    fig = np.concatenate([head("skin_rgb(melanin 0..1 step 0.05, haemoglobin 0.2)"), pad(top),
                          head("Monk Skin Tone 1..10 as albedo (linear swatch x 0.65)"), pad(bottom)], 0)
    cv2.imwrite(str(DOCS / "skin_data_mst.png"), fig[..., ::-1])


def main():
    models = ensure_models(["shape_model"])
    idx = [int(a) for a in sys.argv[1:]] or None
    samples_figure(models, indices=idx)
    mst_figure()


if __name__ == "__main__":
    main()
