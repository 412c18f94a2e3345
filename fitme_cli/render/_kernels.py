"""numba kernels with hand-written backward passes for the renderer's per-pixel gathers and scatters.

torch's CPU autograd spends most of a render in the backward of advanced indexing and grid_sample
(scatter-adds with sorting and atomics). These loops do the same arithmetic directly: measured ~10x
faster on this 2-core machine. Used on CPU tensors only; other devices use the torch reference path
(``raster._interpolate_torch``, ``texture.sample_texture``), which the tests compare against.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

__all__ = ["interpolate_rows", "gather_rows", "bilinear_lookup", "specular_pixels", "barycentric_weights", "srgb_encode"]


def _buffer(shape, dtype, zero: bool = True) -> np.ndarray:
    """A numpy view of a torch-allocated array, for kernel outputs handed back to torch: they get torch's
    64-byte alignment like every tensor torch makes itself (torch's vectorised CPU loops handle the
    unaligned head of an array separately), instead of malloc's 16."""
    t = (torch.zeros if zero else torch.empty)(tuple(shape), dtype=torch.from_numpy(np.empty(0, dtype)).dtype)
    return t.numpy()


@numba.njit(cache=True, nogil=True)
def _interp_fwd(attr, idx, w, out):
    n, c = out.shape
    for i in range(n):
        for k in range(3):
            r = idx[i, k]
            wk = w[i, k]
            for j in range(c):
                out[i, j] += wk * attr[r, j]


# The chunked sums below were written for a parallel loop (see the note on threads); they stay because
# the order of float sums is part of a fit's outcome: the plain loop's order moved the synthetic fits'
# results across their test bounds (tests/test_fit_synthetic.py), which are calibrated on this one.
_INTERP_CHUNKS = 4  # backward pixel chunks, each scattering into its own table; summed in order


@numba.njit(cache=True, nogil=True)
def _interp_bwd(attr, idx, w, g, g_attr, g_w, need_attr, need_w):
    """Chunks of pixels, each with its own attribute-gradient table, added in chunk order."""
    n = g.shape[0]
    per = (n + _INTERP_CHUNKS - 1) // _INTERP_CHUNKS
    if need_attr:
        part = np.zeros((_INTERP_CHUNKS,) + g_attr.shape, g_attr.dtype)
    else:
        part = np.zeros((_INTERP_CHUNKS, 1, 1), g_attr.dtype)  # unused
    for ch in range(_INTERP_CHUNKS):
        _interp_bwd_range(attr, idx, w, g, part[ch], g_w, need_attr, need_w, ch * per, min(n, (ch + 1) * per))
    if need_attr:
        for ch in range(_INTERP_CHUNKS):
            g_attr += part[ch]


@numba.njit(cache=True, nogil=True)
def _interp_bwd_range(attr, idx, w, g, g_attr, g_w, need_attr, need_w, start, stop):
    c = g.shape[1]
    for i in range(start, stop):
        for k in range(3):
            r = idx[i, k]
            wk = w[i, k]
            acc = 0.0
            for j in range(c):
                gij = g[i, j]
                if need_attr:
                    g_attr[r, j] += wk * gij
                acc += attr[r, j] * gij
            if need_w:
                g_w[i, k] = acc


class _InterpolateRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, attr, idx, w):
        a, ix, ww = attr.detach().numpy(), idx.numpy(), w.detach().numpy()
        out = _buffer((ix.shape[0], a.shape[1]), a.dtype)
        _interp_fwd(a, ix, ww.astype(a.dtype, copy=False), out)
        ctx.save_for_backward(attr, idx, w)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g):
        attr, idx, w = ctx.saved_tensors
        need_attr, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[2]
        a = attr.detach().numpy()
        g_attr = _buffer(a.shape, a.dtype)
        g_w = _buffer(w.shape, a.dtype)
        _interp_bwd(a, idx.numpy(), w.detach().numpy().astype(a.dtype, copy=False), np.ascontiguousarray(g.numpy()),
                    g_attr, g_w, need_attr, need_w)
        return (torch.from_numpy(g_attr) if need_attr else None, None,
                torch.from_numpy(g_w).to(w.dtype) if need_w else None)


