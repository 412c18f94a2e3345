"""The reflectance maps as one typed record: what BRDF-GAN produces and the renderer consumes."""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["ReflectanceMaps"]


@dataclass(frozen=True)
class ReflectanceMaps:
    """Physical UV maps in the shape model's layout, (B, C, R, R) float, row 0 at v = 1:
    albedo: linear diffuse albedo A_D in [0, 1] (3 ch); specular: linear specular albedo A_S in [0, 1]
    (1 ch); normals: unit tangent-space detail normals N_S (3 ch; +x along u, +y along v (up), +z out)."""

    albedo: torch.Tensor
    specular: torch.Tensor
    normals: torch.Tensor

    def __post_init__(self) -> None:
        for name, c in (("albedo", 3), ("specular", 1), ("normals", 3)):
            t = getattr(self, name)
            if t.ndim != 4 or t.shape[1] != c:
                raise ValueError(f"ReflectanceMaps.{name}: expected shape (B, {c}, H, W), got {tuple(t.shape)}")
