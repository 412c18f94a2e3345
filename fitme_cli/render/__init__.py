"""A differentiable CPU renderer: camera, rasteriser, texture lookup, Blinn-Phong shading with subsurface
scattering, shadows and SH ambient, silhouette antialiasing. Pure pip: torch plus a numba visibility pass."""

from .camera import Camera, focal_px_from_35mm, project
from .effects import Effects, EffectChoice, select_effects
from .lights import Lights
from .renderer import RenderOutput, Renderer, RenderSettings

__all__ = ["Camera", "focal_px_from_35mm", "project", "Effects", "EffectChoice", "select_effects", "Lights",
           "Renderer", "RenderOutput", "RenderSettings"]