def interpolate_rows(attr: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """out[n] = sum_k w[n, k] attr[idx[n, k]]. attr: (M, C) float CPU; idx: (N, 3) int64; w: (N, 3)."""
    return _InterpolateRows.apply(attr.contiguous(), idx.contiguous(), w.contiguous())


@numba.njit(cache=True, nogil=True)
def _bilinear_setup(u, v, h, wd):
    x = u * wd - 0.5
    y = (1.0 - v) * h - 0.5
    dx = 1.0
    dy = 1.0
    if x <= 0.0:
        x, dx = 0.0, 0.0
    elif x >= wd - 1:
        x, dx = wd - 1.0, 0.0
    if y <= 0.0:
        y, dy = 0.0, 0.0
    elif y >= h - 1:
        y, dy = h - 1.0, 0.0
    x0 = int(np.floor(x))
    y0 = int(np.floor(y))
    x1 = min(x0 + 1, wd - 1)
    y1 = min(y0 + 1, h - 1)
    return x0, y0, x1, y1, x - x0, y - y0, dx, dy


# Up to 4 maps (albedo, specular, normals, shininess) are sampled in one call, each in its own
# (B, C, R, R) array: no torch.cat of the maps (an 8 MB copy at 512^2) and gradients that come out
# contiguous per map. Each pixel's four texels and weights are found once (``_bilinear_prepare``) and
# reused by every map, channel and the backward: the earlier kernels redid that per channel through a
# 4-way map switch and 4-d indexing, and took 4.9 ms forward for 7 channels of 512^2 at 256^2 (28.7k
# pixels) against 0.65 ms now. The weights stay float64, so values are bitwise those of the earlier
# kernels. The texture gradient goes a channel at a time, each channel's scatter in pixel order:
# measured 10 ms against 12 ms for one fused pass over the pixels writing every channel at once (the
# scattered writes stay in one 1 MB plane).


@numba.njit(cache=True, nogil=True)
def _bilinear_prepare(uv, h, wd, off, wts, duv):
    """Per pixel: off (N, 3) int64 flat index of texel (y0, x0), x step (0 or 1), y step (0 or W);
    wts (N, 4) the weights of texels 00, 01, 10, 11; duv (N, 4) fx, fy, dx W, dy H (d: 0 where clamped)."""
    for i in range(uv.shape[0]):
        x0, y0, x1, y1, fx, fy, dx, dy = _bilinear_setup(uv[i, 0], uv[i, 1], h, wd)
        off[i, 0] = y0 * wd + x0
        off[i, 1] = x1 - x0
        off[i, 2] = (y1 - y0) * wd
        wts[i, 0] = (1 - fx) * (1 - fy)
        wts[i, 1] = fx * (1 - fy)
        wts[i, 2] = (1 - fx) * fy
        wts[i, 3] = fx * fy
        duv[i, 0] = fx
        duv[i, 1] = fy
        duv[i, 2] = dx * wd
        duv[i, 3] = dy * h


@numba.njit(cache=True, nogil=True)
def _bilinear_fwd(tex, bidx, off, wts, out, col):
    """tex (B, C, R*R): one map; writes out[:, col:col + C]. B == 1: shared by every image."""
    batched = tex.shape[0] > 1
    for i in range(off.shape[0]):
        b = bidx[i] if batched else 0
        o, ox, oy = off[i, 0], off[i, 1], off[i, 2]
        w00, w01, w10, w11 = wts[i, 0], wts[i, 1], wts[i, 2], wts[i, 3]
        for j in range(tex.shape[1]):
            t = tex[b, j]
            out[i, col + j] = w00 * t[o] + w01 * t[o + ox] + w10 * t[o + oy] + w11 * t[o + ox + oy]


@numba.njit(cache=True, nogil=True)
def _bilinear_bwd_tex(gt, bidx, off, wts, g, col):
    """gt (B, C, R*R) zeros, filled with the gradient of one map from g[:, col:col + C]."""
    batched = gt.shape[0] > 1
    for j in range(gt.shape[1]):
        for i in range(off.shape[0]):
            gij = g[i, col + j]
            if gij == 0.0:
                continue
            b = bidx[i] if batched else 0
            t = gt[b, j]
            o, ox, oy = off[i, 0], off[i, 1], off[i, 2]
            t[o] += wts[i, 0] * gij
            t[o + ox] += wts[i, 1] * gij
            t[o + oy] += wts[i, 2] * gij
            t[o + ox + oy] += wts[i, 3] * gij


@numba.njit(cache=True, nogil=True)
def _bilinear_bwd_uv(tex, bidx, off, duv, g, col, acc):
    """Adds one map's share of dL/dx, dL/dy (texel units) to acc (N, 2) float64, channel by channel."""
    batched = tex.shape[0] > 1
    for i in range(off.shape[0]):
        b = bidx[i] if batched else 0
        o, ox, oy = off[i, 0], off[i, 1], off[i, 2]
        fx, fy = duv[i, 0], duv[i, 1]
        gu = acc[i, 0]
        gv = acc[i, 1]
        for j in range(tex.shape[1]):
            t = tex[b, j]
            gij = g[i, col + j]
            t00, t01, t10, t11 = t[o], t[o + ox], t[o + oy], t[o + ox + oy]
            gu += gij * ((1 - fy) * (t01 - t00) + fy * (t11 - t10))
            gv += gij * ((1 - fx) * (t10 - t00) + fx * (t11 - t01))
        acc[i, 0] = gu
        acc[i, 1] = gv


@numba.njit(cache=True, nogil=True)
def _bilinear_uv_scale(acc, duv, g_uv):
    for i in range(acc.shape[0]):
        g_uv[i, 0] = acc[i, 0] * duv[i, 2]  # dx/du = W
        g_uv[i, 1] = -acc[i, 1] * duv[i, 3]  # dy/dv = -H


# The kernels run serially. With parallel=True (prange over pixels, channels and pixel chunks whose
# partial sums were added in a fixed order: bitwise the same at any thread count) numba's default "omp"
# layer reset OpenMP's thread count when its pool started, raising torch's intra-op threads from 1 to 2
# under `--threads 1` (fits no longer reproducible); its "workqueue" layer avoided that but was no
# faster, its threads competing with torch's spinning OpenMP threads (docs/render.md, "Speed").


def _flat(m: torch.Tensor) -> np.ndarray:
    """(B, C, H, W) tensor -> (B, C, H*W) contiguous numpy view."""
    a = m.detach().contiguous().numpy()
    return a.reshape(a.shape[0], a.shape[1], -1)


class _BilinearLookup(torch.autograd.Function):
    @staticmethod
    def forward(ctx, bidx, uv, *maps):
        ts = [_flat(m) for m in maps]
        dt = ts[0].dtype
        h, wd = maps[0].shape[2], maps[0].shape[3]
        u = uv.detach().numpy().astype(dt, copy=False)
        n = u.shape[0]
        off = np.empty((n, 3), np.int64)
        wts = np.empty((n, 4), np.float64)
        duv = np.empty((n, 4), np.float64)
        _bilinear_prepare(u, h, wd, off, wts, duv)
        out = _buffer((n, sum(t.shape[1] for t in ts)), dt, zero=False)
        b = bidx.numpy()
        col = 0
        for t in ts:
            _bilinear_fwd(t, b, off, wts, out, col)
            col += t.shape[1]
        ctx.save_for_backward(bidx, uv, *maps)
        ctx.setup = (off, wts, duv)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g):
        bidx, uv, *maps = ctx.saved_tensors
        off, wts, duv = ctx.setup
        ts = [_flat(m) for m in maps]
        dt = ts[0].dtype
        b = bidx.numpy()
        gg = np.ascontiguousarray(g.numpy()).astype(dt, copy=False)
        cols = np.cumsum([0] + [t.shape[1] for t in ts])
        g_maps = []
        for k, t in enumerate(ts):
            if ctx.needs_input_grad[2 + k]:
                gm = _buffer(t.shape, dt)
                _bilinear_bwd_tex(gm, b, off, wts, gg, cols[k])
                g_maps.append(torch.from_numpy(gm).view(maps[k].shape))
            else:
                g_maps.append(None)
        g_uv = None
        if ctx.needs_input_grad[1]:
            acc = np.zeros((off.shape[0], 2), np.float64)
            for k, t in enumerate(ts):
                _bilinear_bwd_uv(t, b, off, duv, gg, cols[k], acc)
            g_uv = _buffer((off.shape[0], 2), dt)
            _bilinear_uv_scale(acc, duv, g_uv)
            g_uv = torch.from_numpy(g_uv).to(uv.dtype)
        return (None, g_uv) + tuple(g_maps)


