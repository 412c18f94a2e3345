"""The differentiable renderer: rasterise, interpolate, look up the maps, shade, antialias, encode.

Diffuse irradiance (lights, SH ambient, shadows, subsurface scattering) is computed per vertex from the
smooth normals and interpolated: the head mesh has about one vertex per image pixel at 256^2, and every
diffuse effect then costs O(V), not O(pixels). The specular term is per pixel, with the detail normals.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from ..reflectance.maps import ReflectanceMaps
from ._kernels import specular_pixels
from .antialias import antialias, face_adjacency
from .camera import Camera, project
from .effects import Effects
from .lights import Lights
from .raster import Fragments, barycentrics, interpolate, rasterize, scatter_image
from .shading import (diffuse_irradiance, linear_to_srgb, mesh_smoothing_operator, safe_normalize,
                      specular_reflectance, subsurface_scatter, tangent_to_world)
from .shadows import light_visibility

__all__ = ["RenderSettings", "RenderOutput", "Renderer"]


@dataclass(frozen=True)
class RenderSettings:
    shininess: float = 30.0  # Blinn-Phong exponent when no per-texel map is given
    sss_steps: tuple[int, int, int] = (6, 2, 1)  # 1-ring averaging steps per channel (red widest)
    sss_weights: tuple[float, float, float] = (0.7, 0.4, 0.2)  # share of the blurred irradiance per channel
    antialias: bool = True
    cull_backfaces: bool = True
    shadow_resolution: int = 128  # shadow-map side: 1.6 mm texels over a head; 256 costs 4x (15 vs 4 ms for 3 lights)
    components: bool = False  # also return the diffuse and specular images (diagnostics; costs ~15 %)


@dataclass(frozen=True)
class RenderOutput:
    """image: (B, 3, H, W) sRGB [0, 1]; linear: (B, 3, H, W) linear radiance; mask: (B, 1, H, W) 1 where the
    mesh covers the pixel centre; diffuse, specular: (B, 3, H, W) linear components when
    ``RenderSettings.components`` (specular also None when off); depth: (B, H, W) mm, inf on the background; fragments: the visibility pass."""

    image: torch.Tensor
    linear: torch.Tensor
    mask: torch.Tensor
    diffuse: torch.Tensor | None
    specular: torch.Tensor | None
    depth: torch.Tensor
    fragments: Fragments


class Renderer(nn.Module):
    """Holds the mesh topology (triangles, UVs) and what is derived from it once (adjacency for
    antialiasing, the smoothing operator for subsurface scattering)."""

    def __init__(self, faces: torch.Tensor, uv: torch.Tensor, uv_faces: torch.Tensor, n_vertices: int,
                 settings: RenderSettings = RenderSettings()):
        super().__init__()
        if faces.shape != uv_faces.shape or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces and uv_faces must both be (F, 3), got {tuple(faces.shape)} and {tuple(uv_faces.shape)}")
        self.settings = settings
        self.n_vertices = n_vertices
        self.register_buffer("faces", faces.long())
        self.register_buffer("uv", uv.float())
        self.register_buffer("uv_faces", uv_faces.long())
        self.register_buffer("adjacency", face_adjacency(faces))
        self._smooth = mesh_smoothing_operator(faces, n_vertices)
        from ..ops.sparse import to_csr

        self._smooth_t = to_csr(self._smooth.to_sparse_coo().t())
        self._smooth_cache: dict = {}

    @staticmethod
    def for_shape_model(shape_model, settings: RenderSettings = RenderSettings()) -> Renderer:
        return Renderer(shape_model.triangles, shape_model.uv, shape_model.uv_faces, shape_model.mean.shape[0], settings)

    def _smoothing(self, dtype, device):
        key = (dtype, device)
        if key not in self._smooth_cache:
            self._smooth_cache[key] = (self._smooth.to(device=device, dtype=dtype), self._smooth_t.to(device=device, dtype=dtype))
        return self._smooth_cache[key]

    def forward(self, vertices: torch.Tensor, normals: torch.Tensor, tangents: torch.Tensor, maps: ReflectanceMaps,
                camera: Camera, lights: Lights, effects: Effects = Effects(), shininess_map: torch.Tensor | None = None,
                background: torch.Tensor | None = None) -> RenderOutput:
        """vertices, normals: (B, V, 3) world (mm, unit); tangents: (B, V, 4); maps: (B, ., R, R) or batch 1
        (shared); background: (B, 3, H, W) linear (e.g. the photo) or None for black; shininess_map:
        (B, 1, R, R) or None for the global ``settings.shininess``."""
        s = self.settings
        b, v = vertices.shape[:2]
        for t, name, last in ((vertices, "vertices", 3), (normals, "normals", 3), (tangents, "tangents", 4)):
            if t.ndim != 3 or t.shape[0] != b or t.shape[1] != self.n_vertices or t.shape[2] != last:
                raise ValueError(f"Renderer: expected {name} of shape (B, {self.n_vertices}, {last}), got {tuple(t.shape)}")
        if camera.batch != b or lights.ambient.shape[0] != b:
            raise ValueError(f"Renderer: batch sizes differ: vertices {b}, camera {camera.batch}, lights {lights.ambient.shape[0]}")
        h, w = camera.height, camera.width
        dtype = vertices.dtype

        px = project(vertices, camera)
        frags = rasterize(px, self.faces, h, w, camera.near, s.cull_backfaces)
        bary = barycentrics(px, self.faces, frags)
        used = lights if effects.multi_light else lights.first()

        vis = light_visibility(vertices, self.faces, used, s.shadow_resolution) if effects.shadows and used.count else None
        irr = diffuse_irradiance(normals, vertices, used, use_sh=effects.sh_ambient, visibility=vis)  # (B, V, 3)
        if effects.subsurface:
            irr = subsurface_scatter(irr, self._smoothing(dtype, vertices.device), s.sss_steps, s.sss_weights)
        per_vertex = [irr, px[..., 2:3]]
        if effects.specular:
            per_vertex += [vertices, normals, tangents]
        attrs = interpolate(torch.cat(per_vertex, -1), self.faces, frags, bary)  # (N, C)
        uv = interpolate(self.uv.to(dtype), self.uv_faces, frags, bary)  # (N, 2)

        texture = [maps.albedo]
        if effects.specular:
            texture += [maps.specular, maps.normals]
            if shininess_map is not None:
                texture.append(shininess_map)
        tex = self._lookup([t.to(dtype) for t in texture], uv, frags.index[:, 0], b)  # (N, C)

        e_pix, z_pix = attrs[:, 0:3], attrs[:, 3]
        diffuse = tex[:, 0:3] * e_pix
        colour = diffuse
        spec = None
        if effects.specular:
            p, nrm, tan = attrs[:, 4:7], attrs[:, 7:10], attrs[:, 10:14]
            eye = -torch.einsum("bji,bj->bi", camera.rotation.to(dtype), camera.translation.to(dtype))  # centre = -R^T t
            shin = tex[:, 7:8] if shininess_map is not None else s.shininess
            pvis = None
            if vis is not None:  # per-vertex light visibility, interpolated: (N, L)
                pvis = interpolate(vis.permute(0, 2, 1), self.faces, frags, bary)
            if vertices.device.type == "cpu" and used.position is None and used.count:  # fused loop; the branches below are its reference
                shin_px = tex[:, 7] if shininess_map is not None else torch.tensor([s.shininess], dtype=dtype)
                spec = specular_pixels(tex[:, 4:7], nrm, tan, p, eye, safe_normalize(used.direction.to(dtype)),
                                       used.colour.to(dtype), shin_px, pvis, frags.index[:, 0])
            elif b == 1:  # one image: the pixels are one batch of points, no per-pixel copies of the lights
                n_detail = tangent_to_world(tex[:, 4:7], tan, nrm)
                spec = specular_reflectance(n_detail[None], nrm[None], p[None], eye, used,
                                            shin if isinstance(shin, float) else shin[None],
                                            None if pvis is None else pvis.T[None])[0]
            else:  # each pixel its own batch element, with its image's lights
                n_detail = tangent_to_world(tex[:, 4:7], tan, nrm)
                bi = frags.index[:, 0]
                per_pixel = Lights(used.ambient[bi], used.direction[bi], used.colour[bi],
                                   None if used.position is None else used.position[bi], None)
                spec = specular_reflectance(n_detail[:, None], nrm[:, None], p[:, None], eye[bi], per_pixel,
                                            shin if isinstance(shin, float) else shin[:, None],
                                            None if pvis is None else pvis[:, :, None])[:, 0]
            spec = tex[:, 3:4] * spec
            colour = colour + spec

        bg = background.to(dtype).permute(0, 2, 3, 1) if background is not None else None
        linear = self._to_image(colour, frags, bg)
        depth = torch.full((b, h, w), float("inf"), dtype=dtype, device=vertices.device)
        depth = depth.index_put((frags.index[:, 0], frags.index[:, 1], frags.index[:, 2]), z_pix)
        if s.antialias:
            linear = antialias(linear, frags, px, self.faces, self.adjacency, depth.detach(), camera.near)
        mask = frags.mask[:, None].to(dtype)
        return RenderOutput(linear_to_srgb(linear), linear, mask,
                            self._to_image(diffuse, frags, None) if s.components else None,
                            self._to_image(spec, frags, None) if s.components and spec is not None else None, depth, frags)

    @staticmethod
    def _to_image(values: torch.Tensor, frags: Fragments, background: torch.Tensor | None) -> torch.Tensor:
        img = scatter_image(values, frags)
        if background is None:
            return img
        m = frags.mask[:, None].to(img.dtype)
        return img + (1 - m) * background.permute(0, 3, 1, 2)

    @staticmethod
    def _lookup(maps: list[torch.Tensor], uv: torch.Tensor, batch_index: torch.Tensor, b: int) -> torch.Tensor:
        """(B or 1, C_k, R, R) maps at per-pixel uv (N, 2) of batch elements ``batch_index`` -> (N, sum C_k)."""
        import torch.nn.functional as F

        if maps[0].device.type == "cpu":
            from ._kernels import bilinear_lookup

            return bilinear_lookup(maps, batch_index, uv.to(maps[0].dtype))
        texture = torch.cat([m.expand(max(x.shape[0] for x in maps), -1, -1, -1) for m in maps], 1)
        grid = torch.stack([uv[:, 0] * 2 - 1, 1 - uv[:, 1] * 2], -1)
        if texture.shape[0] == 1 or b == 1:
            return F.grid_sample(texture[:1], grid[None, None], mode="bilinear", padding_mode="border",
                                 align_corners=False)[0, :, 0].T
        out = torch.empty(len(uv), texture.shape[1], dtype=texture.dtype, device=texture.device)
        parts = []
        for k in range(b):
            sel = (batch_index == k).nonzero()[:, 0]
            parts.append((sel, F.grid_sample(texture[k : k + 1], grid[sel][None, None], mode="bilinear",
                                             padding_mode="border", align_corners=False)[0, :, 0].T))
        for sel, val in parts:
            out = out.index_copy(0, sel, val)
        return out
