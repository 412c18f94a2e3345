"""Rasterisation split as nvdiffrast does it: a visibility pass (which triangle covers each pixel;
no gradients, numba) and a differentiable pass (the barycentrics of each covered pixel recomputed in
torch from the projected vertices, so gradients reach the vertex positions).

Sampling: pixel (i, j) is covered by a triangle if its centre (j + 0.5, i + 0.5) is inside (edges
inclusive) and the triangle is the nearest there (perspective-correct depth). Triangles with any vertex
nearer than the camera's near plane are dropped (not clipped): for a head in front of a camera this
only ever removes geometry the camera is inside of.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch

__all__ = ["Fragments", "rasterize", "barycentrics", "interpolate"]


@dataclass(frozen=True)
class Fragments:
    """Visibility of one batch of images.

    triangle: (B, H, W) int64 triangle index, -1 where nothing is drawn.
    index: (N, 3) int64 (b, i, j) of the N covered pixels, row-major order.
    face: (N,) int64 their triangles.
    """

    triangle: torch.Tensor
    index: torch.Tensor
    face: torch.Tensor

    @property
    def mask(self) -> torch.Tensor:
        """(B, H, W) bool, covered pixels."""
        return self.triangle >= 0


_BOX_SLACK = 1e-7


@numba.njit(cache=True, nogil=True)
def _raster_kernel(px, faces, height, width, near, cull, tri_out, depth):
    """px: (V, 3) float64 pixel x, y, depth; tri_out (H, W) int64 filled with -1; depth (H, W) inf."""
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        xa, ya, xb, yb, xc, yc = px[a, 0], px[a, 1], px[b, 0], px[b, 1], px[c, 0], px[c, 1]
        # Pixel centres in the bounding box first: most head triangles are about a pixel and hold none,
        # and leaving them before any other test halved the pass (24.6k triangles: 2.0 -> 0.9 ms). The
        # 1e-7 px slack keeps centres on the box's edge for the exact tests below; NaN fails the compares.
        fx0 = np.ceil(min(xa, xb, xc) - 0.5 - _BOX_SLACK)
        fx1 = np.floor(max(xa, xb, xc) - 0.5 + _BOX_SLACK)
        if not (fx0 <= fx1 and fx1 >= 0.0 and fx0 <= width - 1):
            continue
        fy0 = np.ceil(min(ya, yb, yc) - 0.5 - _BOX_SLACK)
        fy1 = np.floor(max(ya, yb, yc) - 0.5 + _BOX_SLACK)
        if not (fy0 <= fy1 and fy1 >= 0.0 and fy0 <= height - 1):
            continue
        za, zb, zc = px[a, 2], px[b, 2], px[c, 2]
        if za < near or zb < near or zc < near:
            continue
        area = (xb - xa) * (yc - ya) - (xc - xa) * (yb - ya)
        if area == 0.0 or not np.isfinite(area):
            continue
        if cull and area > 0:  # back-facing (see rasterize)
            continue
        x0 = int(max(fx0, 0.0))  # clamped as floats: int() of an infinity is undefined
        x1 = int(min(fx1, width - 1.0))
        y0 = int(max(fy0, 0.0))
        y1 = int(min(fy1, height - 1.0))
        inv = 1.0 / area
        for i in range(y0, y1 + 1):
            py = i + 0.5
            for j in range(x0, x1 + 1):
                qx = j + 0.5
                # each edge function cross(p0 - q, p1 - q) computed on its own: the neighbour across a
                # shared edge gets the exact negation, so a centre on the edge is never missed by both
                e0 = (xb - qx) * (yc - py) - (xc - qx) * (yb - py)
                e1 = (xc - qx) * (ya - py) - (xa - qx) * (yc - py)
                e2 = (xa - qx) * (yb - py) - (xb - qx) * (ya - py)
                w0, w1, w2 = e0 * inv, e1 * inv, e2 * inv
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                z = 1.0 / (w0 / za + w1 / zb + w2 / zc)
                if z < depth[i, j]:
                    depth[i, j] = z
                    tri_out[i, j] = f


def _visibility(px: np.ndarray, faces: np.ndarray, height: int, width: int, near: float, cull: bool,
                return_depth: bool = False):
    b = px.shape[0]
    tri = np.full((b, height, width), -1, np.int64)
    depth = np.full((b, height, width), np.inf)
    for k in range(b):
        _raster_kernel(px[k], faces, height, width, near, cull, tri[k], depth[k])
    return (tri, depth) if return_depth else tri


def _visibility_ref(px: np.ndarray, faces: np.ndarray, height: int, width: int, near: float, cull: bool) -> np.ndarray:
    """Slow and obvious: every pixel tests every triangle."""
    b = px.shape[0]
    tri = np.full((b, height, width), -1, np.int64)
    for k in range(b):
        for i in range(height):
            for j in range(width):
                best = np.inf
                q = np.array([j + 0.5, i + 0.5])
                for f, (a, bb, c) in enumerate(faces):
                    pa, pb, pc = px[k, a], px[k, bb], px[k, c]
                    if min(pa[2], pb[2], pc[2]) < near:
                        continue
                    area = (pb[0] - pa[0]) * (pc[1] - pa[1]) - (pc[0] - pa[0]) * (pb[1] - pa[1])
                    if area == 0 or (cull and area > 0):
                        continue
                    w0 = ((pb[0] - q[0]) * (pc[1] - q[1]) - (pc[0] - q[0]) * (pb[1] - q[1])) / area
                    w1 = ((pc[0] - q[0]) * (pa[1] - q[1]) - (pa[0] - q[0]) * (pc[1] - q[1])) / area
                    w2 = ((pa[0] - q[0]) * (pb[1] - q[1]) - (pb[0] - q[0]) * (pa[1] - q[1])) / area
                    if min(w0, w1, w2) < 0:
                        continue
                    z = 1 / (w0 / pa[2] + w1 / pb[2] + w2 / pc[2])
                    if z < best:
                        best, tri[k, i, j] = z, f
    return tri


def rasterize(px: torch.Tensor, faces: torch.Tensor, height: int, width: int, near: float = 10.0,
              cull_backfaces: bool = True) -> Fragments:
    """Visibility pass. px: (B, V, 3) projected vertices (pixel x, pixel y, depth mm; ``camera.project``);
    faces: (F, 3) int. Counter-clockwise triangles as seen on screen (y down) are front-facing: that
    is what the shape model's outward-wound triangles become under ``camera.project``. No gradients."""
    if px.ndim != 3 or px.shape[-1] != 3:
        raise ValueError(f"rasterize: expected px of shape (B, V, 3), got {tuple(px.shape)}")
    if faces.ndim != 2 or faces.shape[-1] != 3:
        raise ValueError(f"rasterize: expected faces of shape (F, 3), got {tuple(faces.shape)}")
    p = px.detach().to("cpu", torch.float64).numpy()
    p = np.where(np.isfinite(p).all(-1, keepdims=True), p, -1.0)  # any non-finite coordinate: depth -1, dropped
    tri = torch.from_numpy(_visibility(p, faces.detach().cpu().numpy().astype(np.int64), height, width, near, cull_backfaces))
    tri = tri.to(px.device)
    index = (tri >= 0).nonzero()
    return Fragments(tri, index, tri[index[:, 0], index[:, 1], index[:, 2]])