def bilinear_lookup(textures, batch_index: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """One (B, C, H, W) texture, or a sequence of up to 4 (B or 1, C_k, H, W) maps of one size and dtype,
    at (N, 2) uv of batch elements ``batch_index`` (N,) -> (N, C) or (N, sum C_k), the maps' channels in
    order; a map of batch 1 is shared by every image. The same sampling as ``texture.sample_texture``
    (bilinear, texel centres, border clamp)."""
    maps = [textures] if isinstance(textures, torch.Tensor) else list(textures)
    if not 1 <= len(maps) <= 4:
        raise ValueError(f"bilinear_lookup: expected 1 to 4 maps, got {len(maps)}")
    ref = maps[0]
    for m in maps:
        if m.ndim != 4 or m.shape[2:] != ref.shape[2:] or m.dtype != ref.dtype:
            raise ValueError(f"bilinear_lookup: expected maps (B, C, {ref.shape[2]}, {ref.shape[3]}) of {ref.dtype}, got "
                             f"{tuple(m.shape)} of {m.dtype}")
    return _BilinearLookup.apply(batch_index.contiguous(), uv.contiguous(), *(m.contiguous() for m in maps))


@numba.njit(cache=True, nogil=True)
def _gather_bwd(idx, g, g_attr):
    n, k, c = g.shape
    for i in range(n):
        for a in range(k):
            r = idx[i, a]
            for j in range(c):
                g_attr[r, j] += g[i, a, j]


class _GatherRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, attr, idx):
        ctx.save_for_backward(idx)
        ctx.shape = attr.shape
        return attr[idx]

    @staticmethod
    def backward(ctx, g):
        (idx,) = ctx.saved_tensors
        g_attr = _buffer(ctx.shape, g.numpy().dtype)
        _gather_bwd(idx.numpy(), np.ascontiguousarray(g.numpy()), g_attr)
        return torch.from_numpy(g_attr), None


