"""Training data for BRDF-GAN: a folder written by ``fitme dataset`` (or any folder of
``NAME_albedo``, ``NAME_specular``, ``NAME_normals`` maps, PNG or EXR) loaded into one tensor.

PNG conventions (those of ``fitme dataset``): albedo 8/16-bit sRGB; specular 8/16-bit grey, linear;
normals 16-bit (or 8-bit) raw ``0.5 n + 0.5``, not gamma-encoded. EXR maps are linear floats, normals
as raw components in [-1, 1].
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import torch

from ...errors import InputNotFound, WrongLayout
from .networks import GanSettings, ReflectanceMaps, encode_maps

__all__ = ["find_samples", "load_sample", "load_dataset", "load_regions", "hairline_band", "hairline_zones", "hairline_reach",
           "hairline_references", "split_sides", "eye_openings", "eye_rings", "lip_rings", "brow_edges", "beard_zone", "face_square", "layout_image", "LAYOUT_CHANNELS", "HAIRLINE_LABEL",
           "EYE_LABEL", "BROW_EDGE_LABEL", "SIDE_OFFSET"]

_KINDS = ("albedo", "specular", "normals")


def find_samples(data_dir: Path) -> list[str]:
    """Sorted sample stems NAME for which all three maps exist (PNG or EXR)."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise InputNotFound("training data directory not found", data_dir)
    stems = []
    for p in sorted(data_dir.glob("*_albedo.*")):
        stem = p.name[: -len("_albedo" + p.suffix)]
        if all((data_dir / f"{stem}_{k}{p.suffix}").is_file() for k in _KINDS):
            stems.append(f"{stem}{p.suffix}")
    if not stems:
        raise InputNotFound("no NAME_albedo/_specular/_normals map triplets in the directory", data_dir)
    return stems


def _read_raw(path: Path) -> np.ndarray:
    """(H, W, C) float32: PNG scaled to [0, 1] without any transfer function, EXR as stored."""
    if path.suffix.lower() == ".exr":
        from ...io.maps import read_map

        return read_map(path).linear
    a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if a is None:
        raise WrongLayout("cannot read map", path)
    scale = 65535.0 if a.dtype == np.uint16 else 255.0
    a = a.astype(np.float32) / scale
    if a.ndim == 2:
        a = a[..., None]
    elif a.shape[2] >= 3:
        a = a[..., 2::-1]  # BGR -> RGB, drop alpha
    return a


def load_sample(data_dir: Path, stem_ext: str, resolution: int) -> np.ndarray:
    """(7, R, R) float32 physical maps: A_D linear (3), A_S linear (1), N_S unit (3)."""
    from ...io.maps import read_map

    data_dir = Path(data_dir)
    stem, ext = stem_ext.rsplit(".", 1)
    albedo = read_map(data_dir / f"{stem}_albedo.{ext}").linear[..., :3]
    spec = _read_raw(data_dir / f"{stem}_specular.{ext}")[..., :1]
    nrm = _read_raw(data_dir / f"{stem}_normals.{ext}")[..., :3]
    if ext.lower() != "exr":
        nrm = nrm * 2 - 1
    out = []
    for a in (albedo, spec, nrm):
        if a.shape[0] != a.shape[1]:
            raise WrongLayout(f"expected square UV maps, got {a.shape[1]}x{a.shape[0]}", data_dir / stem)
        if a.shape[0] != resolution:
            a = cv2.resize(a, (resolution, resolution), interpolation=cv2.INTER_AREA)
            a = a[..., None] if a.ndim == 2 else a
        out.append(a)
    albedo, spec, nrm = out
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-6)
    x = np.concatenate([np.clip(albedo, 0, 1), np.clip(spec, 0, 1), nrm], -1)
    return np.ascontiguousarray(x.transpose(2, 0, 1), dtype=np.float32)