def barycentrics(px: torch.Tensor, faces: torch.Tensor, frags: Fragments, perspective: bool = True) -> torch.Tensor:
    """(N, 3) barycentric weights of each covered pixel's centre, differentiable w.r.t. ``px``.
    Perspective-correct by default (weights of attributes that vary linearly on the 3D triangle).
    CPU: a numba loop pair (``_kernels.barycentric_weights``); elsewhere, and as its reference,
    ``_barycentrics_torch``."""
    if px.ndim != 3 or px.shape[-1] != 3:
        raise ValueError(f"barycentrics: expected px of shape (B, V, 3), got {tuple(px.shape)}")
    if px.device.type == "cpu":
        from ._kernels import barycentric_weights

        return barycentric_weights(px, faces[frags.face], frags.index, perspective)
    return _barycentrics_torch(px, faces, frags, perspective)


def _barycentrics_torch(px: torch.Tensor, faces: torch.Tensor, frags: Fragments, perspective: bool = True) -> torch.Tensor:
    b, i, j = frags.index.unbind(1)
    v = _gather_corners(px, faces, frags)  # (N, 3 corners, 3)
    q = torch.stack([j, i], 1).to(px.dtype) + 0.5
    a, bb, c = v[:, 0], v[:, 1], v[:, 2]
    area = (bb[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (bb[:, 1] - a[:, 1])
    # visible triangles have |area| > 0 (the visibility pass skips zero-area ones), but a tiny sliver can
    # be 1e-12 px^2: keep its sign, bound its inverse
    area = torch.where(area.abs() < 1e-12, torch.full_like(area, -1e-12), area)
    w0 = ((bb[:, 0] - q[:, 0]) * (c[:, 1] - q[:, 1]) - (c[:, 0] - q[:, 0]) * (bb[:, 1] - q[:, 1])) / area
    w1 = ((c[:, 0] - q[:, 0]) * (a[:, 1] - q[:, 1]) - (a[:, 0] - q[:, 0]) * (c[:, 1] - q[:, 1])) / area
    w = torch.stack([w0, w1, 1 - w0 - w1], 1)
    if not perspective:
        return w
    w = w / v[:, :, 2].clamp(min=1e-6)
    return w / w.sum(1, keepdim=True).where(w.sum(1, keepdim=True).abs() > 1e-12, torch.ones_like(w[:, :1]))


def _gather_corners(attr: torch.Tensor, faces: torch.Tensor, frags: Fragments) -> torch.Tensor:
    """(B, V, C) or (V, C) -> (N, 3, C) values at the corners of each covered pixel's triangle.
    index_select on a flat table: its backward is index_add, several times faster on the CPU than
    advanced indexing's accumulate-put."""
    flat, idx = _flat_rows(attr, faces, frags)
    if flat.device.type == "cpu":
        from ._kernels import gather_rows

        return gather_rows(flat, idx)
    return flat.index_select(0, idx.reshape(-1)).view(len(idx), 3, -1)


def _flat_rows(attr: torch.Tensor, faces: torch.Tensor, frags: Fragments) -> tuple[torch.Tensor, torch.Tensor]:
    """The attribute table as (M, C) and each covered pixel's 3 corner rows in it (N, 3)."""
    tri = faces[frags.face]  # (N, 3)
    if attr.ndim == 2:
        return attr, tri
    return attr.reshape(-1, attr.shape[-1]), tri + frags.index[:, :1] * attr.shape[1]


def interpolate(attr: torch.Tensor, faces: torch.Tensor, frags: Fragments, bary: torch.Tensor) -> torch.Tensor:
    """Per-vertex attributes (B, V, C) (or (V, C), shared by the batch) at the covered pixels: (N, C).
    ``faces`` indexes ``attr``: pass ``uv_faces`` for UVs, ``faces`` for vertex attributes.
    CPU: a numba loop with its own backward; elsewhere (and as the reference) ``_interpolate_torch``."""
    if attr.device.type != "cpu":
        return _interpolate_torch(attr, faces, frags, bary)
    from ._kernels import interpolate_rows

    flat, idx = _flat_rows(attr, faces, frags)
    return interpolate_rows(flat, idx, bary.to(flat.dtype))


def _interpolate_torch(attr, faces, frags, bary):
    flat, idx = _flat_rows(attr, faces, frags)
    vals = flat.index_select(0, idx.reshape(-1)).view(len(idx), 3, -1)
    return (vals * bary[..., None].to(vals.dtype)).sum(1)


def scatter_image(values: torch.Tensor, frags: Fragments, background: float | torch.Tensor = 0.0) -> torch.Tensor:
    """(N, C) per covered pixel -> (B, C, H, W) image, ``background`` elsewhere. Differentiable."""
    b, h, w = frags.triangle.shape
    out = torch.zeros(b, h, w, values.shape[1], dtype=values.dtype, device=values.device)
    if isinstance(background, torch.Tensor) or background != 0:
        out = out + background
    out = out.index_put((frags.index[:, 0], frags.index[:, 1], frags.index[:, 2]), values)
    return out.permute(0, 3, 1, 2)