def gather_rows(attr: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """attr[idx] for (M, C) attr and (N, K) int64 idx -> (N, K, C), with a scatter-add backward loop."""
    return _GatherRows.apply(attr.contiguous(), idx.contiguous())


# --- fused Blinn-Phong specular --------------------------------------------------------------------
# The torch version (``shading.specular_reflectance`` after ``tangent_to_world``) is ~60 small ops per
# render and as many in the backward; per pixel they are a few hundred flops. One loop each way, with
# the backward derived by hand, is what gets render + backward under 30 ms. Directional lights only
# (point lights take the torch path). Normalisation is y = x rsqrt(|x|^2 + eps), whose backward is
# r (g - y (y . g)); the lobe is exp(s log(clamp(n . h, 1e-12, 1))), as in the torch version.

_SPEC_EPS = 1e-8
_NDH_MIN = 1e-12


def _spec_constants(dtype) -> np.ndarray:
    """eps, the n.h floor, 1, 0 in the maps' dtype: float32 renders then run the loops in float32
    (sqrtf, logf, expf): forward 2.9 -> 2.0 ms, backward 2.8 -> 2.3 ms at 256^2 with 3 lights. float64
    renders are unchanged, bit for bit."""
    return np.array([_SPEC_EPS, _NDH_MIN, 1.0, 0.0], dtype)


@numba.njit(cache=True, nogil=True, inline="always")
def _nrm3(x0, x1, x2, k):
    r = k[2] / np.sqrt(x0 * x0 + x1 * x1 + x2 * x2 + k[0])
    return x0 * r, x1 * r, x2 * r, r


@numba.njit(cache=True, nogil=True, inline="always")
def _nrm3_bwd(y0, y1, y2, r, g0, g1, g2):
    d = y0 * g0 + y1 * g1 + y2 * g2
    return r * (g0 - y0 * d), r * (g1 - y1 * d), r * (g2 - y2 * d)


@numba.njit(cache=True, nogil=True, inline="always")
def _frame(nts, nrm, tan, i, k):
    """Detail normal in world space and the intermediates the backward needs."""
    nd0, nd1, nd2, rn = _nrm3(nrm[i, 0], nrm[i, 1], nrm[i, 2], k)
    a = tan[i, 0] * nd0 + tan[i, 1] * nd1 + tan[i, 2] * nd2
    t0, t1, t2, rt = _nrm3(tan[i, 0] - nd0 * a, tan[i, 1] - nd1 * a, tan[i, 2] - nd2 * a, k)
    w = tan[i, 3]
    c0, c1, c2 = nd1 * t2 - nd2 * t1, nd2 * t0 - nd0 * t2, nd0 * t1 - nd1 * t0  # nd x t
    b0, b1, b2 = c0 * w, c1 * w, c2 * w
    m0, m1, m2 = nts[i, 0], nts[i, 1], nts[i, 2]
    ns0, ns1, ns2, rs = _nrm3(m0 * t0 + m1 * b0 + m2 * nd0, m0 * t1 + m1 * b1 + m2 * nd1, m0 * t2 + m1 * b2 + m2 * nd2, k)
    return nd0, nd1, nd2, rn, a, t0, t1, t2, rt, c0, c1, c2, b0, b1, b2, ns0, ns1, ns2, rs


@numba.njit(cache=True, nogil=True)
def _spec_fwd(nts, nrm, tan, p, eye, d, c, shin, vis, bi, out, keep, k):
    """keep (N, L, 3): each lit pixel's n.h, its log and the lobe, for the backward (which then needs no
    log or exp: 3 lights x 3 transcendentals per pixel were most of its time); k: ``_spec_constants``."""
    n_lights = d.shape[1]
    for i in range(nts.shape[0]):
        b = bi[i]
        nd0, nd1, nd2, _, _, _, _, _, _, _, _, _, _, _, _, ns0, ns1, ns2, _ = _frame(nts, nrm, tan, i, k)
        v0, v1, v2, _ = _nrm3(eye[b, 0] - p[i, 0], eye[b, 1] - p[i, 1], eye[b, 2] - p[i, 2], k)
        s = shin[i] if shin.shape[0] > 1 else shin[0]
        for j in range(n_lights):
            dj0, dj1, dj2 = d[b, j, 0], d[b, j, 1], d[b, j, 2]
            f = k[2] if nd0 * dj0 + nd1 * dj1 + nd2 * dj2 > k[3] else k[3]
            if vis.shape[0] > 1:
                f *= vis[i, j]
            if f == k[3]:
                continue
            h0, h1, h2, _ = _nrm3(dj0 + v0, dj1 + v1, dj2 + v2, k)
            x = min(max(ns0 * h0 + ns1 * h1 + ns2 * h2, k[1]), k[2])
            lx = np.log(x)
            raw = np.exp(s * lx)
            keep[i, j, 0] = x
            keep[i, j, 1] = lx
            keep[i, j, 2] = raw
            lobe = raw * f
            out[i, 0] += lobe * c[b, j, 0]
            out[i, 1] += lobe * c[b, j, 1]
            out[i, 2] += lobe * c[b, j, 2]


_SPEC_CHUNKS = 16  # the backward's pixel chunks: per-chunk sums of the shared gradients, added in order


@numba.njit(cache=True, nogil=True)
def _spec_bwd(nts, nrm, tan, p, eye, d, c, shin, vis, bi, keep, g,
              g_nts, g_nrm, g_tan, g_p, g_eye, g_d, g_c, g_shin, k):
    """The shared gradients (eye, lights, global shininess) are summed per chunk of pixels and the
    chunks added in a fixed order (as for ``_interp_bwd``)."""
    n = nts.shape[0]
    per = (n + _SPEC_CHUNKS - 1) // _SPEC_CHUNKS
    pe = np.zeros((_SPEC_CHUNKS,) + g_eye.shape, g_eye.dtype)
    pd = np.zeros((_SPEC_CHUNKS,) + g_d.shape, g_d.dtype)
    pc = np.zeros((_SPEC_CHUNKS,) + g_c.shape, g_c.dtype)
    ps = np.zeros(_SPEC_CHUNKS, g_shin.dtype)
    for ch in range(_SPEC_CHUNKS):
        _spec_bwd_range(nts, nrm, tan, p, eye, d, c, shin, vis, bi, keep, g, g_nts, g_nrm, g_tan, g_p,
                        pe[ch], pd[ch], pc[ch], ps[ch:ch + 1], g_shin, ch * per, min(n, (ch + 1) * per), k)
    for ch in range(_SPEC_CHUNKS):
        g_eye += pe[ch]
        g_d += pd[ch]
        g_c += pc[ch]
        if shin.shape[0] == 1:
            g_shin[0] += ps[ch]


@numba.njit(cache=True, nogil=True)
def _spec_bwd_range(nts, nrm, tan, p, eye, d, c, shin, vis, bi, keep, g, g_nts, g_nrm, g_tan, g_p,
                    g_eye, g_d, g_c, g_shin_global, g_shin, start, stop, k):
    n_lights = d.shape[1]
    for i in range(start, stop):
        b = bi[i]
        nd0, nd1, nd2, rn, a, t0, t1, t2, rt, c0, c1, c2, b0, b1, b2, ns0, ns1, ns2, rs = _frame(nts, nrm, tan, i, k)
        v0, v1, v2, rv = _nrm3(eye[b, 0] - p[i, 0], eye[b, 1] - p[i, 1], eye[b, 2] - p[i, 2], k)
        s = shin[i] if shin.shape[0] > 1 else shin[0]
        gi0, gi1, gi2 = g[i, 0], g[i, 1], g[i, 2]
        gns0 = gns1 = gns2 = k[3]
        gv0 = gv1 = gv2 = k[3]
        gs = k[3]
        for j in range(n_lights):
            dj0, dj1, dj2 = d[b, j, 0], d[b, j, 1], d[b, j, 2]
            f = k[2] if nd0 * dj0 + nd1 * dj1 + nd2 * dj2 > k[3] else k[3]
            if vis.shape[0] > 1:
                f *= vis[i, j]
            if f == k[3]:
                continue
            h0, h1, h2, rh = _nrm3(dj0 + v0, dj1 + v1, dj2 + v2, k)
            xr = ns0 * h0 + ns1 * h1 + ns2 * h2
            x, lx, lobe = keep[i, j, 0], keep[i, j, 1], keep[i, j, 2]
            g_c[b, j, 0] += gi0 * lobe * f
            g_c[b, j, 1] += gi1 * lobe * f
            g_c[b, j, 2] += gi2 * lobe * f
            dl = (gi0 * c[b, j, 0] + gi1 * c[b, j, 1] + gi2 * c[b, j, 2]) * f  # dL/dlobe
            if lobe == k[3]:  # underflow (or x at its floor): no gradient at all
                continue
            gs += dl * lobe * lx
            if xr < k[1] or xr > k[2]:  # clamped: no gradient to the normal or half vector
                continue
            dx = dl * s * (lobe / x)  # d(x^s)/dx = s x^(s-1), x > 0 here
            gns0 += dx * h0
            gns1 += dx * h1
            gns2 += dx * h2
            gh0, gh1, gh2 = _nrm3_bwd(h0, h1, h2, rh, dx * ns0, dx * ns1, dx * ns2)
            g_d[b, j, 0] += gh0
            g_d[b, j, 1] += gh1
            g_d[b, j, 2] += gh2
            gv0 += gh0
            gv1 += gh1
            gv2 += gh2
        if shin.shape[0] > 1:
            g_shin[i] = gs
        else:
            g_shin_global[0] += gs
        gvr0, gvr1, gvr2 = _nrm3_bwd(v0, v1, v2, rv, gv0, gv1, gv2)
        g_eye[b, 0] += gvr0
        g_eye[b, 1] += gvr1
        g_eye[b, 2] += gvr2
        g_p[i, 0] = -gvr0
        g_p[i, 1] = -gvr1
        g_p[i, 2] = -gvr2
        # ns = normalize(m0 t + m1 bt + m2 nd)
        gr0, gr1, gr2 = _nrm3_bwd(ns0, ns1, ns2, rs, gns0, gns1, gns2)
        m0, m1, m2 = nts[i, 0], nts[i, 1], nts[i, 2]
        g_nts[i, 0] = gr0 * t0 + gr1 * t1 + gr2 * t2
        g_nts[i, 1] = gr0 * b0 + gr1 * b1 + gr2 * b2
        g_nts[i, 2] = gr0 * nd0 + gr1 * nd1 + gr2 * nd2
        gt0, gt1, gt2 = m0 * gr0, m0 * gr1, m0 * gr2
        gnd0, gnd1, gnd2 = m2 * gr0, m2 * gr1, m2 * gr2
        w = tan[i, 3]
        gb0, gb1, gb2 = m1 * gr0 * w, m1 * gr1 * w, m1 * gr2 * w  # through bt = w (nd x t)
        g_tan[i, 3] = m1 * (gr0 * c0 + gr1 * c1 + gr2 * c2)
        gnd0 += t1 * gb2 - t2 * gb1  # d(nd x t)/dnd: t x g
        gnd1 += t2 * gb0 - t0 * gb2
        gnd2 += t0 * gb1 - t1 * gb0
        gt0 += gb1 * nd2 - gb2 * nd1  # d(nd x t)/dt: g x nd
        gt1 += gb2 * nd0 - gb0 * nd2
        gt2 += gb0 * nd1 - gb1 * nd0
        # t = normalize(tan - nd (tan . nd))
        gp0, gp1, gp2 = _nrm3_bwd(t0, t1, t2, rt, gt0, gt1, gt2)
        ndgp = nd0 * gp0 + nd1 * gp1 + nd2 * gp2
        g_tan[i, 0] = gp0 - nd0 * ndgp
        g_tan[i, 1] = gp1 - nd1 * ndgp
        g_tan[i, 2] = gp2 - nd2 * ndgp
        gnd0 += -a * gp0 - ndgp * tan[i, 0]
        gnd1 += -a * gp1 - ndgp * tan[i, 1]
        gnd2 += -a * gp2 - ndgp * tan[i, 2]
        g_nrm[i, 0], g_nrm[i, 1], g_nrm[i, 2] = _nrm3_bwd(nd0, nd1, nd2, rn, gnd0, gnd1, gnd2)


class _Specular(torch.autograd.Function):
    @staticmethod
    def forward(ctx, nts, nrm, tan, p, eye, d, c, shin, vis, bi):
        arrs = [x.detach().numpy() for x in (nts, nrm, tan, p, eye, d, c, shin, vis)]
        out = _buffer((nts.shape[0], 3), arrs[0].dtype)
        keep = np.empty((nts.shape[0], d.shape[1], 3), arrs[0].dtype)
        _spec_fwd(*arrs, bi.numpy(), out, keep, _spec_constants(arrs[0].dtype))
        ctx.save_for_backward(nts, nrm, tan, p, eye, d, c, shin, vis, bi)
        ctx.keep = keep
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g):
        saved = ctx.saved_tensors
        arrs = [x.detach().numpy() for x in saved[:9]]
        grads = [_buffer(x.shape, x.dtype) for x in arrs[:8]]
        _spec_bwd(*arrs, saved[9].numpy(), ctx.keep, np.ascontiguousarray(g.numpy()).astype(arrs[0].dtype, copy=False), *grads,
                  _spec_constants(arrs[0].dtype))
        return tuple(torch.from_numpy(x) if need else None
                     for x, need in zip(grads, ctx.needs_input_grad[:8])) + (None, None)


