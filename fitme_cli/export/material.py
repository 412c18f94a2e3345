"""The exported material: our Blinn-Phong skin model (diffuse albedo A_D, specular albedo A_S, a global
shininess s, tangent-space detail normals) expressed in glTF's metallic-roughness PBR and in MTL.

Matching the specular lobe (derivation in docs/export.md): Blinn-Phong with exponent s has about the
width of a GGX/Beckmann lobe with alpha^2 = 2 / (s + 2); glTF's roughness is sqrt(alpha). With a light
scaled so that diffuse = A_D * c * (n . l) in both models, the peaks at normal incidence agree when
F0 = 4 alpha^2 A_S. KHR_materials_specular gives F0 = min(0.04 * specularColor, 1) * specular, so the
specular albedo goes into ``specularColorTexture`` (grey) and ``specularColorFactor`` carries
4 alpha^2 / 0.04 (6.25 for s = 30, the renderer's default: F0 = 0.025 for the average A_S of 0.1, close
to skin's measured 0.028). The colour texture rather than ``specularTexture`` (the A channel, a
strength): Blender 3.4's importer ignores the latter and would make every texel as glossy as the
factor alone says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Material"]

_DIELECTRIC_F0 = 0.04  # glTF's F0 for IOR 1.5, the base KHR_materials_specular scales


@dataclass(frozen=True)
class Material:
    """shininess: the Blinn-Phong exponent the avatar was fitted with (``RenderSettings.shininess``)."""

    shininess: float = 30.0
    name: str = "fitme_skin"

    def __post_init__(self) -> None:
        if not 1.0 <= self.shininess <= 1e4:
            raise ValueError(f"shininess must be in [1, 1e4], got {self.shininess!r}")

    @property
    def alpha_squared(self) -> float:
        return 2.0 / (self.shininess + 2.0)

    @property
    def roughness(self) -> float:
        """glTF perceptual roughness: sqrt(alpha), alpha = sqrt(2 / (s + 2))."""
        return math.sqrt(math.sqrt(self.alpha_squared))

    @property
    def specular_colour_factor(self) -> float:
        """F0 per unit specular albedo, over glTF's dielectric 0.04."""
        return 4.0 * self.alpha_squared / _DIELECTRIC_F0
