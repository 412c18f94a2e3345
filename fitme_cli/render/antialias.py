"""Analytic antialiasing of silhouettes, the idea of nvdiffrast's ``antialias``: where two neighbouring
pixels see different surfaces across a silhouette edge, blend their colours by where that edge
crosses the segment between the pixel centres. The crossing point is a differentiable function of
the edge's projected vertices, so the image's gradient moves the outline: the shape's silhouette can
be fitted to a photo.
"""

from __future__ import annotations

import torch

from .raster import Fragments

__all__ = ["face_adjacency", "antialias"]


def face_adjacency(faces: torch.Tensor) -> torch.Tensor:
    """(F, 3) -> (F, 3) int64: column k is the face across edge (v_k, v_k+1), -1 on a boundary."""
    f = faces.long()
    n = int(f.max()) + 1 if len(f) else 0
    a = torch.cat([f[:, 0], f[:, 1], f[:, 2]])
    b = torch.cat([f[:, 1], f[:, 2], f[:, 0]])
    fid = torch.arange(len(f)).repeat(3)
    slot = torch.arange(3).repeat_interleave(len(f))
    key = a * n + b  # directed edge
    rev = b * n + a
    order = torch.argsort(key)
    skey = key[order]
    pos = torch.searchsorted(skey, rev).clamp(max=len(skey) - 1)
    found = skey[pos] == rev
    out = torch.full((len(f), 3), -1, dtype=torch.long)
    out[fid[found], slot[found]] = fid[order[pos[found]]]
    return out


def _signed_area(px: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    v = px[:, faces]  # (B, F, 3, 3)
    return ((v[..., 1, 0] - v[..., 0, 0]) * (v[..., 2, 1] - v[..., 0, 1])
            - (v[..., 2, 0] - v[..., 0, 0]) * (v[..., 1, 1] - v[..., 0, 1]))


def antialias(color: torch.Tensor, frags: Fragments, px: torch.Tensor, faces: torch.Tensor, adjacency: torch.Tensor,
              depth: torch.Tensor, near: float = 10.0) -> torch.Tensor:
    """color: (B, C, H, W); px: (B, V, 3) projected vertices; depth: (B, H, W) per-pixel depth (inf on
    the background). Returns the antialiased (B, C, H, W)."""
    tri = frags.triangle
    with torch.no_grad():
        area = _signed_area(px.detach(), faces)  # (B, F); front-facing < 0
        behind = (px.detach()[..., 2][:, faces] < near).any(-1)
        front = (area < 0) & ~behind
        adj_front = front.gather(1, adjacency.clamp(min=0).reshape(1, -1).expand(front.shape[0], -1)).view(-1, *adjacency.shape)
        edge_sil = (adjacency[None] < 0) | ~adj_front  # (B, F, 3)
        sil_face = front & edge_sil.any(-1)  # triangles with at least one silhouette edge
        sil_pix = torch.zeros_like(tri, dtype=torch.bool)
        cov = tri >= 0
        sil_pix[cov] = sil_face[cov.nonzero()[:, 0], tri[cov]]
    out = color
    deltas = []
    for axis in (2, 1):  # horizontal neighbours, then vertical
        ta = tri.narrow(axis, 0, tri.shape[axis] - 1)
        tb = tri.narrow(axis, 1, tri.shape[axis] - 1)
        da = depth.narrow(axis, 0, tri.shape[axis] - 1)
        db = depth.narrow(axis, 1, tri.shape[axis] - 1)
        sa = sil_pix.narrow(axis, 0, tri.shape[axis] - 1)
        sb = sil_pix.narrow(axis, 1, tri.shape[axis] - 1)
        # only pairs next to a silhouette triangle can straddle a silhouette edge
        cand = ((ta != tb) & (sa | sb)).nonzero()  # (K, 3) b, i, j of the first pixel of each pair
        if len(cand) == 0:
            continue
        b, i, j = cand.unbind(1)
        a_front = da[b, i, j] <= db[b, i, j]
        t_front = torch.where(a_front, ta[b, i, j], tb[b, i, j])
        keep = t_front >= 0
        b, i, j, a_front, t_front = b[keep], i[keep], j[keep], a_front[keep], t_front[keep]
        # pixel centres of the front (f) and back (k) pixels
        step = torch.tensor([0, 1] if axis == 2 else [1, 0])
        ia, ja = i, j
        ib, jb = i + step[0], j + step[1]
        fi, fj = torch.where(a_front, ia, ib), torch.where(a_front, ja, jb)
        ki, kj = torch.where(a_front, ib, ia), torch.where(a_front, jb, ja)
        qf = torch.stack([fj, fi], 1).to(px.dtype) + 0.5
        qk = torch.stack([kj, ki], 1).to(px.dtype) + 0.5
        fv = faces[t_front]  # (K, 3)
        v = px[b[:, None], fv][..., :2]  # (K, 3, 2)
        best_t = torch.full((len(b),), 2.0, dtype=px.dtype)
        for e in range(3):
            p0, p1 = v[:, e], v[:, (e + 1) % 3]
            silhouette = edge_sil[b, t_front, e]
            ex, ey = p1[:, 0] - p0[:, 0], p1[:, 1] - p0[:, 1]
            # edge function, positive on the triangle's side for front-facing (area < 0) triangles
            gf = -(ex * (qf[:, 1] - p0[:, 1]) - ey * (qf[:, 0] - p0[:, 0]))
            gk = -(ex * (qk[:, 1] - p0[:, 1]) - ey * (qk[:, 0] - p0[:, 0]))
            # each edge belongs to the pairs along its more-normal axis only (horizontal pairs for
            # steep edges, vertical pairs for flat ones), or a diagonal edge would be blended twice
            major = ey.abs() >= ex.abs() if axis == 2 else ex.abs() > ey.abs()
            crosses = silhouette & major & (gk < 0) & (gf >= 0)
            denom = torch.where(crosses, gf - gk, torch.ones_like(gf))
            t = torch.where(crosses, gf / denom, torch.full_like(gf, 2.0))
            best_t = torch.minimum(best_t, t)
        hit = best_t <= 1.0
        if not hit.any():
            continue
        b, fi, fj, ki, kj, t = b[hit], fi[hit], fj[hit], ki[hit], kj[hit], best_t[hit]
        cf = color[b, :, fi, fj]
        ck = color[b, :, ki, kj]
        # t > 1/2: the front surface reaches into the back pixel; t < 1/2: the back one into the front pixel
        wk = (t - 0.5).clamp(min=0)[:, None]
        wf = (0.5 - t).clamp(min=0)[:, None]
        d = torch.zeros_like(color).permute(0, 2, 3, 1)
        d = d.index_put((b, ki, kj), (cf - ck) * wk, accumulate=True)
        d = d.index_put((b, fi, fj), (ck - cf) * wf, accumulate=True)
        deltas.append(d.permute(0, 3, 1, 2))
    for d in deltas:
        out = out + d
    return out