def specular_pixels(n_tangent: torch.Tensor, normal: torch.Tensor, tangent: torch.Tensor, points: torch.Tensor,
                    eye: torch.Tensor, direction: torch.Tensor, colour: torch.Tensor, shininess: torch.Tensor,
                    visibility: torch.Tensor | None, batch_index: torch.Tensor) -> torch.Tensor:
    """Fused ``specular_reflectance(tangent_to_world(n_tangent, tangent, normal), normal, ...)`` for
    directional lights, per pixel: (N, 3) each of n_tangent, normal, points; tangent (N, 4); eye (B, 3);
    direction (unit), colour (B, L, 3); shininess (N,) or (1,); visibility (N, L) or None; batch_index
    (N,) int64 -> (N, 3). All float tensors of one dtype, on the CPU."""
    dt = normal.dtype
    vis = visibility if visibility is not None else torch.ones(1, 1, dtype=dt)
    args = [x.to(dt).contiguous() for x in (n_tangent, normal, tangent, points, eye, direction, colour, shininess)]
    return _Specular.apply(*args, vis.to(dt).contiguous(), batch_index.contiguous())


# --- barycentrics ----------------------------------------------------------------------------------
# ``raster._barycentrics_torch`` is ~25 ops each way over the covered pixels; one loop each way here.
# Same formulas, same guards: |area| < 1e-12 -> -1e-12 (no gradient), depth clamped at 1e-6, a
# near-zero perspective sum leaves the weights unnormalised.