def load_dataset(data_dir: Path, s: GanSettings, limit: int | None = None, progress: bool = False) -> torch.Tensor:
    """(N, 7, R, R) float16 in ``s``'s network space (half the memory; enough for 8/16-bit sources)."""
    resolution = s.resolution
    stems = find_samples(data_dir)[:limit]
    out = torch.empty(len(stems), 7, resolution, resolution, dtype=torch.float16)
    it = stems
    if progress:
        import sys

        from tqdm import tqdm

        it = tqdm(stems, desc="loading data", unit="sample", file=sys.stderr, disable=None)
    for i, stem in enumerate(it):
        x = torch.from_numpy(load_sample(data_dir, stem, resolution))[None]
        out[i] = encode_maps(ReflectanceMaps(x[:, :3], x[:, 3:4], x[:, 4:]), s).cat()[0]
    return out


# the per-region drift terms' extra label (``load_regions(hairline=True)``), after shape.regions.REGIONS' 0-7
HAIRLINE_LABEL = 8
# signed distance into the scalp (UV units) the hairline band spans: ``fitme dataset`` ramps hair in over
# 0.016 from a hairline 0-0.006 inside the scalp edge, ragged by ~0.006 (skin_data.generate_sample), so
# -0.01 .. 0.016 holds the edge of nearly every sample: 7 texels wide at 256^2
_HAIRLINE_UV = (-0.01, 0.016)


def _hair_dist(resolution: int) -> np.ndarray:
    """(S, S) float32, S = max(resolution, 64): the layout's signed distance into the scalp (UV units)."""
    from ...perception.registry import ensure_models
    from ..skin_data import skin_layout

    if resolution < 1:
        raise ValueError(f"expected a resolution >= 1, got {resolution}")
    return skin_layout(ensure_models(["shape_model"]), max(resolution, 64)).hair_dist


def hairline_zones(resolution: int) -> torch.Tensor:
    """(R, R) uint8: the training data's hairline (``fitme dataset``'s layout, ``skin_data.SkinLayout.hair_dist``
    within ``_HAIRLINE_UV``) labelled 1, the face side of it 0 and the scalp side 2 (each as wide as the band,
    0.026 UV), 255 elsewhere. Below 64^2, the 64^2 zones resized (nearest)."""
    dist = _hair_dist(resolution)
    size = dist.shape[0]
    lo, hi = _HAIRLINE_UV
    band = ((dist > lo) & (dist <= hi)).astype(np.uint8)
    # the eye holes are unmapped, which the layout counts as scalp: their rings are small separate
    # components, the hairline is the largest
    _, comp, stats, _ = cv2.connectedComponentsWithStats(band, connectivity=8)
    band = comp == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    width = max(1, round((hi - lo) * size))
    near = cv2.dilate(band.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * width + 1,) * 2)) > 0
    zones = np.full((size, size), 255, np.uint8)
    zones[near & (dist <= lo)] = 0
    zones[near & (dist > hi)] = 2
    zones[band] = 1
    if size != resolution:
        zones = cv2.resize(zones, (resolution,) * 2, interpolation=cv2.INTER_NEAREST)
    return torch.from_numpy(zones)


def hairline_band(resolution: int) -> torch.Tensor:
    """(R, R) bool: the texels around the training data's hairline (``hairline_zones`` 1)."""
    return hairline_zones(resolution) == 1


def hairline_reach(resolution: int) -> torch.Tensor:
    """(R, R) bool: the hairline band and the scalp just behind it (``hairline_zones`` 1 and 2: 0.052 UV, 13 texels
    at 256^2, all along the scalp's edge), which the data's hairline crosses as it recedes: ``fitme dataset`` puts
    it 0-0.006 inside the scalp edge, a further 0-0.03 on two in five older faces."""
    zones = hairline_zones(resolution)
    return (zones == 1) | (zones == 2)


# how far into the scalp (UV) ``hairline_references``' scalp starts: past the most receded data hairline's ramp
# (0.006 + 0.03 + 0.016, ragged by ~0.006)
_SCALP_INTERIOR_UV = 0.06


