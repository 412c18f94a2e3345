"""Self-shadowing: which vertices each light reaches, from a depth map rendered from the light
(orthographic along the light's direction). A mask, not differentiated: gradients flow through the
lit surfaces' shading, as in a shadow-mapped real-time renderer."""

from __future__ import annotations

import numpy as np
import torch

from .lights import Lights
from .raster import _visibility

__all__ = ["light_visibility"]


def light_visibility(vertices: torch.Tensor, faces: torch.Tensor, lights: Lights, resolution: int = 256,
                     bias_mm: float = 2.0) -> torch.Tensor:
    """(B, V, 3) world vertices -> (B, L, V) in [0, 1]: 1 lit, 0 in shadow (3x3 percentage-closer
    filtering softens the edge). Point lights use their direction from the head centre."""
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