_AREA_MIN = 1e-12
_Z_MIN = 1e-6


@numba.njit(cache=True, nogil=True, inline="always")
def _bary_screen(px, b, f0, f1, f2, qx, qy):
    ax, ay, bx, by, cx, cy = px[b, f0, 0], px[b, f0, 1], px[b, f1, 0], px[b, f1, 1], px[b, f2, 0], px[b, f2, 1]
    area = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
    clamped = abs(area) < _AREA_MIN
    if clamped:
        area = -_AREA_MIN
    e0 = (bx - qx) * (cy - qy) - (cx - qx) * (by - qy)
    e1 = (cx - qx) * (ay - qy) - (ax - qx) * (cy - qy)
    w0 = e0 / area
    w1 = e1 / area
    return ax, ay, bx, by, cx, cy, area, clamped, w0, w1, 1.0 - w0 - w1


@numba.njit(cache=True, nogil=True)
def _bary_fwd(px, tri, index, perspective, out):
    for n in range(index.shape[0]):
        b = index[n, 0]
        qx, qy = index[n, 2] + 0.5, index[n, 1] + 0.5
        f0, f1, f2 = tri[n, 0], tri[n, 1], tri[n, 2]
        w0, w1, w2 = _bary_screen(px, b, f0, f1, f2, qx, qy)[8:]
        if perspective:
            w0 /= max(px[b, f0, 2], _Z_MIN)
            w1 /= max(px[b, f1, 2], _Z_MIN)
            w2 /= max(px[b, f2, 2], _Z_MIN)
            s = w0 + w1 + w2
            if abs(s) > 1e-12:
                w0, w1, w2 = w0 / s, w1 / s, w2 / s
        out[n, 0], out[n, 1], out[n, 2] = w0, w1, w2


