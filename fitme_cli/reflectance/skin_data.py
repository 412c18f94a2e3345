"""Procedural capture-quality facial reflectance maps (training data for the BRDF-GAN).

Each sample is three maps in the shape model's UV layout (row 0 = v = 1, face centred at u = 0.5):

- ``albedo``   A_D: (H, W, 3) float32 diffuse albedo, linear light, in [0, 1];
- ``specular`` A_S: (H, W) float32 specular albedo, linear, in [0, 1];
- ``normals``  N_S: (H, W, 3) float32 unit tangent-space normals: +x along +u, +y along +v (up in the
  image, OpenGL convention), +z out of the surface. Written as n * 0.5 + 0.5.

How a sample is made (all sizes in UV units, so features scale with the map size; 1 UV unit is about
400 mm on the face):

1. A height field h(u, v) (in UV units): region-dependent pores (large on the nose and cheeks, finer on
   the forehead, very fine on lips and neck), crossed fine wrinkles (oriented noise), age-dependent
   forehead lines, crow's feet (from the outer eye corners) and nasolabial folds (nose alar to mouth
   corners), vertical lip lines, moles, and strand textures where there is hair. Normals are its
   gradient.
2. Diffuse albedo from the biophysical model (``biophysical.skin_rgb``): per-texel melanin and
   haemoglobin fields = a per-sample base + low-frequency noise + anatomy (red lips, cheeks and nose,
   darker under the eyes, freckles, age spots, moles), then darkening in the height field's cavities
   (the same pores and wrinkles as the normals), then hair composited on top (scalp, brows, lashes,
   stubble/beard) with its own colour, greying with age.
3. Specular albedo: high on the T-zone and lips, low over hair, lower in pores and wrinkle valleys.

Deterministic: sample ``index`` of ``seed`` uses only ``np.random.default_rng([seed, index])``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .biophysical import skin_rgb

__all__ = [
    "SkinDataSettings",
    "SkinSample",
    "SkinLayout",
    "skin_layout",
    "generate_sample",
    "skin_rgb",
    "write_sample",
    "sample_files",
    "MapStats",
    "settings_dict",
]

# FaceMesh contours
_LIPS_OUTER = [61, 146, 91, 181, 84, 17, 314, 405, 321, 375, 291, 409, 270, 269, 267, 0, 37, 39, 40, 185]
_LIPS_INNER = [78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308, 415, 310, 311, 312, 13, 82, 81, 80, 191]
_EYE_R = [33, 7, 163, 144, 145, 153, 154, 155, 133, 173, 157, 158, 159, 160, 161, 246]
_EYE_L = [263, 249, 390, 373, 374, 380, 381, 382, 362, 398, 384, 385, 386, 387, 388, 466]
_BROW_R = [70, 63, 105, 66, 107, 55, 65, 52, 53, 46]
_BROW_L = [300, 293, 334, 296, 336, 285, 295, 282, 283, 276]

_HAIR_COLOURS = {  # linear diffuse albedo of hair in bulk
    "black": (0.018, 0.014, 0.012),
    "dark_brown": (0.045, 0.028, 0.018),
    "brown": (0.11, 0.066, 0.038),
    "light_brown": (0.22, 0.14, 0.08),
    "blond": (0.42, 0.31, 0.17),
    "auburn": (0.20, 0.07, 0.03),
}
_GREY = np.array([0.48, 0.47, 0.45], np.float32)


@dataclass(frozen=True)
class SkinDataSettings:
    """Generator settings (frozen; all per-sample randomness is drawn inside these ranges).

    size: map side in texels, a power of two in 64..4096. melanin_range: range of the normalised
    melanin parameter (0 = lighter than Monk 1, 1 = Monk 10), sampled as lo + (hi - lo) U^melanin_skew,
    U uniform: skew 1 gives roughly equal numbers of samples per Monk level, the default 1.5 leans
    lighter (as capture datasets do: 37 % of samples below m = 0.2, 27 % above 0.6). age_range: 0 = young adult, 1 = elderly (wrinkles, age
    spots, grey hair). beard_probability: chance of stubble or a beard (density and length random).
    freckle_probability: chance of freckles (more likely on light skin). detail: scale of all height
    detail (pores, wrinkles) in the normals."""

    size: int = 512
    melanin_range: tuple[float, float] = (0.0, 1.0)
    melanin_skew: float = 1.5
    age_range: tuple[float, float] = (0.0, 1.0)
    beard_probability: float = 0.4
    freckle_probability: float = 0.35
    detail: float = 1.0

    def __post_init__(self):
        if not isinstance(self.size, int) or self.size < 64 or self.size > 4096 or self.size & (self.size - 1):
            raise ValueError(f"size must be a power of two from 64 to 4096, got {self.size!r}")
        for name in ("melanin_range", "age_range"):
            lo, hi = getattr(self, name)
            if not 0.0 <= lo <= hi <= 1.0:
                raise ValueError(f"{name} must be (lo, hi) with 0 <= lo <= hi <= 1, got {getattr(self, name)!r}")
        for name in ("beard_probability", "freckle_probability"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)!r}")
        if not 0.25 <= self.melanin_skew <= 4.0:
            raise ValueError(f"melanin_skew must be in [0.25, 4], got {self.melanin_skew!r}")
        if not 0.0 <= self.detail <= 4.0:
            raise ValueError(f"detail must be in [0, 4], got {self.detail!r}")


@dataclass(frozen=True)
class SkinSample:
    albedo: np.ndarray  # (H, W, 3) float32 linear [0, 1]
    specular: np.ndarray  # (H, W) float32 linear [0, 1]
    normals: np.ndarray  # (H, W, 3) float32 unit, tangent space (+x = u, +y = v up, +z out)
    params: dict = field(default_factory=dict)  # sampled parameters, JSON-able


@dataclass(frozen=True, eq=False)
class SkinLayout:
    """Everything about the UV layout at one size that does not change between samples.

    masks: {region: (S, S) bool} from ``region_masks`` plus "mapped". lm: (468, 2) float32 landmark
    positions in texels (x = column, y = row). soft: {name: (S, S) float32 in [0, 1]} smooth anatomical
    weights. hair_dist: (S, S) float32 signed distance into the scalp in UV units (< 0 outside it)."""

    size: int
    masks: dict
    lm: np.ndarray
    soft: dict
    hair_dist: np.ndarray
    hair_angle: np.ndarray  # (S, S) float32 hair flow direction on the scalp, radians (image x, y)

    def px(self, uv_len: float) -> float:
        return uv_len * self.size


# ---------------------------------------------------------------------------------------------- layout


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    if sigma_px < 0.3:
        return img.astype(np.float32)
    return cv2.GaussianBlur(img.astype(np.float32), (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)


def _gauss(xx, yy, c, sx, sy):
    return np.exp(-0.5 * (((xx - c[0]) / sx) ** 2 + ((yy - c[1]) / sy) ** 2)).astype(np.float32)


def _poly_mask(size, pts) -> np.ndarray:
    m = np.zeros((size, size), np.uint8)
    cv2.fillPoly(m, [np.round(pts * 16).astype(np.int32)], 1, cv2.LINE_AA, 4)
    return m.astype(np.float32)


@functools.lru_cache(maxsize=8)
def _layout_cached(model_file: str, size: int) -> SkinLayout:
    from safetensors.numpy import load_file

    from ..shape.regions import region_masks

    d = load_file(model_file)
    tri, uvf, uv = d["triangles"], d["uv_faces"], d["uv"]
    vuv = np.zeros((int(tri.max()) + 1, 2), np.float64)
    vuv[tri.ravel()] = uv[uvf.ravel()]
    luv = vuv[d["landmarks"]]
    lm = np.stack([luv[:, 0] * size, (1.0 - luv[:, 1]) * size], 1).astype(np.float32)
    masks = region_masks(d["region_uv"], size)
    S = size
    yy, xx = np.mgrid[0:S, 0:S].astype(np.float32)
    u = (xx + 0.5) / S
    px = lambda a: a * S  # noqa: E731
    f = lambda name: masks[name].astype(np.float32)  # noqa: E731
    face_hard = sum(f(n) for n in ("skin", "forehead", "brows", "eyes", "nose", "lips"))
    soft = {}
    soft["face"] = _blur(face_hard, px(0.006))
    soft["neck"] = _blur(f("neck"), px(0.006))
    soft["forehead"] = _blur(f("forehead"), px(0.01))
    soft["nose"] = np.maximum(_blur(f("nose"), px(0.006)), _gauss(xx, yy, lm[4], px(0.022), px(0.018)))
    lips = _poly_mask(S, lm[_LIPS_OUTER])
    soft["lips"] = _blur(lips, px(0.0018))
    soft["mouth_line"] = _blur(_poly_mask(S, lm[_LIPS_INNER]), px(0.0012))
    soft["lips_zone"] = _blur(lips, px(0.008))
    brows = np.maximum(_poly_mask(S, lm[_BROW_R]), _poly_mask(S, lm[_BROW_L]))
    soft["brows"] = _blur((_blur(brows, px(0.003)) > 0.25).astype(np.float32), px(0.0025))
    eyes_in = np.maximum(_poly_mask(S, lm[_EYE_R]), _poly_mask(S, lm[_EYE_L]))
    soft["eye_inside"] = _blur(eyes_in, px(0.001))
    # lash line: a thin band just outside the eye opening, wider on the upper lid
    ring_up = np.zeros((S, S), np.uint8)
    ring_lo = np.zeros((S, S), np.uint8)
    for eye in (_EYE_R, _EYE_L):
        pts = np.round(lm[eye] * 16).astype(np.int32)
        upper, lower = pts[8:].tolist() + [pts[0].tolist()], pts[:9]
        cv2.polylines(ring_up, [np.array(upper, np.int32)], False, 1, max(1, int(round(px(0.005)))), cv2.LINE_AA, 4)
        cv2.polylines(ring_lo, [lower], False, 1, max(1, int(round(px(0.0025)))), cv2.LINE_AA, 4)
    soft["lash"] = _blur(np.maximum(ring_up, 0.6 * ring_lo).astype(np.float32), px(0.0012))
    soft["eyes"] = _blur(f("eyes"), px(0.004))
    # cheeks and their redness, under-eye darkening, T-zone
    cheeks = np.maximum(_gauss(xx, yy, lm[205], px(0.028), px(0.024)), _gauss(xx, yy, lm[425], px(0.028), px(0.024)))
    cheeks = np.maximum(cheeks, 0.7 * np.maximum(_gauss(xx, yy, lm[50], px(0.02), px(0.016)), _gauss(xx, yy, lm[280], px(0.02), px(0.016))))
    soft["cheeks"] = cheeks * soft["face"]
    down = px(0.012)
    soft["under_eye"] = np.maximum(_gauss(xx, yy, lm[145] + (0, down), px(0.017), px(0.007)),
                                   _gauss(xx, yy, lm[374] + (0, down), px(0.017), px(0.007))) * soft["face"]
    fh_c = (lm[9] + lm[10]) / 2
    soft["tzone"] = np.clip(_gauss(xx, yy, fh_c, px(0.045), px(0.05)) + soft["nose"]
                            + 0.5 * _gauss(xx, yy, lm[152] + (0, -px(0.01)), px(0.02), px(0.015)), 0, 1) * soft["face"]
    # beard zone: below a line from the sideburn (234/454) down to just under the nose
    cx = S / 2
    half = abs(lm[454, 0] - cx)
    dx = np.abs(xx - cx) / half
    nose_base = lm[2, 1] + px(0.004)
    top = nose_base + (lm[234, 1] - px(0.01) - nose_base) * _smoothstep(0.3, 0.95, dx)
    top = np.where(dx < 0.3, nose_base, top)
    top = top + px(0.03) * _smoothstep(0.25, 0.55, dx) * (1 - _smoothstep(0.6, 0.98, dx))  # cheek line dips
    zone = _smoothstep(-px(0.004), px(0.014), yy - top)
    neck_fade = np.exp(-np.maximum(yy - (lm[152, 1] + px(0.01)), 0) / px(0.035))
    beard = zone * np.clip(soft["face"] + soft["neck"] * neck_fade * (1 - _smoothstep(0.8, 1.15, dx)), 0, 1)
    beard *= (1 - _blur((_blur(lips, px(0.0025)) > 0.1).astype(np.float32), px(0.0015)))
    beard *= 1 - soft["nose"] * (yy < nose_base + px(0.002))
    soft["beard"] = np.clip(beard, 0, 1).astype(np.float32)
    soft["skin_detail"] = np.clip(soft["face"] + soft["neck"], 0, 1)
    # hair: distance into the scalp (unmapped corners count as scalp); the hairline moves back beside
    # the lower face, where the scalp region stands for ears and the back of the jaw
    # (the label map's jagged borders and islands are smoothed away first; unmapped texels count as
    # scalp above the chin, as neck below it)
    scalp = masks["scalp"] | (~masks["mapped"] & (yy < lm[152, 1]))
    scalp = _blur(scalp.astype(np.float32), px(0.008)) > 0.5
    dist = (cv2.distanceTransform(scalp.astype(np.uint8), cv2.DIST_L2, 5)
            - cv2.distanceTransform((~scalp).astype(np.uint8), cv2.DIST_L2, 5)) / S  # signed
    side = _smoothstep(lm[33, 1], lm[61, 1], yy) * (1 - _smoothstep(0.2, 0.3, np.abs(u - 0.5)))
    hair_dist = (dist - 0.045 * side).astype(np.float32)
    # hair flow: away from the crown (top centre), down the sides; brows point outwards
    ang = np.arctan2(yy - (-0.05 * S), (xx - cx) * 1.3).astype(np.float32)
    return SkinLayout(size, masks, lm, {k: v.astype(np.float32) for k, v in soft.items()}, hair_dist, ang)


def skin_layout(models_dir: str | Path, size: int) -> SkinLayout:
    """The (cached) layout for ``size``² maps from ``models_dir``/shape_model.safetensors."""
    SkinDataSettings(size=size)  # validates
    path = Path(models_dir) / "shape_model.safetensors"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: shape model not found (run `fitme models` first)")
    return _layout_cached(str(path.resolve()), size)


# ---------------------------------------------------------------------------------------------- noise


def _noise(rng, S: int, cells: float) -> np.ndarray:
    """Smooth value noise, ~unit std, with ``cells`` features per UV unit."""
    n = max(2, int(math.ceil(cells)) + 3)
    g = rng.standard_normal((n, n)).astype(np.float32)
    out = cv2.resize(g, (S, S), interpolation=cv2.INTER_CUBIC)
    return out / (out.std() + 1e-6)


def _fbm(rng, S, cells, octaves=4, gain=0.5):
    out = np.zeros((S, S), np.float32)
    a, tot = 1.0, 0.0
    for _ in range(octaves):
        if cells > S / 2:
            break
        out += a * _noise(rng, S, cells)
        tot += a * a
        cells *= 2.0
        a *= gain
    return out / math.sqrt(tot)


def _aniso_kernel(sl, sw, theta):
    r = int(math.ceil(3 * max(sl, sw)))
    y, x = np.mgrid[-r : r + 1, -r : r + 1].astype(np.float32)
    c, s = math.cos(theta), math.sin(theta)
    a = x * c + y * s
    b = -x * s + y * c
    k = np.exp(-0.5 * ((a / sl) ** 2 + (b / sw) ** 2))
    return (k / np.sqrt((k * k).sum())).astype(np.float32)


def _oriented(rng, S, length, width, angle=None, n_dirs=6, white=None):
    """Oriented noise: white noise smeared along ``angle`` (scalar or per-texel field, radians in image
    coordinates), streaks ``length`` x ``width`` UV. ~unit std."""
    sl = max(length * S, 0.8)
    sw = max(width * S, 0.5)
    w = rng.standard_normal((S, S)).astype(np.float32) if white is None else white
    if angle is None or np.isscalar(angle):
        out = cv2.filter2D(w, -1, _aniso_kernel(sl, sw, float(angle or 0.0)), borderType=cv2.BORDER_REFLECT)
        return out / (out.std() + 1e-6)
    out = np.zeros((S, S), np.float32)
    wsum = np.zeros((S, S), np.float32)
    for k in range(n_dirs):
        th = math.pi * k / n_dirs
        wk = np.exp(4.0 * (np.cos(2.0 * (angle - th)) - 1.0)).astype(np.float32)
        out += wk * cv2.filter2D(w, -1, _aniso_kernel(sl, sw, th), borderType=cv2.BORDER_REFLECT)
        wsum += wk
    out /= wsum
    return out / (out.std() + 1e-6)


def _spots(rng, S, density, sigma_uv, amp_lo=0.6, amp_hi=1.4, unit_peak=True):
    """Random Gaussian spots: ``density`` (S, S) expected spots per UV²; each of radius ``sigma_uv``
    (scalar, floored at ~0.6 texel) and peak ~1."""
    sp = max(sigma_uv * S, 0.6)
    p = np.clip(density / (S * S), 0.0, 0.5)
    imp = (rng.random((S, S), dtype=np.float32) < p) * rng.uniform(amp_lo, amp_hi, (S, S)).astype(np.float32)
    out = cv2.GaussianBlur(imp, (0, 0), sp, borderType=cv2.BORDER_REFLECT)
    return out * (2 * math.pi * sp * sp) if unit_peak else out


def _curve_valley(S, pts_uv_px, width_px, taper=True):
    """Valley profile (peak 1) around a polyline given in texels, over the polyline's bounding box."""
    out = np.zeros((S, S), np.float32)
    r = 3 * width_px + 2
    x0, y0 = np.floor(pts_uv_px.min(0) - r).astype(int)
    x1, y1 = np.ceil(pts_uv_px.max(0) + r).astype(int)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, S), min(y1, S)
    if x1 <= x0 or y1 <= y0:
        return out
    yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
    best = np.full(xx.shape, np.inf, np.float32)
    tbest = np.zeros(xx.shape, np.float32)
    n = len(pts_uv_px) - 1
    for i in range(n):
        a, b = pts_uv_px[i], pts_uv_px[i + 1]
        ab = b - a
        L2 = float(ab @ ab) + 1e-9
        t = np.clip(((xx - a[0]) * ab[0] + (yy - a[1]) * ab[1]) / L2, 0, 1)
        d2 = (xx - a[0] - t * ab[0]) ** 2 + (yy - a[1] - t * ab[1]) ** 2
        sel = d2 < best
        best = np.where(sel, d2, best)
        tbest = np.where(sel, (i + t) / n, tbest)
    prof = np.exp(-0.5 * best / (width_px * width_px))
    if taper:
        prof *= np.clip(np.sin(np.pi * np.clip(tbest, 0, 1)), 0, 1) ** 0.7
    out[y0:y1, x0:x1] = prof
    return out


