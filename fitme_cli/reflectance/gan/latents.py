"""Latents for measuring a generator: the report's samples, the training snapshots, the figures and the
W prior all draw z here.

Why not ``torch.Generator().manual_seed(seed)``: ``train.new_state`` seeds torch's global stream with
``TrainSettings.seed`` and then builds the networks, so the mapping network's first-layer weight rows are
that stream's first vectors, and with ``mapping_lr_mul`` 0.01 they barely move in training. A z drawn
from the same seeded stream lies on one of those rows and maps to an outlier w (measured on the 129 kimg
state at psi 1: albedo means +18/+36/+52 % over the first 128 z of torch seed 0, within 1-3 % of the
data's over seed 0's vectors 512 on, other seeds, or the same vectors with their dimensions permuted;
docs/brdf_gan.md). torch keeps only the low 32 bits of a seed, so no offset escapes that; numpy's PCG64,
another algorithm keyed by a salt, shares no stream with any torch seed.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["sample_z"]

_SALT = 0xB2DF_6A17  # keys the evaluation streams apart from anything else seeded by a small integer


def sample_z(n: int, z_dim: int, seed: int, device: torch.device | str | None = None) -> torch.Tensor:
    """(n, z_dim) float32 z ~ N(0, I), deterministic in ``seed`` (any platform: PCG64 through numpy's
    SeedSequence), independent of every torch stream and of each other seed's."""
    if n < 0 or z_dim < 1:
        raise ValueError(f"sample_z: expected n >= 0 and z_dim >= 1, got n={n}, z_dim={z_dim}")
    rng = np.random.default_rng([_SALT, int(seed)])
    return torch.from_numpy(rng.standard_normal((n, z_dim), dtype=np.float32)).to(device)
