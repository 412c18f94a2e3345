"""ADA-style discriminator augmentation (Karras et al. 2020), reduced to the transforms that make
sense for UV reflectance maps: x-flip (mirrors the symmetric layout; normals' x flips sign), integer
translation, and brightness / contrast / saturation of the albedos (``color=False`` leaves them out).
Each is applied per sample with probability p, identically to real and generated maps, and is
differentiable; an applied flip mirrors half the samples (a fair coin), so p = 1 still augments.
"""

from __future__ import annotations

import torch

__all__ = ["augment"]


def augment(x: torch.Tensor, p: float, generator: torch.Generator | None = None, color: bool = True) -> torch.Tensor:
    """x: (B, 7, R, R) network space (A_D 0:3, A_S 3, N_S 4:7). Returns the augmented batch; with
    ``color=False`` only the geometric transforms (flip, translation)."""
    if p <= 0:
        return x
    b, _, r, _ = x.shape
    dev = x.device

    def draw(*shape):
        return torch.rand(*shape, generator=generator).to(dev)

    def on(prob):
        return (draw(b) < prob).to(x.dtype).view(b, 1, 1, 1)

    # applied with probability p, then a fair coin, as StyleGAN2-ADA's xflip: a flip drawn with p alone flipped every
    # sample at p = 1 (where the committed run's ADA sits from 159 kimg on), which is no augmentation (2026-11-28)
    flip = on(p) * (draw(b) < 0.5).to(x.dtype).view(b, 1, 1, 1)
    flipped = x.flip(3) * torch.tensor([1, 1, 1, 1, -1, 1, 1], dtype=x.dtype, device=dev).view(1, 7, 1, 1)
    x = flip * flipped + (1 - flip) * x

    shifts = ((draw(b, 2) * 2 - 1) * r / 16).round().long() * (draw(b, 1) < p).long()
    x = torch.stack([torch.roll(x[i], (int(shifts[i, 0]), int(shifts[i, 1])), dims=(1, 2)) for i in range(b)])
    if not color:
        return x

    alb = x[:, :4]
    bright = (torch.randn(b, generator=generator).to(dev) * 0.1).view(b, 1, 1, 1) * on(p)
    contrast = torch.exp2(torch.randn(b, generator=generator).to(dev) * 0.25).view(b, 1, 1, 1) ** on(p)
    mean = alb.mean(dim=(1, 2, 3), keepdim=True)
    alb = (alb - mean) * contrast + mean + bright
    rgb = alb[:, :3]
    grey = rgb.mean(1, keepdim=True)
    sat = torch.exp2(torch.randn(b, generator=generator).to(dev) * 0.5).view(b, 1, 1, 1) ** on(p)
    rgb = grey + (rgb - grey) * sat
    return torch.cat([rgb, alb[:, 3:4], x[:, 4:]], 1)
