"""A screen for the blind test's tells, before a judge finds them: ~1,000 per-sample statistics of the maps, each
ranked by how well it alone tells G's samples from the data's (the AUC of a threshold on it).

Judges tell G's triplets by one statistic each (the specular's grey levels, a texel checkerboard, bumps embossed into
the albedo: docs/brdf_gan.md). On 318.61 kimg this screen put both of that session's judges' tells at its top (AUC 1.00
and 0.00), with the next ones below them: the chromaticity's relief, the normals' skew. Each statistic is per sample,
Laplacian band (``metrics._bandpass``; 0: 1-2 texels, 1: 2-4, 2: 4-8, 3: 8-16) and region of ``metrics.region_labels``,
of six maps: the linear albedo's log luminance, its two ``metrics.log_chroma`` axes, the linear specular, the normals'
x and y (``train.texel_maps``). Per map: log variance, skewness, log kurtosis, the correlation of neighbours along u
(``metrics.region_band_neighbour``); per pair of maps: the correlation; per map, over the whole map:
``metrics.nyquist_log_ratio``. Two halves of the data give each one's AUC by chance. The statistics are
``metrics.region_band_statistics``, which the BRDF-GAN's screen term (``--screen-weight``) pulls to the data's: on a G
trained with it, the screen reads how well the term fit, not a fresh tell.

    python -m fitme_cli.reflectance.gan.screen CHECKPOINT_OR_MODELS DATA_DIR [-n 128] [--top 40] [--json OUT]
"""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from .metrics import band_statistic_names, region_band_statistics, region_labels
from .networks import GanSettings
from .train import TEXEL_MAPS, texel_maps

__all__ = ["MAPS", "screen_features", "auc", "Separation", "screen"]

MAPS = TEXEL_MAPS
_LEVELS = 4


def _maps(x: torch.Tensor, s: GanSettings) -> torch.Tensor:
    """(N, 7, R, R) network space -> (N, 6, R, R) float64, the ``MAPS`` (``train.texel_maps``)."""
    return texel_maps(x.float(), s).double()


def screen_features(x: torch.Tensor, regions: torch.Tensor, s: GanSettings, names: tuple[str, ...] | None = None
                    ) -> tuple[np.ndarray, list[str]]:
    """x: (N, 7, R, R) network space, R divisible by 16; regions: (R, R) uint8 labels (255 unmapped); ``names``: one per
    region of ``region_labels`` (default "region{label}") -> ((N, F) float64 ``metrics.region_band_statistics`` of the
    ``MAPS``, their F names). A flat region's variance-normalised statistics are 0."""
    if x.ndim != 4 or x.shape[1] != 7 or x.shape[-1] != x.shape[-2] or x.shape[-1] % 2 ** _LEVELS:
        raise ValueError(f"expected (N, 7, R, R) maps with R divisible by {2 ** _LEVELS}, got {tuple(x.shape)}")
    if regions.shape != x.shape[2:] or regions.dtype != torch.uint8:
        raise ValueError(f"expected (R, R) uint8 regions matching the maps, got {tuple(regions.shape)} {regions.dtype}")
    labels = region_labels(regions)
    names = names or tuple(f"region{lab}" for lab in labels)
    if len(names) != len(labels):
        raise ValueError(f"expected {len(labels)} region names, got {len(names)}")
    with torch.no_grad():
        feats = region_band_statistics(_maps(x, s), regions, _LEVELS)
    return feats.numpy(), band_statistic_names(MAPS, names, _LEVELS)


def auc(a: np.ndarray, b: np.ndarray) -> float:
    """P(a value of a > one of b) + P(equal) / 2 (the Mann-Whitney AUC): 1 or 0 when a threshold splits them, 0.5 when
    they mix. a, b: (n,), (m,) finite."""
    from scipy.stats import rankdata

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.ndim != 1 or b.ndim != 1 or not len(a) or not len(b):
        raise ValueError(f"expected two non-empty 1-D arrays, got shapes {a.shape} and {b.shape}")
    ranks = rankdata(np.concatenate([a, b]))
    return float((ranks[:len(a)].sum() - len(a) * (len(a) + 1) / 2) / (len(a) * len(b)))


