"""Shading as plain functions (FitMe Sec. 3.3, after AvatarMe++): Blinn-Phong in linear light.

Diffuse: A_D * (c_a + sum_j max(0, N_D . l_j) c_j). The paper's Eq. multiplies the ambient term into
the sum over lights; we add it instead, which is what an ambient light physically does (and what
renders a face lit only by ambient light as non-black). N_D are the mesh's smooth normals.
Specular: A_S * sum_j c_j max(0, N_S . h_j)^s, with N_S the GAN's detail normals in the mesh's tangent
frame, h_j the half vector, and no light reaching surfaces that face away from it (N_D . l_j <= 0).

Every function is finite with finite gradients for zero-length vectors, grazing angles, a light exactly
opposite the view (zero half vector) and shininess up to 1e4: normalisations use rsqrt(|x|^2 + eps) and
the power is exp(s log(max(x, tiny))).
"""

from __future__ import annotations

import torch

from ..ops.srgb import linear_to_srgb as _linear_to_srgb_torch
from ..ops.srgb import srgb_to_linear
from .lights import Lights, sh_basis

__all__ = ["safe_normalize", "light_vectors", "diffuse_irradiance", "specular_reflectance", "tangent_to_world",
           "mesh_smoothing_operator", "subsurface_scatter", "srgb_to_linear", "linear_to_srgb"]

_EPS = 1e-12


