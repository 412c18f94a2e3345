"""Shared plumbing of the frozen identity networks: weights held as buffers, and the input check."""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import torch
from torch import nn

__all__ = ["register_weights", "check_image_batch"]


def register_weights(module: nn.Module, weights: Mapping[str, np.ndarray | torch.Tensor]) -> None:
    """Register each named tensor as a float32 buffer, nesting containers at the dots so that
    ``state_dict`` keys equal the names. Buffers follow ``.double()`` / ``.to(device)``; nothing trains them."""
    for name in sorted(weights):
        parent: nn.Module = module
        *path, leaf = name.split(".")
        for part in path:
            if part not in parent._modules:
                parent.add_module(part, nn.Module())
            parent = parent._modules[part]
        parent.register_buffer(leaf, torch.as_tensor(np.asarray(weights[name]), dtype=torch.float32).clone())


def check_image_batch(image: Any, size: int) -> None:
    """Raise ValueError unless ``image`` is a non-empty (B, 3, size, size) float tensor with RGB in [0, 1].

    The value range allows a little slack for rendered images; it catches 0..255 input. Skipped while
    tracing, where the values are symbolic.
    """
    if not isinstance(image, torch.Tensor):
        raise ValueError(f"expected a torch.Tensor image, got {type(image).__name__}")
    if not image.is_floating_point():
        raise ValueError(f"expected a floating-point image in [0, 1], got {image.dtype}")
    if image.ndim != 4 or tuple(image.shape[1:]) != (3, size, size):
        raise ValueError(f"expected image of shape (B, 3, {size}, {size}), got {tuple(image.shape)}")
    if torch.jit.is_tracing() or torch.compiler.is_compiling():
        return
    if image.shape[0] == 0:
        raise ValueError("empty batch")
    lo, hi = (float(v) for v in torch.aminmax(image.detach()))
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError("image contains NaN or infinity")
    if lo < -0.5 or hi > 1.5:
        raise ValueError(f"image values span [{lo:.3g}, {hi:.3g}]; expected RGB in [0, 1], not 0..255")
