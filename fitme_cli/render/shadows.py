"""Self-shadowing: which vertices each light reaches, from a depth map rendered from the light
(orthographic along the light's direction). A mask, not differentiated: gradients flow through the
lit surfaces' shading, as in a shadow-mapped real-time renderer."""

from __future__ import annotations

import numba
import numpy as np
import torch

from .lights import Lights
from .raster import _raster_kernel, _visibility

__all__ = ["light_visibility"]


def light_visibility(vertices: torch.Tensor, faces: torch.Tensor, lights: Lights, resolution: int = 256,
                     bias_mm: float = 2.0) -> torch.Tensor:
    """(B, V, 3) world vertices -> (B, L, V) in [0, 1]: 1 lit, 0 in shadow (3x3 percentage-closer
    filtering softens the edge). Point lights use their direction from the head centre.
    One numba pass per (image, light) (``_shadow_passes``); ``_light_visibility_ref``
    is the step-by-step version the tests compare it with."""
    if vertices.ndim != 3 or vertices.shape[-1] != 3:
        raise ValueError(f"light_visibility: expected vertices of shape (B, V, 3), got {tuple(vertices.shape)}")
    from ._kernels import _buffer

    v = vertices.detach().to("cpu", torch.float64).contiguous().numpy()
    bases = _light_bases(lights).numpy()
    out = _buffer((v.shape[0], lights.count, v.shape[1]), np.float64)
    _shadow_passes(v, bases, faces.detach().cpu().numpy().astype(np.int64), resolution, bias_mm, out)
    return torch.from_numpy(out).to(vertices.dtype).to(vertices.device)


def _light_bases(lights: Lights) -> torch.Tensor:
    """(B, L, 3, 3) float64 rows u, w, d: the shadow map's x and y axes and the direction to the light."""
    src = lights.position if lights.position is not None else lights.direction
    d = torch.nn.functional.normalize(src.detach().to("cpu", torch.float64), dim=-1)
    helper = torch.where((d[..., 1:2].abs() < 0.9), torch.tensor([0.0, 1.0, 0.0], dtype=d.dtype),
                         torch.tensor([1.0, 0.0, 0.0], dtype=d.dtype))
    u = torch.nn.functional.normalize(torch.cross(helper, d, dim=-1), dim=-1)
    w = torch.cross(d, u, dim=-1)
    return torch.stack([u, w, d], -2)


@numba.njit(cache=True, nogil=True)
def _shadow_pass(v, basis, faces, resolution, bias, lit):
    """One light: orthographic depth map along basis[2] (nearer the light = smaller), then each
    vertex's 3x3 PCF test against it. v (V, 3); lit (V,) written."""
    n = v.shape[0]
    px = np.empty((n, 3))
    for i in range(n):
        px[i, 0] = v[i, 0] * basis[0, 0] + v[i, 1] * basis[0, 1] + v[i, 2] * basis[0, 2]
        px[i, 1] = v[i, 0] * basis[1, 0] + v[i, 1] * basis[1, 1] + v[i, 2] * basis[1, 2]
        px[i, 2] = -(v[i, 0] * basis[2, 0] + v[i, 1] * basis[2, 1] + v[i, 2] * basis[2, 2])
    lo = min(px[:, 0].min(), px[:, 1].min()) - 1
    hi = max(px[:, 0].max(), px[:, 1].max()) + 1
    scale = (resolution - 1) / (hi - lo)
    zmin = px[:, 2].min()
    for i in range(n):
        px[i, 0] = (px[i, 0] - lo) * scale
        px[i, 1] = (px[i, 1] - lo) * scale
        px[i, 2] = px[i, 2] - zmin + 100.0
    tri = np.full((resolution, resolution), -1, np.int64)
    depth = np.full((resolution, resolution), np.inf)
    _raster_kernel(px, faces, resolution, resolution, 0.0, False, tri, depth)
    for i in range(n):
        ci = min(max(int(np.floor(px[i, 1])), 0), resolution - 1)
        cj = min(max(int(np.floor(px[i, 0])), 0), resolution - 1)
        hits = 0
        for di in range(-1, 2):
            for dj in range(-1, 2):
                a = min(max(ci + di, 0), resolution - 1)
                b = min(max(cj + dj, 0), resolution - 1)
                if px[i, 2] <= depth[a, b] + bias:
                    hits += 1
        lit[i] = hits / 9.0


@numba.njit(cache=True, nogil=True)
def _shadow_passes(v, bases, faces, resolution, bias, out):
    nb, nl = bases.shape[0], bases.shape[1]
    for k in range(nb * nl):
        b, j = k // nl, k % nl
        _shadow_pass(v[b], bases[b, j], faces, resolution, bias, out[b, j])


def _light_visibility_ref(vertices: torch.Tensor, faces: torch.Tensor, lights: Lights, resolution: int = 256,
                          bias_mm: float = 2.0) -> torch.Tensor:
    """The same, step by step in torch and numpy (the tests' reference)."""
    v = vertices.detach().to("cpu", torch.float64)
    b, n, _ = v.shape
    if lights.position is not None:
        dirs = torch.nn.functional.normalize(lights.position.detach().to("cpu", torch.float64), dim=-1)
    else:
        dirs = torch.nn.functional.normalize(lights.direction.detach().to("cpu", torch.float64), dim=-1)
    f = faces.detach().cpu().numpy().astype(np.int64)
    out = torch.ones(b, lights.count, n, dtype=vertices.dtype)
    for k in range(b):
        for j in range(lights.count):
            d = dirs[k, j]
            helper = torch.tensor([0.0, 1.0, 0.0], dtype=d.dtype) if abs(float(d[1])) < 0.9 else torch.tensor([1.0, 0.0, 0.0], dtype=d.dtype)
            u = torch.nn.functional.normalize(torch.cross(helper, d, dim=0), dim=0)
            w = torch.cross(d, u, dim=0)
            x, y = v[k] @ u, v[k] @ w
            z = -(v[k] @ d)  # smaller = nearer the light
            lo = torch.minimum(x.min(), y.min()) - 1
            hi = torch.maximum(x.max(), y.max()) + 1
            scale = (resolution - 1) / float(hi - lo)
            px = torch.stack([(x - lo) * scale, (y - lo) * scale, z - z.min() + 100.0], 1).numpy()[None]
            _, depth = _visibility(px, f, resolution, resolution, 0.0, False, return_depth=True)
            depth = depth[0]
            ci = np.clip(np.floor(px[0, :, 1]).astype(int), 0, resolution - 1)
            cj = np.clip(np.floor(px[0, :, 0]).astype(int), 0, resolution - 1)
            lit = np.zeros(n)
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    dd = depth[np.clip(ci + di, 0, resolution - 1), np.clip(cj + dj, 0, resolution - 1)]
                    lit += px[0, :, 2] <= dd + bias_mm
            out[k, j] = torch.from_numpy(lit / 9.0).to(vertices.dtype)
    return out.to(vertices.device)
