"""Analytic antialiasing of silhouettes, the idea of nvdiffrast's ``antialias``: where two neighbouring
pixels see different surfaces across a silhouette edge, blend their colours by where that edge
crosses the segment between the pixel centres. The crossing point is a differentiable function of
the edge's projected vertices, so the image's gradient moves the outline: the shape's silhouette can
be fitted to a photo.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from ._kernels import _buffer
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
    the background). Returns the antialiased (B, C, H, W), differentiable w.r.t. ``color`` and the x, y
    of ``px``. CPU: numba loops with a hand-written backward (``_Antialias``); elsewhere, and as their
    reference in the tests, ``_antialias_torch``."""
    for t, name, nd in ((color, "color", 4), (px, "px", 3), (depth, "depth", 3)):
        if t.ndim != nd:
            raise ValueError(f"antialias: expected {name} with {nd} dimensions, got shape {tuple(t.shape)}")
    if color.device.type != "cpu" or px.device.type != "cpu":
        return _antialias_torch(color, frags, px, faces, adjacency, depth, near)
    return _Antialias.apply(color, px, frags.triangle, depth, faces, adjacency, float(near))


# --- numba path ---------------------------------------------------------------------------------------
# The torch version below is ~60 small ops (nonzero, gathers, index_put with accumulate) each way; the
# pixels it changes are a few thousand. Two passes over the image find the blended pairs (a record each:
# which pixels, the front triangle, the edge, the crossing t), the forward blends them, the backward
# uses the same records. Same rules as the reference, pair for pair.


@numba.njit(cache=True, nogil=True)
def _aa_silhouettes(px, faces, adjacency, near, front, edge_sil, sil_face):
    """One image. px: (V, 3); fills front (F,), edge_sil (F, 3), sil_face (F,) (bool)."""
    nf = faces.shape[0]
    for f in range(nf):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        area = ((px[b, 0] - px[a, 0]) * (px[c, 1] - px[a, 1]) - (px[c, 0] - px[a, 0]) * (px[b, 1] - px[a, 1]))
        behind = px[a, 2] < near or px[b, 2] < near or px[c, 2] < near
        front[f] = area < 0 and not behind
    for f in range(nf):
        any_sil = False
        for e in range(3):
            n = adjacency[f, e]
            s = n < 0 or not front[n]
            edge_sil[f, e] = s
            any_sil = any_sil or s
        sil_face[f] = front[f] and any_sil


@numba.njit(cache=True, nogil=True)
def _aa_pair(px, faces, edge_sil, tf, fi, fj, ki, kj, horizontal):
    """Where the front triangle ``tf``'s silhouette edges cross the segment from the front pixel's
    centre (fi, fj) to the back pixel's (ki, kj): (t, edge), t = 2.0 when none does."""
    best_t = 2.0
    best_e = -1
    qfx, qfy = fj + 0.5, fi + 0.5
    qkx, qky = kj + 0.5, ki + 0.5
    for e in range(3):
        if not edge_sil[tf, e]:
            continue
        v0, v1 = faces[tf, e], faces[tf, (e + 1) % 3]
        p0x, p0y, p1x, p1y = px[v0, 0], px[v0, 1], px[v1, 0], px[v1, 1]
        ex, ey = p1x - p0x, p1y - p0y
        gf = -(ex * (qfy - p0y) - ey * (qfx - p0x))
        gk = -(ex * (qky - p0y) - ey * (qkx - p0x))
        major = abs(ey) >= abs(ex) if horizontal else abs(ex) > abs(ey)
        if major and gk < 0 and gf >= 0:
            t = gf / (gf - gk)
            if t < best_t:
                best_t, best_e = t, e
    return best_t, best_e


@numba.njit(cache=True, nogil=True)
def _aa_classify(px, faces, adjacency, near, tri, edge_sil, sil_face):
    """All images: fills edge_sil (B, F, 3) and sil_face (B, F); returns the number of covered pixels
    whose triangle has a silhouette edge (each blended pair has one such pixel, a pixel is in <= 4 pairs:
    4x this bounds the records)."""
    nb, h, w = tri.shape
    front = np.empty(faces.shape[0], np.bool_)
    n = 0
    for b in range(nb):
        _aa_silhouettes(px[b], faces, adjacency, near, front, edge_sil[b], sil_face[b])
        for i in range(h):
            for j in range(w):
                t = tri[b, i, j]
                if t >= 0 and sil_face[b, t]:
                    n += 1
    return n


@numba.njit(cache=True, nogil=True)
def _aa_find(px, faces, tri, depth, edge_sil, sil_face, rec, rec_t):
    """All images. Fills rec (K, 7) int64 rows (b, fi, fj, ki, kj, front triangle, edge) and rec_t (K,);
    returns K. rec must hold 4 rows per silhouette pixel (``_aa_classify``)."""
    nb, h, w = tri.shape
    k = 0
    for b in range(nb):
        sil = sil_face[b]
        for axis in range(2):
            horizontal = axis == 0
            for i in range(h - 1 + horizontal):
                for j in range(w - horizontal):
                    i2, j2 = (i, j + 1) if horizontal else (i + 1, j)
                    ta, tb = tri[b, i, j], tri[b, i2, j2]
                    if ta == tb:
                        continue
                    if not ((ta >= 0 and sil[ta]) or (tb >= 0 and sil[tb])):
                        continue
                    a_front = depth[b, i, j] <= depth[b, i2, j2]
                    tf = ta if a_front else tb
                    if tf < 0:
                        continue
                    fi, fj, ki, kj = (i, j, i2, j2) if a_front else (i2, j2, i, j)
                    t, e = _aa_pair(px[b], faces, edge_sil[b], tf, fi, fj, ki, kj, horizontal)
                    if t <= 1.0:
                        rec[k, 0], rec[k, 1], rec[k, 2], rec[k, 3], rec[k, 4], rec[k, 5], rec[k, 6] = b, fi, fj, ki, kj, tf, e
                        rec_t[k] = t
                        k += 1
    return k