@numba.njit(cache=True, nogil=True)
def _bary_bwd(px, tri, index, perspective, g, g_px):
    for n in range(index.shape[0]):
        b = index[n, 0]
        qx, qy = index[n, 2] + 0.5, index[n, 1] + 0.5
        f0, f1, f2 = tri[n, 0], tri[n, 1], tri[n, 2]
        ax, ay, bx, by, cx, cy, area, clamped, w0, w1, w2 = _bary_screen(px, b, f0, f1, f2, qx, qy)
        g0, g1, g2 = g[n, 0], g[n, 1], g[n, 2]
        if perspective:
            z0, z1, z2 = px[b, f0, 2], px[b, f1, 2], px[b, f2, 2]
            zc0, zc1, zc2 = max(z0, _Z_MIN), max(z1, _Z_MIN), max(z2, _Z_MIN)
            p0, p1, p2 = w0 / zc0, w1 / zc1, w2 / zc2
            s = p0 + p1 + p2
            if abs(s) > 1e-12:  # W_k = p_k / s: dL/dp_k = (g_k - sum_j g_j W_j) / s
                dot = (g0 * p0 + g1 * p1 + g2 * p2) / s
                g0, g1, g2 = (g0 - dot) / s, (g1 - dot) / s, (g2 - dot) / s
            if z0 >= _Z_MIN:
                g_px[b, f0, 2] -= g0 * p0 / zc0
            if z1 >= _Z_MIN:
                g_px[b, f1, 2] -= g1 * p1 / zc1
            if z2 >= _Z_MIN:
                g_px[b, f2, 2] -= g2 * p2 / zc2
            g0, g1, g2 = g0 / zc0, g1 / zc1, g2 / zc2
        # w2 = 1 - w0 - w1
        d0 = (g0 - g2) / area  # dL/de0
        d1 = (g1 - g2) / area  # dL/de1
        da = 0.0 if clamped else -(d0 * w0 + d1 * w1)  # dL/darea, from w = e / area
        # e0 = (bx - qx)(cy - qy) - (cx - qx)(by - qy); e1 = (cx - qx)(ay - qy) - (ax - qx)(cy - qy)
        # area = (bx - ax)(cy - ay) - (cx - ax)(by - ay)
        g_px[b, f0, 0] += -d1 * (cy - qy) + da * (by - cy)
        g_px[b, f0, 1] += d1 * (cx - qx) + da * (cx - bx)
        g_px[b, f1, 0] += d0 * (cy - qy) + da * (cy - ay)
        g_px[b, f1, 1] += -d0 * (cx - qx) - da * (cx - ax)
        g_px[b, f2, 0] += -d0 * (by - qy) + d1 * (ay - qy) - da * (by - ay)
        g_px[b, f2, 1] += d0 * (bx - qx) - d1 * (ax - qx) + da * (bx - ax)