def safe_normalize(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """x / |x| along the last axis; the zero vector maps to zero with finite gradients."""
    return x * torch.rsqrt(x.square().sum(-1, keepdim=True) + eps)


def light_vectors(points: torch.Tensor, lights: Lights) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, N, 3) world points -> unit directions to each light (B, L, N, 3) and the colour reaching
    each point (B, L, N, 3): point lights fall off with the inverse square, normalised at the origin."""
    b, n, _ = points.shape
    colour = lights.colour.to(points.dtype)[:, :, None, :]
    if lights.position is None:
        d = safe_normalize(lights.direction.to(points.dtype))[:, :, None, :].expand(b, lights.count, n, 3)
        return d, colour.expand(b, lights.count, n, 3)
    pos = lights.position.to(points.dtype)
    v = pos[:, :, None, :] - points[:, None]
    dist2 = v.square().sum(-1, keepdim=True).clamp(min=1.0)
    ref2 = pos.square().sum(-1)[:, :, None, None].clamp(min=1.0)
    return safe_normalize(v), colour * (ref2 / dist2)


def diffuse_irradiance(normals: torch.Tensor, points: torch.Tensor, lights: Lights, use_sh: bool = False,
                       visibility: torch.Tensor | None = None) -> torch.Tensor:
    """(B, N, 3) smooth normals and points -> (B, N, 3) c_a + sum_j max(0, n . l_j) c_j (linear RGB).
    ``use_sh``: the ambient term is the SH environment's irradiance instead of the constant c_a.
    ``visibility``: (B, L, N) in [0, 1], shadowing of each light (None: unshadowed)."""
    n = safe_normalize(normals)
    if use_sh:
        if lights.sh is None:
            raise ValueError("the SH ambient effect is on but the lights have no sh coefficients")
        e = torch.einsum("bnk,bkc->bnc", sh_basis(n), lights.sh.to(n.dtype)).clamp(min=0)
    else:
        e = lights.ambient.to(n.dtype)[:, None, :].expand_as(n)
    if lights.count == 0:
        return e
    d, c = light_vectors(points, lights)
    cos = (n[:, None] * d).sum(-1, keepdim=True).clamp(min=0)  # (B, L, N, 1)
    if visibility is not None:
        cos = cos * visibility[..., None].to(cos.dtype)
    return e + (cos * c).sum(1)


def specular_reflectance(detail_normals: torch.Tensor, smooth_normals: torch.Tensor, points: torch.Tensor,
                         eye: torch.Tensor, lights: Lights, shininess: torch.Tensor | float,
                         visibility: torch.Tensor | None = None) -> torch.Tensor:
    """sum_j c_j max(0, N_S . h_j)^s [N_D . l_j > 0] (B, N, 3), to be multiplied by A_S.

    detail_normals, smooth_normals, points: (B, N, 3); eye: (B, 3) camera centre (world mm);
    shininess: float or (B, N, 1); visibility: (B, L, N) or None."""
    ns = safe_normalize(detail_normals)
    nd = safe_normalize(smooth_normals)
    v = safe_normalize(eye.to(points.dtype)[:, None, :] - points)  # (B, N, 3)
    d, c = light_vectors(points, lights)
    h = safe_normalize(d + v[:, None])  # zero when the light is exactly behind the surface, seen head-on
    ndh = (ns[:, None] * h).sum(-1, keepdim=True).clamp(min=_EPS, max=1.0)
    s = shininess if isinstance(shininess, float) else shininess[:, None]
    lobe = torch.exp(s * torch.log(ndh))  # ndh^s without pow's inf gradient at 0
    facing = ((nd[:, None] * d).sum(-1, keepdim=True) > 0).to(lobe.dtype)
    if visibility is not None:
        facing = facing * visibility[..., None].to(lobe.dtype)
    return (lobe * facing * c).sum(1)


def tangent_to_world(n_ts: torch.Tensor, tangent: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """(..., 3) tangent-space normals (+x along u, +y along v, +z out) -> (..., 3) unit world normals.
    tangent: (..., 4) with w the bitangent sign (glTF), normal: (..., 3)."""
    nrm = safe_normalize(normal)
    t = safe_normalize(tangent[..., :3] - nrm * (tangent[..., :3] * nrm).sum(-1, keepdim=True))
    bt = torch.cross(nrm, t, dim=-1) * tangent[..., 3:4]
    return safe_normalize(n_ts[..., 0:1] * t + n_ts[..., 1:2] * bt + n_ts[..., 2:3] * nrm)


def mesh_smoothing_operator(faces: torch.Tensor, n_vertices: int) -> torch.Tensor:
    """(V, V) sparse row-stochastic matrix: each vertex averaged with its 1-ring (self included)."""
    f = faces.long()
    i = torch.cat([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0], torch.arange(n_vertices)])
    j = torch.cat([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2], torch.arange(n_vertices)])
    a = torch.sparse_coo_tensor(torch.stack([i, j]), torch.ones(len(i)), (n_vertices, n_vertices),
                                check_invariants=False).coalesce()
    idx = a.indices()
    deg = torch.bincount(idx[0], minlength=n_vertices).float()  # duplicates were summed: count entries
    coo = torch.sparse_coo_tensor(idx, 1.0 / deg[idx[0]], a.shape, check_invariants=False).coalesce()
    from ..ops.sparse import to_csr

    return to_csr(coo)  # CSR: ~10x faster than COO in sparse.mm on the CPU


def subsurface_scatter(irradiance: torch.Tensor, operator: torch.Tensor | tuple[torch.Tensor, torch.Tensor],
                       steps: tuple[int, int, int], weights: tuple[float, float, float]) -> torch.Tensor:
    """Subsurface scattering as a per-channel blur of the diffuse irradiance over the skin surface
    (texture-space diffusion, done on the mesh graph: same idea, no texture-sized pass). Channel c
    becomes (1 - w_c) E_c + w_c S^{k_c} E_c, with S the 1-ring average; red spreads widest.
    irradiance: (B, V, 3) -> (B, V, 3). ``operator``: S, or (S, S^T) for a faster backward."""
    b, v, _ = irradiance.shape
    if isinstance(operator, tuple):
        from ..ops.sparse import sparse_apply

        op, op_t = operator

        def apply(x):
            return sparse_apply(op, op_t, x)
    else:
        op = operator.to(irradiance.dtype)

        def apply(x):
            return op @ x
    e = irradiance.permute(1, 0, 2).reshape(v, b * 3)  # (V, B*3): all channels share the steps
    level = {0: e}
    cur = e
    for k in range(1, max(steps) + 1):
        cur = apply(cur)
        level[k] = cur
    w = torch.tensor(weights, dtype=e.dtype, device=e.device)
    blurred = torch.stack([level[steps[c]].view(v, b, 3)[..., c] for c in range(3)], -1)  # (V, B, 3)
    out = (1 - w) * e.view(v, b, 3) + w * blurred
    return out.permute(1, 0, 2)


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Linear [0, inf) -> sRGB [0, 1] (clipped), with finite gradients at 0. CPU float tensors take one
    numba loop each way (``_kernels.srgb_encode``); ``_linear_to_srgb_torch`` (``ops.srgb``) is its
    reference. ``srgb_to_linear`` is ``ops.srgb``'s, re-exported."""
    if x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64):
        from ._kernels import srgb_encode

        return srgb_encode(x)
    return _linear_to_srgb_torch(x)
