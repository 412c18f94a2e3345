"""Scene lights: ambient, directional or point lights, and an optional order-2 spherical-harmonics
environment. Colours are linear RGB, unbounded (1 = a light that makes albedo-1 skin facing it white).
Directions and positions are in the world (shape model) frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

__all__ = ["Lights", "sh_basis", "single_colour_sh"]


@dataclass(frozen=True)
class Lights:
    """ambient: (B, 3); direction: (B, L, 3) unit vectors from the surface toward each light (directional
    lights; ignored where ``position`` is set); colour: (B, L, 3); position: (B, L, 3) mm or None, point
    lights with inverse-square falloff normalised at the world origin (``colour`` is what reaches the head
    centre); sh: (B, 9, 3) or None, irradiance coefficients of an environment on the SH basis
    ``sh_basis`` (used instead of ``ambient`` when the SH effect is on)."""

    ambient: torch.Tensor
    direction: torch.Tensor
    colour: torch.Tensor
    position: torch.Tensor | None = None
    sh: torch.Tensor | None = None

    def __post_init__(self) -> None:
        b = self.ambient.shape[0]
        n = self.direction.shape[1] if self.direction.ndim == 3 else -1
        checks = [(self.ambient, (b, 3), "ambient"), (self.direction, (b, n, 3), "direction"), (self.colour, (b, n, 3), "colour")]
        if self.position is not None:
            checks.append((self.position, (b, n, 3), "position"))
        if self.sh is not None:
            checks.append((self.sh, (b, 9, 3), "sh"))
        for t, shape, name in checks:
            if tuple(t.shape) != shape:
                raise ValueError(f"Lights.{name}: expected shape {shape}, got {tuple(t.shape)}")

    @property
    def count(self) -> int:
        return self.direction.shape[1]

    def first(self) -> Lights:
        """Only the first light (the single-light scene)."""
        return replace(self, direction=self.direction[:, :1], colour=self.colour[:, :1],
                       position=None if self.position is None else self.position[:, :1])

    @staticmethod
    def frontal(batch: int = 1, ambient: float = 0.35, intensity: float = 0.8, dtype=torch.float32, device=None) -> Lights:
        """A soft key light from the upper left front, plus ambient: a neutral default."""
        kw = {"dtype": dtype, "device": device}
        d = torch.nn.functional.normalize(torch.tensor([0.4, 0.5, 1.0], **kw), dim=0)
        sh = torch.zeros(batch, 9, 3, **kw)
        sh[:, 0] = ambient * 2 * math.sqrt(math.pi)  # the same constant ambient, as an SH environment
        sh[:, 2] = ambient * 0.3 * 2 * math.sqrt(math.pi / 3)  # a little brighter from above
        return Lights(torch.full((batch, 3), ambient, **kw), d.expand(batch, 1, 3).clone(),
                      torch.full((batch, 1, 3), intensity, **kw), sh=sh)


def sh_basis(n: torch.Tensor) -> torch.Tensor:
    """(..., 3) unit normals -> (..., 9) real SH basis Y_00, Y_1-1, Y_10, Y_11, Y_2-2, Y_2-1, Y_20, Y_21, Y_22."""
    x, y, z = n.unbind(-1)
    c0 = 0.5 / math.sqrt(math.pi)
    c1 = math.sqrt(3 / (4 * math.pi))
    c2 = 0.5 * math.sqrt(15 / math.pi)
    c3 = 0.25 * math.sqrt(5 / math.pi)
    c4 = 0.25 * math.sqrt(15 / math.pi)
    return torch.stack([torch.full_like(x, c0), c1 * y, c1 * z, c1 * x, c2 * x * y, c2 * y * z,
                        c3 * (3 * z * z - 1), c2 * x * z, c4 * (x * x - y * y)], -1)


def single_colour_sh(sh: torch.Tensor, eps: float = 1e-4) -> torch.Tensor:
    """(B, 9, 3) SH irradiance coefficients (linear RGB) -> the same environment in one colour: each
    coefficient's grey level (its mean over RGB) times band 0's chromaticity (its RGB over their mean,
    negative parts cut, ``eps`` added so that a black band 0 gives grey).

    Why: fitted freely, the 27 coefficients meet the photo only where the photometric mask is, the
    front of the face. Toward the silhouette and under the nose and jaw the three channels' separate
    extrapolations cross zero at different places, and the render turns green at the sides and magenta
    underneath (docs/fitting.md, "One colour for the SH environment"). A grey environment is unchanged;
    band 0 keeps its colour (up to ``eps``)."""
    if sh.ndim != 3 or tuple(sh.shape[1:]) != (9, 3):
        raise ValueError(f"single_colour_sh: expected (B, 9, 3) coefficients, got {tuple(sh.shape)}")
    c0 = sh[:, :1].clamp(min=0) + eps
    return sh.mean(-1, keepdim=True) * (c0 / c0.mean(-1, keepdim=True))
