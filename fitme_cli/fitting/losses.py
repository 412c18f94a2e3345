"""The fitting's losses (FitMe Eq. 5-8) as plain functions. Each returns a (B,) tensor, one value per
photo, so several photos of a person can be weighted and reported separately."""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["landmark_loss", "photometric_loss", "mean_colour_loss", "identity_loss", "perceptual_loss", "w_prior", "flip_loss",
           "chromaticity_loss"]


def landmark_loss(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor, scale: torch.Tensor,
                  delta: float = 0.02) -> torch.Tensor:
    """Robust landmark distance. pred, target: (B, N, 2) pixels; weights: (N,) (e.g. lower on the jaw
    contour, whose landmarks slide along the outline); scale: (B,) the face size in pixels, so the loss
    means the same for a 100 px and a 2000 px face. Pseudo-Huber with knee ``delta`` (in face sizes):
    quadratic for small errors, linear for outliers (a misplaced landmark cannot dominate)."""
    if pred.shape != target.shape or pred.ndim != 3 or pred.shape[-1] != 2:
        raise ValueError(f"expected pred and target of the same shape (B, N, 2), got {tuple(pred.shape)} and {tuple(target.shape)}")
    d2 = ((pred - target) / scale[:, None, None]).square().sum(-1)  # (B, N)
    rho = delta**2 * (torch.sqrt(1 + d2 / delta**2) - 1)
    w = weights.to(pred.dtype)
    return (rho * w).sum(-1) / w.sum()


def photometric_loss(render: torch.Tensor, photo: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean L1 over the mask. render, photo: (B, 3, H, W) in the same space (sRGB [0, 1]); mask: (B, 1, H, W)."""
    if render.shape != photo.shape or mask.shape != (render.shape[0], 1, *render.shape[2:]):
        raise ValueError(f"photometric_loss: got render {tuple(render.shape)}, photo {tuple(photo.shape)}, mask {tuple(mask.shape)}")
    m = mask.to(render.dtype)
    return ((render - photo).abs() * m).sum(dim=(1, 2, 3)) / (3 * m.sum(dim=(1, 2, 3))).clamp(min=1.0)


def mean_colour_loss(render: torch.Tensor, photo: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """L1 between the mean colours of render and photo over the mask, averaged over the channels; 0 for
    an empty mask. render, photo: (B, 3, H, W) in the same space; mask: (B, 1, H, W) weights. Unlike
    ``photometric_loss`` it asks for a region's colour, not for its pixels to line up: the hair term's
    measure (fitting/invert.py)."""
    if render.shape != photo.shape or mask.shape != (render.shape[0], 1, *render.shape[2:]):
        raise ValueError(f"mean_colour_loss: got render {tuple(render.shape)}, photo {tuple(photo.shape)}, mask {tuple(mask.shape)}")
    m = mask.to(render.dtype)
    area = m.sum(dim=(1, 2, 3)).clamp(min=1.0)
    diff = ((render - photo) * m).sum(dim=(2, 3)) / area[:, None]  # (B, 3) mean colour difference
    return diff.abs().mean(-1)


def identity_loss(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """1 - cos(a, b) of identity descriptors (B, D)."""
    return 1 - F.cosine_similarity(a, b, dim=-1, eps=1e-8)


def perceptual_loss(feats_a: list[torch.Tensor], feats_b: list[torch.Tensor]) -> torch.Tensor:
    """Mean over layers of the mean squared difference of channel-normalised activations (the LPIPS
    recipe without its learned weights): each (B, C, H, W) pair."""
    if len(feats_a) != len(feats_b) or not feats_a:
        raise ValueError(f"perceptual_loss: expected two equal non-empty lists of features, got {len(feats_a)} and {len(feats_b)}")
    total = 0
    for a, b in zip(feats_a, feats_b):
        na = a * torch.rsqrt(a.square().sum(1, keepdim=True) + 1e-10)
        nb = b * torch.rsqrt(b.square().sum(1, keepdim=True) + 1e-10)
        total = total + (na - nb).square().sum(1).mean(dim=(1, 2))
    return total / len(feats_a)


def w_prior(ws: torch.Tensor, w_avg: torch.Tensor) -> torch.Tensor:
    """Mean squared distance of W (B, num_ws, w_dim) from the generator's W average (w_dim,)."""
    return (ws - w_avg).square().mean(dim=(1, 2))


def flip_loss(albedo: torch.Tensor, mapped: torch.Tensor) -> torch.Tensor:
    """L1 between the albedo (B, 3, R, R) and its mirror image, over the UV texels ``mapped`` (R, R) that
    map to the mesh: the UV layout is symmetric about u = 0.5, so this asks for a symmetric face."""
    m = (mapped & mapped.flip(-1)).to(albedo.dtype)
    return ((albedo - albedo.flip(-1)).abs() * m).sum(dim=(1, 2, 3)) / (3 * m.sum()).clamp(min=1.0)


def chromaticity_loss(albedo: torch.Tensor, reference: torch.Tensor, mapped: torch.Tensor) -> torch.Tensor:
    """L1 between the chromaticities (rgb / (r + g + b)) of the tuned albedo and the inverted one
    (B, 3, R, R): tuning may add shading detail, not change the skin's colour."""
    def chroma(x):
        return x / x.sum(1, keepdim=True).clamp(min=1e-4)

    m = mapped.to(albedo.dtype)
    return ((chroma(albedo) - chroma(reference)).abs() * m).sum(dim=(1, 2, 3)) / (3 * m.sum()).clamp(min=1.0)