def hairline_references(resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(face, scalp), each (R, R) bool: where ``metrics.soft_hairline_share`` takes a sample's skin and hair colour.
    face: the face side of the hairline (``hairline_zones`` 0); scalp: the scalp region (``shape.regions.REGIONS``
    0) at least 0.06 UV inside the scalp's edge, where every data sample has hair."""
    dist = _hair_dist(resolution)
    if dist.shape[0] != resolution:
        dist = cv2.resize(dist, (resolution,) * 2, interpolation=cv2.INTER_NEAREST)
    scalp = torch.from_numpy(dist > _SCALP_INTERIOR_UV) & (load_regions(resolution) == 0)
    return hairline_zones(resolution) == 0, scalp


# the per-region terms' labels for the eye openings (``load_regions(eyes=True)``) and the brows' edges
# (``load_regions(brows=True)``), after ``HAIRLINE_LABEL``
EYE_LABEL = 9
BROW_EDGE_LABEL = 10


def _layout_mask(resolution: int, mask: Callable[[np.ndarray], np.ndarray], key: str) -> torch.Tensor:
    """(R, R) bool: ``mask`` of the training data's layout (``fitme dataset``'s ``skin_data.SkinLayout.soft[key]``).
    Below 64^2, the texels at least half covered by the 64^2 mask, or where none is, the most covered (at 16^2 an
    eye is a fraction of a texel, and a resize would lose it)."""
    from ...perception.registry import ensure_models
    from ..skin_data import skin_layout

    if resolution < 1:
        raise ValueError(f"expected a resolution >= 1, got {resolution}")
    size = max(resolution, 64)
    m = mask(skin_layout(ensure_models(["shape_model"]), size).soft[key]).astype(np.float32)
    if size != resolution:
        cover = cv2.resize(m, (resolution,) * 2, interpolation=cv2.INTER_AREA)
        m = cover >= min(0.5, float(cover.max()) - 1e-6)
    return torch.from_numpy(m.astype(bool))


_FACE_LABELS = ("skin", "forehead", "brows", "eyes", "nose", "lips")

# What G reads of the layout (``GanSettings.layout_channels``), in this order: the soft masks with which ``fitme
# dataset`` places the anatomy (``skin_data.SkinLayout.soft``), then the hairline's signed distance into the scalp, the
# hair's flow as the cosine and sine of twice its angle (a strand has no head or tail), and the texel's column and row.
_LAYOUT_SOFT = ("lips", "mouth_line", "lips_zone", "brows", "eye_inside", "lash", "eyes", "beard", "neck", "face")
LAYOUT_CHANNELS = _LAYOUT_SOFT + ("hair_distance", "hair_flow_cos", "hair_flow_sin", "column", "row")
# UV units per unit of the hair_distance channel: the data's hairline lies 0-0.036 UV inside the scalp's edge
# (``hairline_reach``), which this puts at 0-1.5
_HAIR_DISTANCE_UV = 0.024
# Each map is scaled to unit RMS over the map, as G's features are about unit, so that an Adam step on a weight moves
# what each input adds alike (the equalised learning rate's point), but by at most this: unscaled, the 346.00 kimg G's
# layout weights grew to only 0.02-0.05 in a kimg against ~1 for its features' (2026-12-04); unit RMS would take the
# thinnest masks, the lashes and the mouth line, to 38-69x
_LAYOUT_GAIN_MAX = 10.0


@functools.lru_cache(maxsize=4)
def _layout_image(resolution: int) -> np.ndarray:
    from ...perception.registry import ensure_models
    from ..skin_data import skin_layout

    size = max(resolution, 64)
    lay = skin_layout(ensure_models(["shape_model"]), size)
    coord = (np.arange(size, dtype=np.float32) + 0.5) / size * 2 - 1
    maps = [lay.soft[k] for k in _LAYOUT_SOFT]
    maps += [np.clip(lay.hair_dist / _HAIR_DISTANCE_UV, -1.5, 1.5), np.cos(2 * lay.hair_angle), np.sin(2 * lay.hair_angle),
             np.broadcast_to(coord[None, :], (size, size)), np.broadcast_to(coord[:, None], (size, size))]
    rms = [float(np.sqrt(np.mean(np.square(m, dtype=np.float64)))) for m in maps]
    maps = [m * (_LAYOUT_GAIN_MAX if r * _LAYOUT_GAIN_MAX <= 1 else 1 / r) for m, r in zip(maps, rms)]  # r may be 0
    if size != resolution:
        maps = [cv2.resize(np.ascontiguousarray(m, np.float32), (resolution,) * 2, interpolation=cv2.INTER_AREA) for m in maps]
    return np.stack(maps).astype(np.float32)


def layout_image(resolution: int) -> torch.Tensor:
    """(K, R, R) float32, K = len(LAYOUT_CHANNELS): the training data's layout as G reads it
    (``SynthesisNetwork.layout_image``): masks (0 outside, > 0 inside), the hairline's signed distance (> 0 in the
    scalp, clipped at 0.036 UV either side), the flow's cosine and sine, and the coordinates (column left to right,
    row top to bottom, 0 at the centre), each scaled to unit RMS over the map or by 10 where that is less (the masks
    of the lips, mouth line, lips zone, brows, eye openings, lashes and eyes). Below 64^2, the 64^2 maps
    area-averaged."""
    if resolution < 1:
        raise ValueError(f"expected a resolution >= 1, got {resolution}")
    return torch.from_numpy(_layout_image(resolution).copy())


@functools.lru_cache(maxsize=8)
def face_square(resolution: int) -> tuple[int, int, int]:
    """(row, column, side) of a square crop of the face: side max(16, R / 2) (at most R), centred on the mean texel of
    the shape model's face labels (skin, forehead, brows, eyes, nose, lips), moved inside the map. At 256^2 rows and
    columns 53-181 and 64-192: 79 % face labels, 19 % scalp at its upper corners. The Nyquist term's face ratios: over
    the whole map the scalp's strands, where G matches the data, hid a face whose normals carry ~14 times the data's
    energy at the Nyquist row and column (346.00 kimg, docs/brdf_gan.md)."""
    from ...shape.regions import REGIONS

    regions = load_regions(resolution)
    face = torch.isin(regions, torch.tensor([REGIONS.index(n) for n in _FACE_LABELS], dtype=regions.dtype))
    rows, cols = face.nonzero(as_tuple=True)
    side = min(max(16, resolution // 2), resolution)
    row = min(max(round(float(rows.double().mean()) - side / 2), 0), resolution - side)
    col = min(max(round(float(cols.double().mean()) - side / 2), 0), resolution - side)
    return row, col, side


def eye_openings(resolution: int) -> torch.Tensor:
    """(R, R) bool: the training data's eye openings (the layout's ``eye_inside`` > 0.5), where the data paints a
    flat dim eyeball (0.4 of the skin plus a fixed grey). Most of it lies in the shape model's unmapped eye holes
    (90 of 121 texels at 256^2), which no region label covers."""
    return _layout_mask(resolution, lambda m: m > 0.5, "eye_inside")


# the outer edges of ``eye_rings``' bands, in texels at 256^2 from the eye openings: G_ema's ring ("eyeshadow") at
# 289.04 kimg spans 0-6 texels, and the socket out to ~26; the last band, the profile's reference, is all the skin
# beyond (7286 texels at 256^2, 7-70 times a band's), so that a texel of it weighs too little for G to meet the
# profile by moving it. A reference band as narrow as the others was moved: at 9-14 texels G darkened the socket with
# it (293-294 kimg), at 26-34 the whole mid-face (D won within 0.5 kimg; docs/brdf_gan.md)
_EYE_RING_EDGES = (2.0, 4.0, 6.0, 9.0, 14.0, 20.0, 26.0, math.inf)


def eye_rings(resolution: int) -> torch.Tensor:
    """(R, R) uint8: the training data's eye openings (``eye_openings``) labelled 0, and the skin around them in
    bands of distance from them labelled 1, 2, ... (outer edges 2, 4, 6, 9, 14, 20 and 26 texels at 256^2, scaled to
    R and each at least one texel wider than the one before, then all the rest; a band that holds no texel is dropped
    and the labels stay consecutive), 255 elsewhere. Only texels of the shape model's skin and eyes regions join a
    band: the brows (whose colour is the hair's), the forehead and the nose do not. ``metrics.ring_profile`` of these
    bands, each against the last, is the eye-ring term's measure."""
    from ...shape.regions import REGIONS

    inside = eye_openings(resolution).numpy()
    regions = load_regions(resolution).numpy()
    around = np.isin(regions, [REGIONS.index("skin"), REGIONS.index("eyes")]) & ~inside
    return torch.from_numpy(_distance_bands(inside, around, _EYE_RING_EDGES))


def _distance_bands(inside: np.ndarray, around: np.ndarray, edges: tuple[float, ...]) -> np.ndarray:
    """(R, R) bool ``inside`` and ``around`` -> (R, R) uint8: ``inside`` labelled 0, the texels of ``around`` in bands
    of distance from it labelled 1, 2, ... (outer edges ``edges`` in texels at 256^2, scaled to R and each at least
    one texel wider than the one before; a band that holds no texel is dropped, the labels stay consecutive), 255
    elsewhere."""
    resolution = inside.shape[0]
    dist = cv2.distanceTransform((~inside).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    out = np.full(inside.shape, 255, np.uint8)
    out[inside] = 0
    lo, band = 0.0, 1
    for edge in edges:
        hi = max(edge * resolution / 256, lo + 1)
        sel = around & (dist > lo) & (dist <= hi)
        if sel.any():
            out[sel] = band
            band += 1
        lo = hi
    return out


def lip_rings(resolution: int) -> torch.Tensor:
    """(2, R, R) uint8: the layout's lips and the skin around them in bands of distance (``_distance_bands``, outer
    edges 2, 4, 6, 9, 14, 20 and 26 texels at 256^2: the eye rings' without the rest of the face), above the lips'
    mean row (0) and at or below it (1); in each half the lips are 0 and the bands 1, 2, ... in order (one empty in
    that half dropped), 255 elsewhere, and all 255 in a half with fewer than two labels. Only the shape model's skin
    region joins a band (not the nose, nor the neck). ``metrics.ring_profile`` over each half is the lips and each band
    against the 20-26 texel band on that side: the data's skin is as light next to the lips as 20 texels out (log
    luminance 2-9 texels above the upper lip +0.015, below the lower lip 0.00), where G_ema at 343.17 kimg drew a
    lighter patch above the upper lip (+0.09) and a halo below (+0.05) (docs/brdf_gan.md)."""
    from ...shape.regions import REGIONS

    regions = load_regions(resolution).numpy()
    lips = regions == REGIONS.index("lips")
    bands = _distance_bands(lips, (regions == REGIONS.index("skin")) & ~lips, _EYE_RING_EDGES[:-1])
    out = np.full((2, resolution, resolution), 255, np.uint8)
    if not lips.any():  # below 16^2
        return torch.from_numpy(out)
    rows = np.arange(resolution)[:, None].repeat(resolution, 1)
    centre = rows[lips].mean()
    for h, side in enumerate((rows < centre, rows >= centre)):
        present = [b for b in np.unique(bands[side]) if b != 255]
        if len(present) >= 2:
            for label, b in enumerate(present):
                out[h][side & (bands == b)] = label
    return torch.from_numpy(out)


_EYE_RING_NEAR = 3  # ``eye_ring_halves``: the bands nearest the openings (0-2, 2-4 and 4-6 texels at 256^2)


def eye_ring_halves(resolution: int) -> torch.Tensor:
    """(2, R, R) uint8: ``eye_rings``' texels above the openings' mean row (0) and at or below it (1). In each half the
    three bands nearest the openings (0-2, 2-4 and 4-6 texels at 256^2) are labelled 0, 1, ... in order (one empty in
    that half is dropped) and the bands beyond them to 26 texels (the zone they sit in) the last label; 255
    elsewhere, and all 255 in a half without a near band or a zone (the upper half below 32^2).
    ``metrics.ring_profile`` over each half is each near band against the zone just outside it on the same side of the
    eye: the data's upper lid and its under-eye darkening differ (log albedo, the three near bands together against the
    zone: -0.03 above, -0.07 below), and a ring profile over whole bands was met at 301.25 kimg by a lighter, peach
    upper lid and a darker under-eye (docs/brdf_gan.md)."""
    bands = eye_rings(resolution)
    k = int(bands[bands != 255].max())  # the far skin's label, the profile's reference in ``eye_rings``
    rows = torch.arange(resolution)[:, None].expand(resolution, resolution)
    centre = rows[bands == 0].double().mean()
    out = torch.full((2, resolution, resolution), 255, dtype=torch.uint8)
    for h, side in enumerate((rows < centre, rows >= centre)):
        label = 0
        for band in range(1, _EYE_RING_NEAR + 1):
            sel = side & (bands == band)
            if bool(sel.any()):
                out[h][sel] = label
                label += 1
        zone = side & (bands > _EYE_RING_NEAR) & (bands < k)
        if label and bool(zone.any()):
            out[h][zone] = label
        else:  # below 32^2 the openings are a texel or two at the layout's top edge of the eye
            out[h] = 255
    return out


def brow_edges(resolution: int) -> torch.Tensor:
    """(R, R) bool: a 3-texel ring along the edge of the training data's brows (the layout's ``brows`` > 0.5,
    where every sample's brow hair is; its density varies). 312 texels at 256^2, 305 of them from the brows region,
    which reaches well beyond the hair."""
    def ring(m: np.ndarray) -> np.ndarray:
        inside, k = (m > 0.5).astype(np.uint8), np.ones((3, 3), np.uint8)
        return (cv2.dilate(inside, k) > 0) & ~(cv2.erode(inside, k) > 0)

    return _layout_mask(resolution, ring, "brows")


def beard_zone(resolution: int) -> torch.Tensor:
    """(R, R) bool: where the training data grows stubble and beards (the layout's ``beard`` > 0.5): the jaw, chin
    and upper lip, below a line from the sideburns to just under the nose."""
    return _layout_mask(resolution, lambda m: m > 0.5, "beard")


# added by ``split_sides`` to the label of each texel right of the UV midline; above every base label
SIDE_OFFSET = 16


def split_sides(regions: torch.Tensor) -> torch.Tensor:
    """(R, R) uint8 labels (255 unmapped), each below ``SIDE_OFFSET`` -> a copy with every mapped texel of
    column >= R // 2 (u >= 0.5 for an even R, the layout's midline) relabelled label + ``SIDE_OFFSET``: each
    region split into its two halves. The layout is mirror-symmetric (95 % of texels carry their mirror's
    label; the small regions split within 2-3 % of even, the nose 44 / 56 %)."""
    if regions.ndim != 2 or regions.shape[0] != regions.shape[1] or regions.dtype != torch.uint8:
        raise ValueError(f"expected (R, R) uint8 region labels, got {tuple(regions.shape)} {regions.dtype}")
    mapped = regions != 255
    if bool((regions[mapped] >= SIDE_OFFSET).any()):
        raise ValueError(f"expected labels below {SIDE_OFFSET} (or 255), got {int(regions[mapped].max())}: already split?")
    out = regions.clone()
    right = mapped.clone()
    right[:, : regions.shape[1] // 2] = False
    out[right] += SIDE_OFFSET
    return out


def load_regions(resolution: int, hairline: bool = False, sides: bool = False, eyes: bool = False,
                 brows: bool = False) -> torch.Tensor:
    """(R, R) uint8: the shape model's UV region labels (255 unmapped) at the maps' resolution (nearest).
    ``hairline``: the texels of ``hairline_band`` relabelled ``HAIRLINE_LABEL`` (the BRDF-GAN's
    ``TrainSettings.hairline_region``), taken from the scalp, forehead, skin or unmapped border around it.
    ``eyes``: the texels of ``eye_openings`` labelled ``EYE_LABEL`` (``TrainSettings.eye_region``), taken from
    the eyes region and the unmapped eye holes. ``brows``: the texels of ``brow_edges`` labelled ``BROW_EDGE_LABEL``
    (``TrainSettings.brow_edge_region``), taken from the brows region.
    ``sides``: then each region split at the midline (``split_sides``; ``TrainSettings.side_regions``)."""
    from safetensors.numpy import load_file

    from ...perception.registry import ensure_models

    region_uv = load_file(str(ensure_models(["shape_model"]) / "shape_model.safetensors"))["region_uv"]
    regions = torch.from_numpy(cv2.resize(region_uv, (resolution,) * 2, interpolation=cv2.INTER_NEAREST))
    if hairline:
        regions[hairline_band(resolution)] = HAIRLINE_LABEL
    if eyes:
        regions[eye_openings(resolution)] = EYE_LABEL
    if brows:
        regions[brow_edges(resolution)] = BROW_EDGE_LABEL
    return split_sides(regions) if sides else regions