def _bezier(p0, p1, p2, n=24):
    t = np.linspace(0, 1, n)[:, None]
    return ((1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t * t * p2).astype(np.float32)


# ---------------------------------------------------------------------------------------------- sample


def _hair_colour(rng, melanin: float) -> tuple[str, np.ndarray]:
    names = list(_HAIR_COLOURS)
    # darker skin -> mostly black / dark brown hair
    light = max(0.0, 1.0 - melanin * 2.5)
    p = np.array([0.35 + 0.4 * (1 - light), 0.3, 0.15 * light + 0.05, 0.12 * light, 0.15 * light, 0.05 * light])
    name = names[int(rng.choice(len(names), p=p / p.sum()))]
    col = np.array(_HAIR_COLOURS[name], np.float32) * np.float32(rng.uniform(0.8, 1.2))
    return name, col


def _skin_lut(eumelanin: float, oxygenation: float, n_m: int = 65, n_h: int = 33) -> np.ndarray:
    m = np.linspace(0, 1, n_m)[:, None]
    h = np.linspace(0, 1, n_h)[None, :]
    return skin_rgb(m, h, eumelanin, oxygenation)  # (n_m, n_h, 3)


def generate_sample(layout: SkinLayout, seed: int, index: int, settings: SkinDataSettings = SkinDataSettings()) -> SkinSample:
    """One sample (see the module docstring). ``layout.size`` is the map size (``settings.size`` must
    match it). Deterministic in (seed, index, settings)."""
    S = layout.size
    if settings.size != S:
        raise ValueError(f"settings.size is {settings.size} but the layout is for {S}; build skin_layout(models_dir, {settings.size})")
    rng = np.random.default_rng([int(seed), int(index)])
    soft, lm = layout.soft, layout.lm
    px = layout.px
    yy, xx = np.mgrid[0:S, 0:S].astype(np.float32)

    # ---- parameters
    m_lo, m_hi = settings.melanin_range
    a_lo, a_hi = settings.age_range
    melanin = float(m_lo + (m_hi - m_lo) * rng.random() ** settings.melanin_skew)
    age = float(rng.uniform(a_lo, a_hi))
    haemo = float(rng.uniform(0.12, 0.3))
    eumel = float(rng.uniform(0.6, 0.85) + 0.1 * melanin)
    oxy = float(rng.uniform(0.65, 0.85))
    redness = float(rng.uniform(0.0, 1.0) ** 1.5)
    has_beard = bool(rng.random() < settings.beard_probability)
    beard_density = float(rng.uniform(0.25, 1.0)) if has_beard else 0.0
    beard_length = float(rng.uniform(0.0, 1.0) ** 2) if has_beard else 0.0
    freckles = bool(rng.random() < settings.freckle_probability * (1.0 - 0.8 * melanin))
    n_freckle_scale = float(rng.uniform(0.3, 1.0)) if freckles else 0.0
    oil = float(rng.uniform(0.75, 1.3))
    pore_scale = float(rng.uniform(0.85, 1.2))
    hair_name, hair_col = _hair_colour(rng, melanin)
    grey = float(np.clip((age - 0.45) / 0.5 + rng.normal(0, 0.15), 0, 1))
    hairline = float(rng.uniform(0.0, 0.006) + (rng.uniform(0, 0.03) if age > 0.5 and rng.random() < 0.4 else 0.0))
    brow_density = float(rng.uniform(0.6, 1.0))
    detail = settings.detail

    face_d = soft["skin_detail"]
    hair_alpha = _smoothstep(0.0, 0.016, layout.hair_dist - hairline + 0.006 * _noise(rng, S, 60) + 0.002 * _noise(rng, S, 250))
    # ---- height field (UV units)
    h = np.zeros((S, S), np.float32)
    # pores: three bands with region-dependent density (per UV²) and size
    nose, cheeks, fh, lipsz = soft["nose"], soft["cheeks"], soft["forehead"], soft["lips_zone"]
    large = np.clip(nose + 0.9 * cheeks, 0, 1) * (1 - lipsz)
    medium = np.clip(face_d - large - 0.7 * fh, 0, 1) * (1 - lipsz)
    fine = np.clip(fh + 0.4 * medium + soft["neck"] + lipsz, 0, 1)
    pores = (_spots(rng, S, 25000.0 * large, 0.0014 * pore_scale) * 0.0022
             + _spots(rng, S, 30000.0 * medium, 0.0011 * pore_scale) * 0.0013
             + _spots(rng, S, 45000.0 * fine, 0.0007 * pore_scale) * 0.0006)
    pores *= max(1.0, 1.0 / (0.0012 * S)) ** -0.5  # sub-texel pores average out at low resolution
    h -= pores * (1 - hair_alpha)
    # fine crossed wrinkles (skin microrelief), stronger with age, weaker on the forehead centre
    fa = float(rng.uniform(-0.3, 0.3))
    micro = (_oriented(rng, S, 0.006, 0.0009, 0.6 + fa) + _oriented(rng, S, 0.006, 0.0009, -0.6 + fa)) * 0.5
    h += micro * 0.00035 * (0.6 + 0.8 * age) * face_d
    # forehead lines
    lines = np.zeros((S, S), np.float32)
    top_row, bot_row = lm[10, 1] + px(0.008), lm[105, 1] - px(0.016)
    n_lines = int(rng.integers(3, 6))
    x_env = np.exp(-0.5 * ((xx[0] - S / 2) / px(0.075)) ** 2)
    width = px(0.0018 + 0.0012 * age)
    for k in range(n_lines):
        r = bot_row + (top_row - bot_row) * (k + 0.5 + rng.uniform(-0.25, 0.25)) / n_lines
        wob = np.interp(xx[0], np.linspace(0, S, 9), rng.normal(0, px(0.003), 9))
        arch = -px(0.02) * ((xx[0] - S / 2) / px(0.12)) ** 2 * rng.uniform(-0.3, 1.0)
        seg = np.clip(np.interp(xx[0], np.linspace(0, S, 13), rng.uniform(-0.2, 1.6, 13)), 0, 1)
        prof = np.exp(-0.5 * ((yy - (r + wob + arch)[None, :]) / width) ** 2)
        lines += prof * (x_env * seg)[None, :] * rng.uniform(0.5, 1.0)
    lines *= fh * (1 - hair_alpha)
    # crow's feet
    crows = np.zeros((S, S), np.float32)
    for corner, side in ((33, -1.0), (263, 1.0)):
        c = lm[corner]
        for _ in range(int(rng.integers(3, 7))):
            th = math.radians(rng.uniform(-55, 45))
            r0, r1 = px(rng.uniform(0.004, 0.009)), px(rng.uniform(0.02, 0.035))
            d = np.array([side * math.cos(th), -math.sin(th)], np.float32)
            bend = np.array([-d[1], d[0]]) * px(rng.uniform(-0.004, 0.004))
            crows += _curve_valley(S, _bezier(c + d * r0, c + d * (r0 + r1) / 2 + bend, c + d * r1, 10), px(0.0016 + 0.001 * age)) * rng.uniform(0.5, 1.0)
    # nasolabial folds (alar -> just outside the mouth corner)
    naso = np.zeros((S, S), np.float32)
    for alar, mouth, side in ((129, 61, -1.0), (358, 291, 1.0)):
        p0 = lm[alar] + (side * px(0.006), -px(0.002))
        p2 = lm[mouth] + (side * px(0.009), px(0.012))
        p1 = (p0 + p2) / 2 + (side * px(0.012), 0)
        naso += _curve_valley(S, _bezier(p0, p1, p2), px(0.003 + 0.002 * age))
    # vertical lip lines
    liplines = np.abs(_oriented(rng, S, 0.004, 0.0006, math.pi / 2)) * soft["lips"]
    a15 = age**1.5
    wr = (0.004 * a15 * lines + 0.003 * (0.15 + a15) * crows * (1 - hair_alpha)
          + 0.004 * (0.25 + 0.75 * age) * naso + 0.0005 * liplines)
    h -= wr
    # moles (raised)
    mole_d = rng.integers(0, 6) * 4.0 * (face_d + 0.5 * soft["neck"]) * (1 - soft["lips"])
    moles = _spots(rng, S, mole_d, rng.uniform(0.0015, 0.003))
    h += 0.0015 * np.clip(moles, 0, 1.5)
    # hair strands: scalp (flowing from the crown), brows (outwards, up), beard (down)
    strands = _oriented(rng, S, 0.008, 0.0005, layout.hair_angle)
    brow_ang = np.where(xx < S / 2, math.pi - 0.35, 0.35).astype(np.float32)
    brow_str = _oriented(rng, S, 0.004, 0.0006, brow_ang, n_dirs=4)
    beard_str = _oriented(rng, S, 0.002 + 0.006 * beard_length, 0.0006, math.pi / 2 + 0.3 * (xx - S / 2) / S)
    brows_a = np.clip(soft["brows"] * brow_density * (0.85 + 0.35 * brow_str), 0, 1)
    beard_zone = soft["beard"] * _smoothstep(0.15, 0.6, soft["beard"] + 0.2 * _noise(rng, S, 60))
    beard_a = np.clip(beard_zone * beard_density * (0.5 + 0.6 * beard_length + 0.25 * beard_str), 0, 1) if has_beard else np.zeros_like(h)
    h += 0.0012 * strands * hair_alpha + 0.001 * brow_str * brows_a + 0.001 * beard_str * beard_a
    h *= np.float32(detail)

    # normals from the gradient (dh/du, dh/dv with v up)
    gx = cv2.Sobel(h, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) * (S / 8.0)
    gy = cv2.Sobel(h, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) * (S / 8.0)
    n = np.stack([-gx, gy, np.ones_like(gx)], -1)  # dh/dv = -dh/drow
    n /= np.linalg.norm(n, axis=-1, keepdims=True)

    # cavities: how far each texel lies below its neighbourhood (pores, wrinkle valleys), ~[0, 1]
    cav = np.clip(_blur(h, px(0.004)) - h, 0, None) / (0.002 * max(detail, 1e-3))
    cav = np.clip(cav, 0, 1.5)

    # ---- diffuse albedo
    mel = melanin + 0.035 * _fbm(rng, S, 6, 4) * (0.3 + melanin)
    mel = mel + 0.05 * soft["under_eye"] * (0.5 + melanin) + 0.03 * soft["lips"] * melanin
    if freckles:
        fr_d = (nose + cheeks + 0.3 * fh + 0.15 * face_d) * 3000.0 * n_freckle_scale
        mel = mel + rng.uniform(0.06, 0.14) * np.clip(_spots(rng, S, fr_d, 0.0016, 0.3, 1.2), 0, 1.2) * face_d
    n_age = int(rng.poisson(12 * max(age - 0.35, 0) ** 1.5 * 10))
    if n_age:
        ad = (fh + cheeks + 0.5 * soft["face"]) * n_age * 6.0
        spots_a = _spots(rng, S, ad, 0.005, 0.4, 1.0) * (0.6 + 0.4 * _noise(rng, S, 150))
        mel = mel + 0.1 * np.clip(spots_a, 0, 1.2) * (1 - 0.5 * melanin)
    mel = mel + 0.35 * np.clip(moles, 0, 1) * (1 - 0.4 * melanin)
    hb = haemo * (1 + 0.2 * _fbm(rng, S, 10, 3))
    hb = hb + (0.12 + 0.3 * redness) * np.clip(cheeks + 0.8 * nose, 0, 1) + 0.1 * soft["eyes"]
    hb = hb + (0.55 + 0.3 * rng.random()) * soft["lips"] + 0.1 * soft["lips_zone"]
    lut = _skin_lut(min(eumel, 0.98), oxy)
    mx = (np.clip(hb, 0, 1) * (lut.shape[1] - 1)).astype(np.float32)
    my = (np.clip(mel, 0, 1) * (lut.shape[0] - 1)).astype(np.float32)
    alb = cv2.remap(lut, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    alb *= (1.0 - 0.08 * soft["under_eye"])[..., None]
    alb *= np.exp(-0.4 * cav)[..., None]  # same cavities as the normals
    alb *= (1.0 - 0.55 * soft["mouth_line"])[..., None]
    # hair on top
    hair_c = hair_col[None, None, :] * np.exp(0.25 * strands)[..., None]
    if grey > 0:
        g = grey * np.clip(0.75 + 0.3 * _oriented(rng, S, 0.008, 0.0005, layout.hair_angle), 0, 1)
        hair_c = hair_c * (1 - g[..., None]) + _GREY * np.exp(0.2 * strands)[..., None] * g[..., None]
    alb = alb * (1 - hair_alpha[..., None]) + hair_c * hair_alpha[..., None]
    brow_c = hair_col * 0.8 * (1 - 0.6 * grey) + _GREY * 0.6 * grey * 0.6
    alb = alb * (1 - brows_a[..., None]) + brow_c * brows_a[..., None] * np.exp(0.3 * brow_str)[..., None]
    beard_c = hair_col * 0.85 * (1 - grey) + _GREY * grey * 0.8
    alb = alb * (1 - beard_a[..., None]) + beard_c * beard_a[..., None]
    lash = np.clip(soft["lash"], 0, 1)[..., None]
    alb = alb * (1 - 0.85 * lash) + np.array([0.012, 0.01, 0.009], np.float32) * 0.85 * lash
    ein = soft["eye_inside"][..., None]
    alb = alb * (1 - ein) + (0.4 * alb + np.array([0.2, 0.18, 0.17], np.float32)) * ein  # unmapped: dim eyeball
    alb = np.clip(alb, 0, 1).astype(np.float32)

    # ---- specular albedo
    spec = 0.14 + 0.14 * soft["tzone"] + 0.08 * soft["lips"] - 0.04 * soft["neck"] + 0.06 * soft["eyes"]
    spec = spec * oil * (1 - 0.15 * age) * np.exp(0.12 * _fbm(rng, S, 20, 3)) * (1 - 0.35 * np.clip(cav, 0, 1))
    spec = spec * (1 - hair_alpha) + (0.07 + 0.02 * strands) * hair_alpha
    spec = spec * (1 - brows_a) + 0.07 * brows_a
    spec = spec * (1 - beard_a) + 0.07 * beard_a
    spec = np.clip(spec * (1 - 0.6 * soft["lash"]), 0, 1).astype(np.float32)

    params = {
        "seed": int(seed), "index": int(index), "melanin": round(melanin, 5), "eumelanin": round(eumel, 5),
        "haemoglobin": round(haemo, 5), "oxygenation": round(oxy, 5), "redness": round(redness, 5),
        "age": round(age, 5), "beard": has_beard, "beard_density": round(beard_density, 5),
        "beard_length": round(beard_length, 5), "freckles": freckles, "age_spots": n_age,
        "hair_colour": hair_name, "grey": round(grey, 5), "hairline": round(hairline, 5), "oil": round(oil, 5),
        "pore_scale": round(pore_scale, 5), "forehead_lines": n_lines,
    }
    return SkinSample(alb, spec, n.astype(np.float32), params)


# ---------------------------------------------------------------------------------------------- io


def sample_files(name: str, fmt: str) -> dict[str, str]:
    """{map: file name} of sample ``name`` in ``fmt``."""
    ext = {"png": "png", "exr": "exr"}[fmt]
    return {k: f"{name}_{k}.{ext}" for k in ("albedo", "specular", "normals")}


def write_sample(out_dir: str | Path, name: str, sample: SkinSample, fmt: str) -> list[Path]:
    """Write ``name``_{albedo,specular,normals}.{png,exr} into ``out_dir``, atomically.

    png: albedo 8-bit sRGB; specular 8-bit LINEAR grey; normals 16-bit RGB of n * 0.5 + 0.5 (raw, not
    gamma-encoded). exr: half-float RGB, all linear: albedo, specular (grey in R = G = B), normals as
    n * 0.5 + 0.5. Returns the paths written."""
    from ..io.atomic import atomic_write_bytes
    from ..io.maps import write_map

    if fmt not in ("png", "exr"):
        raise ValueError(f"format must be 'png' or 'exr', got {fmt!r}")
    out_dir = Path(out_dir)
    files = {k: out_dir / v for k, v in sample_files(name, fmt).items()}
    enc = np.clip(sample.normals * 0.5 + 0.5, 0, 1)
    if fmt == "exr":
        write_map(files["albedo"], sample.albedo, "exr16")
        write_map(files["specular"], np.repeat(sample.specular[..., None], 3, -1), "exr16")
        write_map(files["normals"], enc, "exr16")
    else:
        write_map(files["albedo"], sample.albedo, "png8")
        for key, arr in (("specular", np.round(np.clip(sample.specular, 0, 1) * 255).astype(np.uint8)),
                         ("normals", np.round(enc[..., ::-1] * 65535).astype(np.uint16))):
            ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
            if not ok:
                from ..errors import OutputNotWritable

                raise OutputNotWritable("PNG encoding failed", files[key])
            atomic_write_bytes(files[key], buf.tobytes())
    return list(files.values())


@dataclass
class MapStats:
    """Running statistics over mapped texels: albedo = A_D (3 channels) and A_S pooled, linear; normals
    encoded n * 0.5 + 0.5, pooled over channels and per channel."""

    n_alb: int = 0
    s_alb: float = 0.0
    ss_alb: float = 0.0
    n_nrm: int = 0
    s_nrm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ss_nrm: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def add(self, sample: SkinSample, mapped: np.ndarray) -> None:
        a = np.concatenate([sample.albedo[mapped].ravel(), sample.specular[mapped].ravel()]).astype(np.float64)
        self.n_alb += a.size
        self.s_alb += a.sum()
        self.ss_alb += (a * a).sum()
        e = sample.normals[mapped].astype(np.float64) * 0.5 + 0.5
        self.n_nrm += len(e)
        self.s_nrm += e.sum(0)
        self.ss_nrm += (e * e).sum(0)

    def merge(self, other: "MapStats") -> None:
        for k in ("n_alb", "s_alb", "ss_alb", "n_nrm", "s_nrm", "ss_nrm"):
            setattr(self, k, getattr(self, k) + getattr(other, k))

    def summary(self) -> dict:
        am = self.s_alb / max(self.n_alb, 1)
        astd = math.sqrt(max(self.ss_alb / max(self.n_alb, 1) - am * am, 0))
        n = max(self.n_nrm, 1)
        cm = self.s_nrm / n
        cs = np.sqrt(np.maximum(self.ss_nrm / n - cm * cm, 0))
        pm = cm.mean()
        ps = math.sqrt(max((self.ss_nrm / n).mean() - pm * pm, 0))
        r = lambda x: round(float(x), 4)  # noqa: E731
        return {"albedo_mean": r(am), "albedo_std": r(astd), "normals_mean": r(pm), "normals_std": r(ps),
                "normals_channel_mean": [r(x) for x in cm], "normals_channel_std": [r(x) for x in cs]}


def settings_dict(s: SkinDataSettings) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(s).items()}
