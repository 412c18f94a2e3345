"""Skin-tone augmentation by masked histogram matching (FitMe, Eq. 2): A_D' = M h(A_D, A_D*) + (1 - M) A_D.

- M: how close each texel is to the mean forehead skin tone. Exactly 1 near it, exactly 0 far from it
  (brows, lips, hair, stubble keep their own colour), smooth in between.
- h: per-channel histogram matching, in log albedo, of the skin texels to a target of the Monk Skin
  Tone level: its mean from the MST swatch, its spread the source's own (texture contrast is kept;
  the distribution's shape is matched to a log-normal).
- Monk Skin Tone swatches (Monk 2019, skintone.google) are display sRGB colours, not albedos. We take
  their linear values times 0.65, which puts MST 1 near the diffuse albedo of very light skin (~0.6 in
  red) and MST 10 near that of very dark skin (~0.014).

Everything works in linear light on (H, W, 3) float32 maps in the shape model's UV layout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import WrongLayout
from ..io.maps import srgb_to_linear

__all__ = ["MONK_SRGB", "AugmentSettings", "monk_albedo", "skin_mask", "match_to_level", "augment_albedo"]

MONK_SRGB = ("#f6ede4", "#f3e7db", "#f7ead0", "#eadaba", "#d7bd96", "#a07e56", "#825c43", "#604134", "#3a312a", "#292420")
_ALBEDO_SCALE = 0.65


@dataclass(frozen=True)
class AugmentSettings:
    # M = 1 within ``inner`` forehead log-spreads (a 3-channel distance: 3.5 keeps 99 % of skin texels
    # at M = 1, so strong re-toning shows no half-mixed speckles); M = 0 beyond ``outer``.
    inner: float = 3.5
    outer: float = 6.0
    sample: int = 200_000  # texels used to estimate the source distribution (speed; deterministic)


def monk_albedo(level: int) -> np.ndarray:
    """(3,) linear diffuse albedo for Monk Skin Tone ``level`` (1 lightest .. 10 darkest)."""
    if not 1 <= level <= 10:
        raise ValueError(f"Monk Skin Tone level must be 1..10, got {level}")
    h = MONK_SRGB[level - 1].lstrip("#")
    srgb = np.array([int(h[i : i + 2], 16) / 255.0 for i in (0, 2, 4)])
    return (srgb_to_linear(srgb) * _ALBEDO_SCALE).astype(np.float32)


def _forehead_stats(albedo: np.ndarray, forehead: np.ndarray) -> tuple[np.ndarray, float]:
    logs = np.log(np.clip(albedo[forehead], 1e-4, None))
    centre = np.median(logs, axis=0)
    spread = float(np.median(np.abs(logs - centre)) * 1.4826) + 1e-3  # robust std
    return centre, spread


def check_layout(albedo: np.ndarray, forehead: np.ndarray) -> None:
    """Raise WrongLayout unless ``albedo`` looks like a skin albedo map in our UV layout."""
    h, w = albedo.shape[:2]
    if albedo.ndim != 3 or albedo.shape[2] != 3:
        raise WrongLayout(f"expected a 3-channel albedo map, got shape {albedo.shape}")
    if h != w or h < 64:
        raise WrongLayout(f"expected a square UV map of at least 64x64, got {w}x{h}")
    vals = albedo[forehead]
    med = np.median(vals, axis=0)
    if not (0.005 < med.mean() < 0.9):
        raise WrongLayout(f"the forehead area has mean albedo {med.mean():.3f}; expected skin (0.005-0.9): not an albedo map in fitme's UV layout")
    if not med[0] >= med[2]:
        raise WrongLayout("the forehead area is bluer than it is red: not a skin albedo map in fitme's UV layout")
    _, spread = _forehead_stats(albedo, forehead)
    if spread > 0.5:
        raise WrongLayout(f"the forehead area varies too much (log spread {spread:.2f}; skin is < 0.5): not an albedo map in fitme's UV layout")


def skin_mask(albedo: np.ndarray, forehead: np.ndarray, mapped: np.ndarray, s: AugmentSettings = AugmentSettings()) -> np.ndarray:
    """(H, W) float32 M in [0, 1]: 1 at the forehead's tone, exactly 0 from ``outer`` spreads away.

    Per texel, in log albedo. (Blurring first, to make M spatially smooth, puts halos of the old tone
    around brows and hair: their dark colour bleeds into the neighbouring skin's distance.)"""
    centre, spread = _forehead_stats(albedo, forehead)
    d = np.linalg.norm(np.log(np.clip(albedo, 1e-4, None)) - centre, axis=-1) / spread
    t = np.clip((s.outer - d) / (s.outer - s.inner), 0.0, 1.0)
    return (t * t * (3 - 2 * t) * mapped).astype(np.float32)


def match_to_level(albedo: np.ndarray, mask: np.ndarray, level: int, s: AugmentSettings = AugmentSettings()) -> np.ndarray:
    """h(A_D, A_D*): every texel's per-channel log albedo, mapped through the skin texels' empirical CDF
    onto a log-normal around the level's albedo with the skin's own log-spread."""
    from scipy.special import ndtri

    skin = mask >= 0.5
    if skin.sum() < 16:
        raise WrongLayout("too few skin texels to match (is this an albedo map in fitme's UV layout?)")
    logs = np.log(np.clip(albedo, 1e-4, None))
    target = np.log(monk_albedo(level))
    out = np.empty_like(albedo)
    rng = np.random.default_rng(0)
    for c in range(3):
        src = logs[..., c][skin]
        if src.size > s.sample:
            src = rng.choice(src, s.sample, replace=False)
        src = np.sort(src)
        spread = float(np.std(src)) + 1e-6
        q = (np.arange(src.size) + 0.5) / src.size
        mapped = target[c] + spread * ndtri(q)
        out[..., c] = np.exp(np.interp(logs[..., c], src, mapped))
    return out


def augment_albedo(albedo: np.ndarray, forehead: np.ndarray, mapped: np.ndarray, level: int,
                   s: AugmentSettings = AugmentSettings()) -> tuple[np.ndarray, np.ndarray]:
    """(A_D', M) for one Monk level. ``forehead``/``mapped``: (H, W) bool UV masks at the map's size."""
    check_layout(albedo, forehead)
    m = skin_mask(albedo, forehead, mapped, s)
    h = match_to_level(albedo, m, level, s)
    out = m[..., None] * h + (1 - m[..., None]) * albedo
    out[m == 0] = albedo[m == 0]  # exactly as they were, not a float round trip
    return out.astype(np.float32), m
