"""A slow, obvious reference renderer for tiny meshes, to test ``Renderer`` against.

Everything is written out plainly, one pixel at a time, with none of the renderer's machinery (no numba
visibility pass, no gather tables, no grid_sample, no antialiasing, no subsurface scattering, no
shadows, no SH):

1. project every vertex with the pinhole formula x = fx X_c / Z_c + cx, X_c = R X + t;
2. for every pixel centre, test every triangle (edge functions, edges inclusive; drop triangles with a
   vertex nearer than the near plane, zero-area ones and, when culling, back-facing ones: signed area
   (b - a) x (c - a) > 0 in y-down pixel coordinates) and keep the nearest (perspective-correct depth);
3. perspective-correct barycentrics: screen-space weights divided by each corner's depth, renormalised;
4. diffuse: per-vertex irradiance ambient + sum_j max(0, n . l_j) c_j (point lights: l_j toward the
   light, c_j scaled by |p_j|^2 / |p_j - x|^2), interpolated, times the bilinearly looked-up albedo;
5. specular: the detail normal from the normal map in the interpolated tangent frame (Gram-Schmidt
   tangent, bitangent N x T times the handedness), Blinn-Phong A_S sum_j c_j max(0, N_S . h_j)^s,
   only for lights the smooth normal faces (N . l_j > 0).

It is torch code, so autograd differentiates it (with the visibility held fixed, as in the renderer).
Minutes per image beyond ~64x64 pixels and ~100 triangles: tests only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..reflectance.maps import ReflectanceMaps
from .camera import Camera
from .lights import Lights

__all__ = ["ReferenceOutput", "reference_render"]


@dataclass(frozen=True)
class ReferenceOutput:
    """linear: (B, 3, H, W) diffuse + specular, background 0; diffuse, specular: (B, 3, H, W); mask:
    (B, H, W) bool; triangle: (B, H, W) int64, -1 on the background."""

    linear: torch.Tensor
    diffuse: torch.Tensor
    specular: torch.Tensor
    mask: torch.Tensor
    triangle: torch.Tensor


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / torch.sqrt((x * x).sum())


def _bilinear(texture: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """(C, Ht, Wt) texture, row 0 at v = 1, texel centres at (k + 1/2) / size, clamped to the border."""
    _, h, w = texture.shape
    x = (u * w - 0.5).clamp(0, w - 1)
    y = ((1 - v) * h - 0.5).clamp(0, h - 1)
    x0, y0 = int(math.floor(float(x.detach()))), int(math.floor(float(y.detach())))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * texture[:, y0, x0] + fx * (1 - fy) * texture[:, y0, x1]
            + (1 - fx) * fy * texture[:, y1, x0] + fx * fy * texture[:, y1, x1])


def _light_at(lights: Lights, k: int, j: int, point: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit direction toward light j and the colour reaching ``point`` (batch element k)."""
    colour = lights.colour[k, j].to(point.dtype)
    if lights.position is None:
        return _unit(lights.direction[k, j].to(point.dtype)), colour
    pos = lights.position[k, j].to(point.dtype)
    to_light = pos - point
    dist2 = torch.clamp((to_light * to_light).sum(), min=1.0)
    ref2 = torch.clamp((pos * pos).sum(), min=1.0)
    return _unit(to_light), colour * ref2 / dist2


def _signed_area(a, b, c) -> float:
    return (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1])


