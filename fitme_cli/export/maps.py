"""Full-head texture maps for export: holes filled, the back seam made continuous, upsampled with care,
and encoded as EXR and PNG.

The avatar's maps (256^2 for the shipped generator) are in the shape model's cylindrical UV layout
(row 0 = v = 1; the face at u = 0.5; u = 0 and u = 1 meet at the back of the head). Steps:

1. **Fill**: texels no triangle of the export mesh covers (UV gutters, the pole at the top) are
   replaced by a push-pull fill from the covered ones, so bilinear filtering and mipmaps at a UV border
   never pull in unrelated (or black) values. Non-finite texels are filled the same way. Before that,
   a margin of ``MapSettings.border_texels`` along the map's four edges is replaced by the mirror image
   of the texels next to it: a convolutional generator's outermost texels carry padding artefacts (the
   shipped one draws a bright, green-tinged stripe in its last columns, which on the head is a line down
   the back). Mirroring keeps the texture (hair strands) that a smooth fill would wash out.
2. **Seam**: the columns at u = 0 and u = 1 are neighbours on the head, but a generator does not know
   that; a band on each side is cross-faded so both edges meet at their mean (samplers wrap u).
3. **Upsample** to the export size: Lanczos-4 for the albedos, each output clamped into the range of
   the source texels around it (the kernel's ringing would otherwise draw halos around hair strands
   and undershoot to black next to dark ones), bicubic for the normals, then
   renormalised with z kept on the outer hemisphere. The image is padded by wrapping in u and by
   repeating edges in v first, so the seam stays continuous and borders are not darkened.

Encodings (docs/export.md): albedo EXR half-float linear RGB, PNG 8-bit sRGB; specular EXR half-float
linear grey (R = G = B), PNG 8-bit sRGB grey (glTF's KHR_materials_specular reads it as
``specularColorTexture``, an sRGB colour); normals tangent space, OpenGL convention (+x along
u, +y along v, i.e. up in the image, +z out), EXR half-float and 16-bit PNG of n * 0.5 + 0.5 (linear).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["MapSettings", "SourceMaps", "ExportMaps", "uv_coverage", "push_pull_fill", "blend_u_seam",
           "mirror_margins", "upsample", "prepare_maps", "encode_png", "exr_arrays", "MAP_NAMES"]

MAP_NAMES = ("albedo", "specular", "normals")


@dataclass(frozen=True)
class MapSettings:
    """resolution: side of the exported maps (a power of two, 64..4096); seam_band: width of the
    cross-fade at u = 0 and u = 1, as a fraction of the source width; border_texels: source texels
    along each edge that are refilled (generator padding artefacts), per 256 texels of source width."""

    resolution: int = 1024
    seam_band: float = 0.03
    border_texels: int = 4

    def __post_init__(self) -> None:
        r = self.resolution
        if not isinstance(r, int) or r < 64 or r > 4096 or r & (r - 1):
            raise ValueError(f"resolution must be a power of two from 64 to 4096, got {r!r}")
        if not 0.0 <= self.seam_band <= 0.25:
            raise ValueError(f"seam_band must be in [0, 0.25], got {self.seam_band!r}")
        if not isinstance(self.border_texels, int) or not 0 <= self.border_texels <= 16:
            raise ValueError(f"border_texels must be an integer in [0, 16], got {self.border_texels!r}")


@dataclass(frozen=True, eq=False)
class SourceMaps:
    """Maps as the avatar holds them: albedo (R, R, 3) linear [0, 1]; specular (R, R) linear [0, 1];
    normals (R, R, 3) unit tangent-space vectors (not encoded). float32, row 0 = v = 1."""

    albedo: np.ndarray
    specular: np.ndarray
    normals: np.ndarray

    def __post_init__(self) -> None:
        r = self.albedo.shape[0]
        for name, shape in (("albedo", (r, r, 3)), ("specular", (r, r)), ("normals", (r, r, 3))):
            got = getattr(self, name).shape
            if got != shape:
                raise ValueError(f"SourceMaps.{name}: expected shape {shape}, got {got}")


@dataclass(frozen=True, eq=False)
class ExportMaps:
    """The exported maps at ``MapSettings.resolution`` (S), float32, same conventions as SourceMaps;
    coverage: (S, S) bool, texels the mesh covers (with u wrapped); filled_fraction: share of the
    source texels replaced (the mirrored margins, and texels not covered by the mesh or not finite)."""

    albedo: np.ndarray
    specular: np.ndarray
    normals: np.ndarray
    coverage: np.ndarray
    filled_fraction: float

    @property
    def resolution(self) -> int:
        return int(self.albedo.shape[0])


def uv_coverage(uv: np.ndarray, uv_faces: np.ndarray, size: int) -> np.ndarray:
    """(size, size) bool: texels whose centre some UV triangle covers (row 0 = v = 1). Triangles past
    u = 1 (the seam) are also drawn shifted by -1, as a wrapping sampler reads them."""
    if uv.ndim != 2 or uv.shape[1] != 2 or uv_faces.ndim != 2 or uv_faces.shape[1] != 3:
        raise ValueError(f"expected uv (T, 2) and uv_faces (F, 3), got {uv.shape} and {uv_faces.shape}")
    shift = 4  # sub-pixel bits of cv2's rasteriser
    out = np.zeros((size, size), np.uint8)
    px = np.stack([uv[:, 0] * size - 0.5, (1.0 - uv[:, 1]) * size - 0.5], 1)  # texel-centre coordinates
    tris = px[uv_faces]  # (F, 3, 2)
    polys = [tris]
    wrapped = tris[(tris[..., 0] > size - 0.5).any(1)]
    if len(wrapped):
        polys.append(wrapped - [size, 0.0])
    for p in polys:
        pts = np.round(p * (1 << shift)).astype(np.int32)
        cv2.fillPoly(out, list(pts), 1, cv2.LINE_8, shift)
    return out.astype(bool)


def push_pull_fill(img: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill the texels where ``valid`` is False from the valid ones: an image pyramid of valid-weighted
    means ("push"), then each level's holes taken from the next coarser level ("pull"). Smooth, and
    it never invents values outside the range of the valid texels. img: (H, W) or (H, W, C) float."""
    if img.shape[:2] != valid.shape:
        raise ValueError(f"img {img.shape[:2]} and valid {valid.shape} differ in size")
    if not valid.any():
        raise ValueError("push_pull_fill: no valid texel to fill from")
    squeeze = img.ndim == 2
    x = np.asarray(img, np.float64)
    x = x[..., None] if squeeze else x
    w = valid.astype(np.float64)
    x = np.where(valid[..., None], x, 0.0)  # non-finite values in holes must not leak into sums
    levels = [(x * w[..., None], w)]
    while max(levels[-1][1].shape) > 1:
        xs, ws = levels[-1]
        h, wd = ws.shape
        ph, pw = h % 2, wd % 2  # odd sizes: pad with zero weight
        xs = np.pad(xs, ((0, ph), (0, pw), (0, 0)))
        ws = np.pad(ws, ((0, ph), (0, pw)))
        xs = xs.reshape(xs.shape[0] // 2, 2, xs.shape[1] // 2, 2, -1).sum((1, 3))
        ws = ws.reshape(ws.shape[0] // 2, 2, ws.shape[1] // 2, 2).sum((1, 3))
        levels.append((xs, ws))
    # pull: from the coarsest level down, holes take the (bilinearly) upsampled coarser mean
    xs, ws = levels[-1]
    mean = xs / np.maximum(ws, 1e-12)[..., None]
    for xs, ws in reversed(levels[:-1]):
        h, wd = ws.shape
        hh, ww = mean.shape[0] * 2, mean.shape[1] * 2
        up = cv2.resize(mean, (ww, hh), interpolation=cv2.INTER_LINEAR).reshape(hh, ww, -1)[:h, :wd]
        own = xs / np.maximum(ws, 1e-12)[..., None]
        a = np.clip(ws, 0.0, 1.0)[..., None]  # a full-weight texel keeps its own value
        mean = a * own + (1 - a) * up
    out = np.where(valid[..., None], np.asarray(img, np.float64).reshape(x.shape), mean)
    return (out[..., 0] if squeeze else out).astype(np.float32)


def mirror_margins(x: np.ndarray, m: int) -> np.ndarray:
    """Replace ``m`` texels along each of the four edges by the mirror image of the next ``m``: column 0
    takes column 2m - 1, column m - 1 takes column m (likewise for the last columns and the rows)."""
    if m <= 0:
        return x.copy()
    if 2 * m > min(x.shape[:2]):
        raise ValueError(f"margin {m} is too wide for a {x.shape[0]}x{x.shape[1]} map")
    x = x.copy()
    x[:, :m] = x[:, m : 2 * m][:, ::-1]
    x[:, -m:] = x[:, -2 * m : -m][:, ::-1]
    x[:m] = x[m : 2 * m][::-1]
    x[-m:] = x[-2 * m : -m][::-1]
    return x


def blend_u_seam(img: np.ndarray, band: int) -> np.ndarray:
    """Cross-fade ``band`` columns at each side so that column 0 and column W-1 (neighbours across the
    back seam) both become their mean; the correction fades linearly into the map. The per-row
    difference is smoothed vertically first, so texel noise is not copied into the band."""
    if band < 1:
        return img.astype(np.float32)
    x = np.asarray(img, np.float32).copy()
    d = x[:, 0] - x[:, -1]  # (H,) or (H, C)
    d = cv2.GaussianBlur(d.reshape(d.shape[0], -1), (1, 0), 0, sigmaY=2.0, borderType=cv2.BORDER_REFLECT).reshape(d.shape)
    ramp = 0.5 * (1.0 - np.arange(band, dtype=np.float32) / band)  # 0.5 at the edge -> 0 inside
    shape = (1, band) + (1,) * (x.ndim - 2)
    x[:, :band] -= d[:, None] * ramp.reshape(shape)
    x[:, -band:] += d[:, None] * ramp[::-1].reshape(shape)
    return x


def upsample(img: np.ndarray, size: int, interpolation: int, antiring: bool = False) -> np.ndarray:
    """(R, R[, C]) -> (size, size[, C]) float32, padded by wrapping in u and repeating edges in v so the
    kernel sees the head's neighbours across the back seam. ``size`` a multiple of R (or R itself).
    ``antiring``: clamp each output texel into the range of the 3 x 3 source texels around it, so a
    sharp kernel (Lanczos) adds no halo: no texel brighter or darker than its neighbourhood, and no
    black specks where it would undershoot below zero next to dark hair."""
    r = img.shape[0]
    if size == r:
        return img.astype(np.float32)
    if size % r:
        raise ValueError(f"upsample: {size} is not a multiple of the source size {r}")
    k, p = size // r, 4  # Lanczos-4 reads 4 texels each side
    extra = ((0, 0),) * (img.ndim - 2)
    x = np.pad(img.astype(np.float32), ((p, p), (0, 0)) + extra, mode="edge")
    x = np.pad(x, ((0, 0), (p, p)) + extra, mode="wrap")

    def up(a: np.ndarray, how: int) -> np.ndarray:
        y = cv2.resize(a, (a.shape[1] * k, a.shape[0] * k), interpolation=how).reshape(a.shape[0] * k, a.shape[1] * k, -1)
        return y[p * k : p * k + size, p * k : p * k + size].reshape((size, size) + img.shape[2:])

    y = up(x, interpolation)
    if antiring:
        kernel = np.ones((2, 2), np.uint8)  # the two anchors together: the 3 x 3 texels around each output
        lo = up(cv2.erode(x, kernel, anchor=(0, 0)), cv2.INTER_NEAREST)
        hi = up(cv2.dilate(x, kernel, anchor=(0, 0)), cv2.INTER_NEAREST)
        lo2 = up(cv2.erode(x, kernel, anchor=(1, 1)), cv2.INTER_NEAREST)
        hi2 = up(cv2.dilate(x, kernel, anchor=(1, 1)), cv2.INTER_NEAREST)
        y = np.clip(y, np.minimum(lo, lo2), np.maximum(hi, hi2))
    return np.ascontiguousarray(y, dtype=np.float32)


def _unit_normals(n: np.ndarray) -> np.ndarray:
    n = n.astype(np.float32).copy()
    n[..., 2] = np.maximum(n[..., 2], 1e-3)  # tangent-space detail normals face out of the surface
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def prepare_maps(source: SourceMaps, uv: np.ndarray, uv_faces: np.ndarray, settings: MapSettings = MapSettings()) -> ExportMaps:
    """Fill, blend the seam and upsample the source maps for a mesh with texture coordinates ``uv``
    (T, 2) and triangles ``uv_faces`` (F, 3) (see the module docstring)."""
    r = source.albedo.shape[0]
    size = settings.resolution
    if size < r:
        raise ValueError(f"export resolution {size} is below the avatar's maps ({r}); downsampling is not supported")
    stack = np.concatenate([source.albedo, source.specular[..., None], source.normals], -1).astype(np.float32)
    finite = np.isfinite(stack).all(-1)
    valid = uv_coverage(uv, uv_faces, r) & finite
    m = int(round(settings.border_texels * r / 256))
    stack, valid = mirror_margins(stack, m), mirror_margins(valid, m)  # a margin texel is as good as its source
    kept = valid.copy()
    if m:
        kept[:m], kept[-m:], kept[:, :m], kept[:, -m:] = False, False, False, False
    if not valid.any():
        raise ValueError("no texel of the maps is both covered by the mesh and finite")
    filled = push_pull_fill(stack, valid)
    filled = blend_u_seam(filled, int(round(settings.seam_band * r)))
    albedo = np.clip(upsample(filled[..., :3], size, cv2.INTER_LANCZOS4, antiring=True), 0.0, 1.0)
    specular = np.clip(upsample(filled[..., 3], size, cv2.INTER_LANCZOS4, antiring=True), 0.0, 1.0)
    normals = _unit_normals(upsample(_unit_normals(filled[..., 4:7]), size, cv2.INTER_CUBIC))
    return ExportMaps(albedo, specular, normals, uv_coverage(uv, uv_faces, size), float(1.0 - kept.mean()))


def _srgb8(linear: np.ndarray) -> np.ndarray:
    from ..io.maps import linear_to_srgb

    return np.round(linear_to_srgb(linear) * 255).astype(np.uint8)


def encode_png(maps: ExportMaps, name: str) -> bytes:
    """The PNG file of map ``name`` (see the module docstring for each encoding)."""
    if name == "albedo":
        arr = _srgb8(maps.albedo)[..., ::-1]  # cv2 writes BGR
    elif name == "specular":
        arr = np.repeat(_srgb8(maps.specular)[..., None], 3, -1)  # grey: glTF reads it as an sRGB colour
    elif name == "normals":
        arr = np.round(np.clip(maps.normals * 0.5 + 0.5, 0, 1) * 65535).astype(np.uint16)[..., ::-1]
    else:
        raise ValueError(f"unknown map {name!r}; expected one of {', '.join(MAP_NAMES)}")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr), [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise ValueError(f"PNG encoding of {name} failed")
    return buf.tobytes()


def exr_arrays(maps: ExportMaps) -> dict[str, np.ndarray]:
    """The (S, S, 3) float16 arrays the EXR files hold, exactly: albedo, specular (grey RGB), normals
    encoded n * 0.5 + 0.5 (as the avatar's maps and as normal-map nodes expect)."""
    return {"albedo": maps.albedo.astype(np.float16),
            "specular": np.repeat(maps.specular[..., None], 3, -1).astype(np.float16),
            "normals": (maps.normals * 0.5 + 0.5).astype(np.float16)}
