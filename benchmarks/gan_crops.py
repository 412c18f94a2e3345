"""Close-ups of the lips and the brows, the judges' oldest tells (docs/brdf_gan.md): the data's maps above, each
checkpoint's G_ema below, albedo (sRGB) | specular (x3, sRGB) per crop, enlarged x4 with nearest texels, two samples a
row. Writes one PNG.

    python benchmarks/gan_crops.py DATA_DIR CKPT... -o crops.png [--rows 3] [--seed 5]

The crops are the bounding boxes of the data's layout masks (``data.layout_image``'s lips and brows channels above
half their peak), grown by 6 texels at 256^2: the same texels for every map, so a soft edge or a halo shows against the data's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch


def _boxes(masks: list[torch.Tensor], pad: int) -> list[tuple[slice, slice]]:
    """Each mask's bounding box grown by ``pad``, all as tall as the tallest (centred, kept inside the map)."""
    found = [m.nonzero(as_tuple=True) for m in masks]
    r = masks[0].shape[0]
    height = max(int(rows.max()) - int(rows.min()) + 1 + 2 * pad for rows, _ in found)
    out = []
    for rows, cols in found:
        top = min(max((int(rows.min()) + int(rows.max()) + 1 - height) // 2, 0), r - height)
        out.append((slice(top, top + height), slice(max(int(cols.min()) - pad, 0), min(int(cols.max()) + pad + 1, r))))
    return out


def _sheet_maps(images, gan) -> np.ndarray:
    """(B, R, R, 4) float in [0, 1]: the albedo in sRGB and the specular x3 in sRGB, as the blind sheets show them."""
    from fitme_cli.ops.srgb import linear_to_srgb
    from fitme_cli.reflectance.gan.networks import decode_maps

    m = decode_maps(images, gan)
    spec = linear_to_srgb((3 * (m.specular.clamp(0, 1) * 255).round() / 255).clamp(0, 1))
    return torch.cat([linear_to_srgb(m.albedo), spec], 1).permute(0, 2, 3, 1).clamp(0, 1).numpy()


def _row(maps: np.ndarray, boxes, scale: int) -> np.ndarray:
    """One sample: for each box, albedo | specular, enlarged."""
    tiles = []
    for rs, cs in boxes:
        crop = maps[rs, cs]
        alb, spec = crop[..., :3], np.repeat(crop[..., 3:], 3, axis=-1)
        for t in (alb, spec):
            tiles.append(cv2.resize(t, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST))
            tiles.append(np.ones((t.shape[0] * scale, 4, 3)))
    return np.hstack(tiles[:-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("checkpoints", type=Path, nargs="+")
    ap.add_argument("-o", "--output", type=Path, required=True)
    ap.add_argument("--rows", type=int, default=3, help="rows per block (two samples a row) [3]")
    ap.add_argument("--seed", type=int, default=5, help="the latents' seed (gan.latents.sample_z) [5]")
    ap.add_argument("--scale", type=int, default=4)
    a = ap.parse_args()

    from fitme_cli.reflectance.gan.data import LAYOUT_CHANNELS, layout_image, load_dataset
    from fitme_cli.reflectance.gan.latents import sample_z
    from fitme_cli.reflectance.gan.networks import GanImages
    from fitme_cli.reflectance.gan.train import load_checkpoint

    torch.set_num_threads(1)
    n = 2 * a.rows
    blocks = []
    gan = None
    for ckpt in a.checkpoints:
        state = load_checkpoint(ckpt)
        gan = state.gan
        with torch.no_grad():
            imgs = state.G_ema(sample_z(n, gan.z_dim, a.seed), noise_mode="const")
        blocks.append((f"G_ema {state.nimg / 1000:.2f} kimg ({ckpt.parent.name})", _sheet_maps(imgs, gan)))
    data = load_dataset(a.data_dir, gan, limit=n).float()
    blocks.insert(0, ("data", _sheet_maps(GanImages.split(data), gan)))
    r = gan.resolution
    lay = layout_image(r)
    pad = max(1, round(6 * r / 256))
    masks = [lay[LAYOUT_CHANNELS.index(k)] for k in ("lips", "brows")]
    boxes = _boxes([m > 0.5 * m.max() for m in masks], pad)  # the layout scales the small masks by 10
    rows = []
    for title, maps in blocks:
        body = []
        for i in range(0, n, 2):
            left, right = _row(maps[i], boxes, a.scale), _row(maps[i + 1], boxes, a.scale)
            body += [np.hstack([left, np.ones((left.shape[0], 12, 3)), right]), np.ones((4, left.shape[1] * 2 + 12, 3))]
        block = (np.vstack(body) * 255 + 0.5).astype(np.uint8)
        head = np.full((18, block.shape[1], 3), 255, np.uint8)
        cv2.putText(head, f"{title}: lips albedo | specular x3 | brows albedo | specular x3 (two samples a row)", (2, 13),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        rows += [head, block]
    sheet = np.vstack(rows)
    a.output.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(a.output), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    print(f"wrote {a.output} ({sheet.shape[1]}x{sheet.shape[0]})")


if __name__ == "__main__":
    main()
