"""The sRGB transfer curve on torch tensors: the one copy the renderer, the fit and BRDF-GAN share
(numpy arrays: ``io.maps``; the renderer's CPU fast path: ``render._kernels.srgb_encode``)."""

from __future__ import annotations

import torch

__all__ = ["srgb_to_linear", "linear_to_srgb"]


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """sRGB -> linear light, elementwise, any shape and float dtype. Not clamped (callers whose values
    may leave [0, 1] clamp first); the inner clamp keeps the unused branch's gradient finite at 0."""
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Linear light -> sRGB [0, 1], clipped to [0, 1] first; finite gradients at 0."""
    x = x.clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)