@numba.njit(cache=True, nogil=True)
def _aa_blend(color, rec, rec_t, out):
    nc = color.shape[1]
    for r in range(rec.shape[0]):
        b, fi, fj, ki, kj = rec[r, 0], rec[r, 1], rec[r, 2], rec[r, 3], rec[r, 4]
        t = rec_t[r]
        wk = max(t - 0.5, 0.0)  # t > 1/2: the front surface reaches into the back pixel
        wf = max(0.5 - t, 0.0)  # t < 1/2: the back surface into the front pixel
        for c in range(nc):
            d = color[b, c, fi, fj] - color[b, c, ki, kj]
            out[b, c, ki, kj] += d * wk
            out[b, c, fi, fj] -= d * wf


@numba.njit(cache=True, nogil=True)
def _aa_backward(color, px, faces, rec, rec_t, g, g_color, g_px, need_px):
    nc = color.shape[1]
    for r in range(rec.shape[0]):
        b, fi, fj, ki, kj, tf, e = rec[r, 0], rec[r, 1], rec[r, 2], rec[r, 3], rec[r, 4], rec[r, 5], rec[r, 6]
        t = rec_t[r]
        wk = max(t - 0.5, 0.0)
        wf = max(0.5 - t, 0.0)
        gt = 0.0
        for c in range(nc):
            gk_, gf_ = g[b, c, ki, kj], g[b, c, fi, fj]
            g_color[b, c, fi, fj] += wk * gk_ - wf * gf_
            g_color[b, c, ki, kj] += -wk * gk_ + wf * gf_
            d = color[b, c, fi, fj] - color[b, c, ki, kj]
            if t > 0.5:
                gt += gk_ * d
            elif t < 0.5:
                gt += gf_ * d  # d(-d wf)/dt = d
        if not need_px or gt == 0.0:
            continue
        v0, v1 = faces[tf, e], faces[tf, (e + 1) % 3]
        p0x, p0y, p1x, p1y = px[b, v0, 0], px[b, v0, 1], px[b, v1, 0], px[b, v1, 1]
        ex, ey = p1x - p0x, p1y - p0y
        qfx, qfy, qkx, qky = fj + 0.5, fi + 0.5, kj + 0.5, ki + 0.5
        sf = -(ex * (qfy - p0y) - ey * (qfx - p0x))
        sk = -(ex * (qky - p0y) - ey * (qkx - p0x))
        den = sf - sk
        dsf = -sk / (den * den) * gt  # t = sf / (sf - sk)
        dsk = sf / (den * den) * gt
        # s(q) = -ex (qy - p0y) + ey (qx - p0x), ex = p1x - p0x, ey = p1y - p0y
        g_px[b, v0, 0] += dsf * ((qfy - p0y) - ey) + dsk * ((qky - p0y) - ey)
        g_px[b, v1, 0] += -dsf * (qfy - p0y) - dsk * (qky - p0y)
        g_px[b, v0, 1] += dsf * (ex - (qfx - p0x)) + dsk * (ex - (qkx - p0x))
        g_px[b, v1, 1] += dsf * (qfx - p0x) + dsk * (qkx - p0x)


class _Antialias(torch.autograd.Function):
    @staticmethod
    def forward(ctx, color, px, tri, depth, faces, adjacency, near):
        c = color.detach().contiguous().numpy()
        p = px.detach().contiguous().numpy()
        f = faces.contiguous().numpy()
        adj = adjacency.contiguous().numpy()
        t = tri.contiguous().numpy()
        edge_sil = np.empty((t.shape[0], f.shape[0], 3), np.bool_)
        sil_face = np.empty((t.shape[0], f.shape[0]), np.bool_)
        cap = 4 * _aa_classify(p, f, adj, near, t, edge_sil, sil_face)
        rec = np.empty((cap, 7), np.int64)
        rec_t = np.empty(cap, p.dtype)
        k = _aa_find(p, f, t, depth.detach().to(px.dtype).contiguous().numpy(), edge_sil, sil_face, rec, rec_t)
        rec, rec_t = rec[:k], rec_t[:k]
        out = _buffer(c.shape, c.dtype, zero=False)
        out[...] = c
        _aa_blend(c, rec, rec_t.astype(c.dtype), out)
        ctx.save_for_backward(color, px, faces)
        ctx.rec, ctx.rec_t = rec, rec_t
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g):
        color, px, faces = ctx.saved_tensors
        c = color.detach().contiguous().numpy()
        p = px.detach().contiguous().numpy()
        gg = np.ascontiguousarray(g.numpy())
        g_color = _buffer(gg.shape, gg.dtype, zero=False)
        g_color[...] = gg
        need_px = ctx.needs_input_grad[1]
        g_px = _buffer(p.shape if need_px else (1, 1, 3), p.dtype)
        _aa_backward(c, p, faces.contiguous().numpy(), ctx.rec, ctx.rec_t, gg, g_color, g_px, need_px)
        return (torch.from_numpy(g_color).to(color.dtype) if ctx.needs_input_grad[0] else None,
                torch.from_numpy(g_px) if need_px else None, None, None, None, None, None)


# --- torch path (other devices; the reference) --------------------------------------------------------


def _antialias_torch(color: torch.Tensor, frags: Fragments, px: torch.Tensor, faces: torch.Tensor, adjacency: torch.Tensor,
                     depth: torch.Tensor, near: float = 10.0) -> torch.Tensor:
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
