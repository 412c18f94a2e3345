"""Perspective pinhole cameras, batched over photos.

Frames: world = the shape model's frame (mm; x to the subject's left, y up, z out of the face).
Camera = OpenCV's (x right, y down, z forward into the scene), X_cam = R X_world + t. Pixels: (x, y)
with (0, 0) the top-left corner of the top-left pixel, so pixel (i, j) has its centre at (j + 0.5, i + 0.5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = ["DEFAULT_FOCAL_35MM", "Camera", "focal_px_from_35mm", "frontal_rotation", "project"]

# A phone's main camera is 24-28 mm (35 mm equivalent); without EXIF we assume 28 mm. A wrong focal
# mostly trades off against the subject's distance, so the fit stays good; the shape changes a little.
DEFAULT_FOCAL_35MM = 28.0
_FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


def focal_px_from_35mm(focal_35mm: float | None, width: int, height: int) -> float:
    """Focal length in pixels from a 35 mm equivalent focal length (EXIF FocalLengthIn35mmFilm), which
    is defined on the diagonal. ``None`` or a non-positive value uses DEFAULT_FOCAL_35MM."""
    f = focal_35mm if focal_35mm and focal_35mm > 0 else DEFAULT_FOCAL_35MM
    return float(f) * math.hypot(width, height) / _FULL_FRAME_DIAGONAL_MM


def frontal_rotation(batch: int = 1, dtype=torch.float32, device=None) -> torch.Tensor:
    """(B, 3, 3) rotation that shows the model's face to the camera: model y up -> image y down, model +z
    (out of the face) -> toward the camera (camera -z)."""
    return torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=dtype, device=device)).expand(batch, 3, 3).clone()


@dataclass(frozen=True)
class Camera:
    """One camera per batch element.

    focal: (B, 2) fx, fy in pixels; principal: (B, 2) cx, cy in pixels; rotation: (B, 3, 3); translation:
    (B, 3) mm; width, height: image size in pixels; near: mm, points closer than this are not drawn."""

    focal: torch.Tensor
    principal: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor
    width: int
    height: int
    near: float = 10.0

    def __post_init__(self) -> None:
        b = self.rotation.shape[0] if self.rotation.ndim == 3 else -1
        checks = ((self.focal, (b, 2), "focal"), (self.principal, (b, 2), "principal"),
                  (self.rotation, (b, 3, 3), "rotation"), (self.translation, (b, 3), "translation"))
        for t, shape, name in checks:
            if tuple(t.shape) != shape:
                raise ValueError(f"Camera.{name}: expected shape {shape}, got {tuple(t.shape)}")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"Camera: image size must be positive, got {self.width}x{self.height}")

    @property
    def batch(self) -> int:
        return self.rotation.shape[0]

    def with_size(self, width: int, height: int) -> Camera:
        """The same camera for an image scaled to width x height (intrinsics scaled)."""
        s = torch.tensor([width / self.width, height / self.height], dtype=self.focal.dtype, device=self.focal.device)
        return Camera(self.focal * s, self.principal * s, self.rotation, self.translation, width, height, self.near)

    @staticmethod
    def looking_at_face(batch: int, width: int, height: int, distance_mm: float = 500.0, focal_35mm: float | None = None,
                        dtype=torch.float32, device=None) -> Camera:
        """A frontal camera ``distance_mm`` from the model origin, principal point at the image centre."""
        f = focal_px_from_35mm(focal_35mm, width, height)
        kw = {"dtype": dtype, "device": device}
        return Camera(torch.tensor([[f, f]], **kw).expand(batch, 2).clone(),
                      torch.tensor([[width / 2, height / 2]], **kw).expand(batch, 2).clone(),
                      frontal_rotation(batch, **kw), torch.tensor([[0.0, 0.0, distance_mm]], **kw).expand(batch, 3).clone(),
                      width, height)


def to_camera(points: torch.Tensor, cam: Camera) -> torch.Tensor:
    """(B, N, 3) world mm -> (B, N, 3) camera mm."""
    return torch.einsum("bij,bnj->bni", cam.rotation.to(points.dtype), points) + cam.translation.to(points.dtype)[:, None]


def project(points: torch.Tensor, cam: Camera) -> torch.Tensor:
    """(B, N, 3) world mm -> (B, N, 3): pixel x, pixel y, camera depth z (mm). Points at z <= 0 get a
    finite but meaningless pixel position (the divisor is clamped); the rasteriser drops them by depth."""
    if points.ndim != 3 or points.shape[-1] != 3 or points.shape[0] != cam.batch:
        raise ValueError(f"project: expected points of shape ({cam.batch}, N, 3), got {tuple(points.shape)}")
    pc = to_camera(points, cam)
    z = pc[..., 2:3]
    zs = torch.where(z.abs() < 1e-6, torch.full_like(z, 1e-6), z)
    xy = pc[..., :2] / zs * cam.focal.to(points.dtype)[:, None] + cam.principal.to(points.dtype)[:, None]
    return torch.cat([xy, z], -1)