@dataclass(frozen=True)
class Separation:
    name: str
    auc: float  # G's samples against all the data's
    auc_half: float  # the data's first half against its second: the same statistic by chance
    data_median: float
    gan_median: float


def screen(gan: np.ndarray, data: np.ndarray, names: list[str]) -> list[Separation]:
    """gan: (n, F), data: (m, F) ``screen_features`` (m >= 4), names: F -> every statistic finite on both sides,
    the best-separating first (by |auc - 0.5|)."""
    if gan.ndim != 2 or data.ndim != 2 or gan.shape[1] != data.shape[1] != len(names) or len(data) < 4 or not len(gan):
        raise ValueError(f"expected (n, F) and (m >= 4, F) statistics and F names, got {gan.shape}, {data.shape}, "
                         f"{len(names)}")
    h = len(data) // 2
    out = [Separation(n, auc(gan[:, j], data[:, j]), auc(data[:h, j], data[h:, j]), float(np.median(data[:, j])),
                      float(np.median(gan[:, j])))
           for j, n in enumerate(names) if np.isfinite(gan[:, j]).all() and np.isfinite(data[:, j]).all()]
    return sorted(out, key=lambda r: -abs(r.auc - 0.5))


def _features(x: torch.Tensor, regions: torch.Tensor, s: GanSettings, names: tuple[str, ...], chunk: int = 16):
    parts = [screen_features(x[i:i + chunk], regions, s, names) for i in range(0, len(x), chunk)]
    return np.concatenate([p[0] for p in parts]), parts[0][1]


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("generator", type=Path, help="a models folder (brdf_gan.safetensors) or a training checkpoint")
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("-n", type=int, default=128, help="samples per side (G_ema's; the data's first 2n split in two)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--json", type=Path, help="also write every statistic's separation here")
    args = ap.parse_args(argv)
    from ...errors import FitmeError
    from .data import load_dataset, load_regions
    from .latents import sample_z
    from .report import _region_name
    from .store import load_generator
    from .train import load_checkpoint

    try:
        if args.n < 2:
            raise ValueError(f"expected -n of at least 2, got {args.n}")
        G = load_checkpoint(args.generator).G_ema if args.generator.is_file() else load_generator(args.generator)
        data = load_dataset(args.data_dir, G.settings, limit=2 * args.n, progress=False)
        regions = load_regions(G.settings.resolution)
        names = tuple(_region_name(lab) for lab in region_labels(regions))
        with torch.no_grad():
            fake = torch.cat([G(z, noise_mode="random").cat() for z in sample_z(args.n, G.settings.z_dim, args.seed).split(16)])
        rows = screen(_features(fake, regions, G.settings, names)[0], *_features(data, regions, G.settings, names))
        if args.json:
            from ...io.atomic import atomic_write_bytes

            atomic_write_bytes(args.json, (json.dumps([asdict(r) for r in rows], indent=1) + "\n").encode())
    except (FitmeError, OSError, ValueError) as e:
        print(f"screen: {e}", file=sys.stderr)
        return 2
    tell = sum(abs(r.auc - 0.5) >= 0.45 for r in rows)
    print(f"{len(rows)} statistics; {tell} tell G from the data at AUC >= 0.95 or <= 0.05 "
          f"(by chance between the data's halves: {sum(abs(r.auc_half - 0.5) >= 0.45 for r in rows)})")
    for r in rows[:args.top]:
        print(f"  AUC {r.auc:.3f} (halves {r.auc_half:.3f})  {r.name:45s} data {r.data_median:+.3f}  G {r.gan_median:+.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