class _Barycentrics(torch.autograd.Function):
    @staticmethod
    def forward(ctx, px, tri, index, perspective):
        p = px.detach().contiguous().numpy()
        out = _buffer((index.shape[0], 3), p.dtype, zero=False)
        _bary_fwd(p, tri.numpy(), index.numpy(), perspective, out)
        ctx.save_for_backward(px, tri, index)
        ctx.perspective = perspective
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g):
        px, tri, index = ctx.saved_tensors
        p = px.detach().contiguous().numpy()
        g_px = _buffer(p.shape, p.dtype)
        _bary_bwd(p, tri.numpy(), index.numpy(), ctx.perspective, np.ascontiguousarray(g.numpy()), g_px)
        return torch.from_numpy(g_px), None, None, None


def barycentric_weights(px: torch.Tensor, tri: torch.Tensor, index: torch.Tensor, perspective: bool) -> torch.Tensor:
    """px: (B, V, 3) float CPU; tri: (N, 3) int64 vertex ids of each covered pixel's triangle; index: (N, 3)
    int64 (b, i, j) -> (N, 3) weights of the pixel centres (``raster.barycentrics``)."""
    return _Barycentrics.apply(px, tri.contiguous(), index.contiguous(), bool(perspective))


# --- sRGB encoding -----------------------------------------------------------------------------------
# ``shading._linear_to_srgb_torch`` is clamp, where, pow (and as many ops back): ~3 ms of a 256^2
# render + backward. Same function and the same one-sided choices at the kinks (0, 0.0031308, 1).
# The arithmetic runs in the input's precision (``_srgb_constants``): float32 images take powf, 3x
# faster than pow (2.9 -> 0.9 ms for 196k values; within 2.5e-7, two float32 ulps at 1, of float64). The backward
# needs no power: d/dv (1.055 v^(1/2.4) - 0.055) = (y + 0.055) / (2.4 v), from the saved output y.

_SRGB_KNEE = 0.0031308


def _srgb_constants(dtype) -> np.ndarray:
    """0, 1, knee, 12.92, 1.055, 0.055, 1/2.4, 2.4 in ``dtype``: numba then keeps the loop in that precision."""
    return np.array([0.0, 1.0, _SRGB_KNEE, 12.92, 1.055, 0.055, 1 / 2.4, 2.4], dtype)


@numba.njit(cache=True, nogil=True)
def _srgb_fwd(x, k, out):
    zero, one, knee, lin, a, b, e = k[0], k[1], k[2], k[3], k[4], k[5], k[6]
    for i in range(x.shape[0]):
        v = min(max(x[i], zero), one)
        out[i] = lin * v if v <= knee else a * v ** e - b


@numba.njit(cache=True, nogil=True)
def _srgb_bwd(x, y, g, k, out):
    zero, one, knee, lin, b, gamma = k[0], k[1], k[2], k[3], k[5], k[7]
    for i in range(x.shape[0]):
        v = x[i]
        if v < zero or v > one:
            out[i] = zero
        elif v <= knee:
            out[i] = lin * g[i]
        else:
            out[i] = g[i] * ((y[i] + b) / (gamma * v))


class _Srgb(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        a = x.detach().contiguous().view(-1).numpy()
        out = _buffer(a.shape, a.dtype, zero=False)
        _srgb_fwd(a, _srgb_constants(a.dtype), out)
        y = torch.from_numpy(out).view(x.shape)
        ctx.save_for_backward(x, y)
        return y

    @staticmethod
    def backward(ctx, g):
        x, y = ctx.saved_tensors
        a = x.detach().contiguous().view(-1).numpy()
        out = _buffer(a.shape, a.dtype, zero=False)
        _srgb_bwd(a, y.detach().contiguous().view(-1).numpy(), np.ascontiguousarray(g.numpy()).reshape(-1).astype(a.dtype, copy=False),
                  _srgb_constants(a.dtype), out)
        return torch.from_numpy(out).view(x.shape)


def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    """Linear [0, inf) -> sRGB [0, 1], clipped; float32/64 CPU tensors of any shape (``shading.linear_to_srgb``)."""
    return _Srgb.apply(x)