def reference_render(vertices: torch.Tensor, normals: torch.Tensor, tangents: torch.Tensor, faces: torch.Tensor,
                     uv: torch.Tensor, uv_faces: torch.Tensor, maps: ReflectanceMaps, camera: Camera, lights: Lights,
                     shininess: float = 30.0, specular: bool = True, cull_backfaces: bool = True) -> ReferenceOutput:
    """vertices, normals: (B, V, 3) world; tangents: (B, V, 4); faces, uv_faces: (F, 3); uv: (Vt, 2);
    maps: (B or 1, ., R, R). Every light in ``lights`` is used (the renderer's ``multi_light``)."""
    bsz = vertices.shape[0]
    h, w = camera.height, camera.width
    dtype = vertices.dtype
    faces_l, uv_faces_l = faces.tolist(), uv_faces.tolist()
    linear = torch.zeros(bsz, 3, h, w, dtype=dtype)
    diffuse_img = torch.zeros(bsz, 3, h, w, dtype=dtype)
    spec_img = torch.zeros(bsz, 3, h, w, dtype=dtype)
    mask = torch.zeros(bsz, h, w, dtype=torch.bool)
    tri_img = torch.full((bsz, h, w), -1, dtype=torch.int64)
    for k in range(bsz):
        m = 0 if maps.albedo.shape[0] == 1 else k
        albedo, spec_map, normal_map = maps.albedo[m].to(dtype), maps.specular[m].to(dtype), maps.normals[m].to(dtype)
        rot, trans = camera.rotation[k].to(dtype), camera.translation[k].to(dtype)
        fx, fy = camera.focal[k].to(dtype)
        cx, cy = camera.principal[k].to(dtype)

        # 1. projection
        proj = []
        for x in vertices[k]:
            xc = rot @ x + trans
            proj.append(torch.stack([fx * xc[0] / xc[2] + cx, fy * xc[1] / xc[2] + cy, xc[2]]))
        pf = [[float(c) for c in p.detach()] for p in proj]  # plain floats for the visibility search

        # 4a. per-vertex diffuse irradiance
        irradiance = []
        for x, n in zip(vertices[k], normals[k]):
            n = _unit(n)
            e = lights.ambient[k].to(dtype)
            for j in range(lights.count):
                l_dir, c = _light_at(lights, k, j, x)
                e = e + torch.clamp((n * l_dir).sum(), min=0) * c
            irradiance.append(e)

        eye = -rot.T @ trans  # camera centre in the world
        for i in range(h):
            for jj in range(w):
                qx, qy = jj + 0.5, i + 0.5
                # 2. nearest covering triangle
                best, best_f = math.inf, -1
                for f, (a, b, c) in enumerate(faces_l):
                    pa, pb, pc = pf[a], pf[b], pf[c]
                    if min(pa[2], pb[2], pc[2]) < camera.near:
                        continue
                    area = _signed_area(pa, pb, pc)
                    if area == 0 or (cull_backfaces and area > 0):
                        continue
                    l0 = _signed_area((qx, qy), pb, pc) / area
                    l1 = _signed_area(pa, (qx, qy), pc) / area
                    l2 = 1 - l0 - l1
                    if l0 < 0 or l1 < 0 or l2 < 0:
                        continue
                    z = 1 / (l0 / pa[2] + l1 / pb[2] + l2 / pc[2])
                    if z < best:
                        best, best_f = z, f
                if best_f < 0:
                    continue
                mask[k, i, jj] = True
                tri_img[k, i, jj] = best_f
                a, b, c = faces_l[best_f]
                ta, tb, tc = uv_faces_l[best_f]
                pa, pb, pc = proj[a], proj[b], proj[c]

                # 3. perspective-correct barycentrics (differentiable in the projected vertices)
                area = _signed_area(pa, pb, pc)
                q = torch.tensor([qx, qy], dtype=dtype)
                lam = torch.stack([_signed_area(q, pb, pc) / area, _signed_area(pa, q, pc) / area])
                lam = torch.cat([lam, 1 - lam.sum(0, keepdim=True)])
                wgt = lam / torch.stack([pa[2], pb[2], pc[2]])
                wgt = wgt / wgt.sum()

                uv_p = wgt[0] * uv[ta].to(dtype) + wgt[1] * uv[tb].to(dtype) + wgt[2] * uv[tc].to(dtype)
                e_p = wgt[0] * irradiance[a] + wgt[1] * irradiance[b] + wgt[2] * irradiance[c]
                diffuse = _bilinear(albedo, uv_p[0], uv_p[1]) * e_p
                colour = diffuse
                diffuse_img[k, :, i, jj] = diffuse
                if specular:
                    # 5. Blinn-Phong with the detail normal in the tangent frame
                    vk = vertices[k]
                    point = wgt[0] * vk[a] + wgt[1] * vk[b] + wgt[2] * vk[c]
                    nrm = _unit(wgt[0] * normals[k, a] + wgt[1] * normals[k, b] + wgt[2] * normals[k, c])
                    tan4 = wgt[0] * tangents[k, a] + wgt[1] * tangents[k, b] + wgt[2] * tangents[k, c]
                    t = _unit(tan4[:3] - nrm * (tan4[:3] * nrm).sum())
                    bt = torch.linalg.cross(nrm, t) * tan4[3]
                    ts = _bilinear(normal_map, uv_p[0], uv_p[1])
                    n_detail = _unit(ts[0] * t + ts[1] * bt + ts[2] * nrm)
                    view = _unit(eye - point)
                    a_s = _bilinear(spec_map, uv_p[0], uv_p[1])[0]
                    s = torch.zeros(3, dtype=dtype)
                    for j in range(lights.count):
                        l_dir, c_l = _light_at(lights, k, j, point)
                        if float((nrm * l_dir).sum().detach()) <= 0:
                            continue
                        half = _unit(l_dir + view)
                        s = s + c_l * torch.clamp((n_detail * half).sum(), min=0, max=1) ** shininess
                    spec = a_s * s
                    spec_img[k, :, i, jj] = spec
                    colour = colour + spec
                linear[k, :, i, jj] = colour
    return ReferenceOutput(linear, diffuse_img, spec_img, mask, tri_img)
