"""Bilinear UV texture lookup, differentiable with respect to both the texture and the UVs."""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["sample_texture"]


def sample_texture(texture: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """texture: (B, C, Ht, Wt), row 0 at v = 1 (images are stored top row first); uv: (B, H, W, 2) in
    [0, 1] (u right, v up). Returns (B, C, H, W). Texel centres at (k + 0.5) / size; lookups outside
    [0, 1] clamp to the border texels."""
    if texture.ndim != 4:
        raise ValueError(f"sample_texture: expected texture of shape (B, C, H, W), got {tuple(texture.shape)}")
    if uv.ndim != 4 or uv.shape[-1] != 2 or uv.shape[0] != texture.shape[0]:
        raise ValueError(f"sample_texture: expected uv of shape ({texture.shape[0]}, H, W, 2), got {tuple(uv.shape)}")
    grid = torch.stack([uv[..., 0] * 2 - 1, 1 - uv[..., 1] * 2], -1).to(texture.dtype)
    return F.grid_sample(texture, grid, mode="bilinear", padding_mode="border", align_corners=False)


def _sample_texture_ref(texture, uv):
    """Per pixel: the four texels around (u W - 1/2, (1 - v) H - 1/2), weighted bilinearly."""
    b, c, h, w = texture.shape
    out = torch.zeros(b, c, uv.shape[1], uv.shape[2], dtype=texture.dtype)
    for k in range(b):
        for i in range(uv.shape[1]):
            for j in range(uv.shape[2]):
                x = (uv[k, i, j, 0] * w - 0.5).clamp(0, w - 1)
                y = ((1 - uv[k, i, j, 1]) * h - 0.5).clamp(0, h - 1)
                x0, y0 = int(x.floor()), int(y.floor())
                x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
                fx, fy = x - x0, y - y0
                out[k, :, i, j] = ((1 - fx) * (1 - fy) * texture[k, :, y0, x0] + fx * (1 - fy) * texture[k, :, y0, x1]
                                   + (1 - fx) * fy * texture[k, :, y1, x0] + fx * fy * texture[k, :, y1, x1])
    return out
