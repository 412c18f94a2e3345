"""Quality measures for BRDF-GAN against its training data, without ImageNet weights.

- ``reflectance_features``: a descriptor of what the data generator varies, per UV region (8 regions):
  for each of the 7 channels its mean, and its band-pass energy at 3 scales (a Laplacian pyramid:
  pores at the finest, wrinkles and hair strands in the middle, freckles and stubble patches at the
  coarsest). 8 x 7 x 4 = 224 dimensions. A Frechet distance in this space compares tone, redness,
  beard, specular layout and detail statistics region by region; it has no learned weights, so it
  cannot be fooled by features a network happens to ignore, and means the same on any machine.
- ``modality_consistency``: does one sample's albedo darken where its normals show cavities? The
  correlation between the albedo's band-pass luminance and the normals' divergence (concave < 0),
  for matching pairs against mismatched pairs.
- ``std_parts``: a channel's spread split by scale: between samples (their means), within a sample
  above a 9-texel window (regions, patches), and below it (grain, pores, strands). Says which part of
  a std difference to the data is tone and which is texture.
- ``interpolation_smoothness``: the largest step of a latent walk relative to its mean step.
- ``orientation_coherence`` / ``strand_coherence``: how much one direction dominates the local
  gradients (structure tensor): strands and wrinkles near 1, isotropic grain low. The number for "hair
  is grain, not strands" that the band energies cannot see (both carry the same energy).
- ``feature_parts``, ``region_albedo`` and ``region_albedo_bands``: views of ``reflectance_features`` that
  say where a Frechet distance comes from (tone per region vs detail), how each region's albedo is
  distributed, and how much grain each region's albedo has at each scale.
- ``region_spectrum`` / ``spectrum_distance``: how the finest band's energy is spread over 2-D
  frequencies, per region. The band energies and coherences cannot tell sparse pores from a regular
  texel lattice of the same energy; the spectrum can (a lattice is a peak).
- ``crown_flow``: which way the hair runs across the crown, column by column. The data's strands fan out from
  the whorl at the top centre (u = 0.5), turning smoothly through vertical; a G that draws a left and a right
  field meeting in a line (the seam of the 176.50 kimg person test) shows as a jump or a shift of the profile.
- ``hair_share``: per sample, the share of a zone that reads as hair (a rough local texture). The data's beards
  are there or not (a bimodal share); the means over samples that the other measures take cannot see a G that
  draws a thin beard on every face, or none. ``soft_hair_share`` is its differentiable twin, for training.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["ChannelStats", "channel_stats", "StdParts", "std_parts", "region_labels", "reflectance_features",
           "feature_parts", "region_albedo", "frechet_distance", "detail_region", "detail_link",
           "modality_consistency", "interpolation_smoothness", "orientation_coherence", "orientation_field",
           "region_coherence", "strand_coherence", "region_band_energy", "region_albedo_bands", "region_spectrum",
           "spectrum_distance", "spectrum_excess_peak", "region_relief", "region_moments", "region_flat_share",
           "hair_share",
           "soft_hair_share", "soft_hairline_share", "crown_window", "crown_flow", "gaussian_blur", "detail_map",
           "log_chroma", "region_texel_grain", "region_grain_evenness", "LATTICE_PARTS", "texel_lattice", "texel_phase",
           "region_band_correlation", "region_band_magnitude_correlation",
           "region_specular_link", "region_texel_tails", "gamut_excess", "ring_profile",
           "region_edge_sharpness", "SLOPE_KERNELS", "region_slope_link", "filter_fit_r2", "row_profile",
           "hairline_edge_coherence",
           "dark_speck_depth", "nyquist_log_ratio", "corner_log_ratio", "TOP_BANDS", "band_log_ratio",
           "RADIAL_EDGES", "radial_log_profile", "AXIS_EDGES", "axis_log_profile", "region_band_skew",
           "region_band_neighbour",
           "BAND_STATISTICS", "region_band_statistics", "band_statistic_names", "region_quantiles", "local_range",
           "log_luminance"]

_PER_REGION = 28  # reflectance_features: per region, 7 channel means then 3 bands x 7 channels


@dataclass(frozen=True)
class ChannelStats:
    mean: list[float]  # 7 physical channels: A_D r, g, b (linear), A_S, N_S x, y, z
    std: list[float]


def channel_stats(phys: torch.Tensor, mask: torch.Tensor | None = None) -> ChannelStats:
    """phys: (N, 7, R, R) physical maps; mask: (R, R) bool texels to count (default all)."""
    x = phys.float().permute(1, 0, 2, 3).reshape(7, phys.shape[0], -1)
    if mask is not None:
        x = x[:, :, mask.flatten()]
    x = x.reshape(7, -1)
    return ChannelStats(x.mean(1).tolist(), x.std(1).tolist())


@dataclass(frozen=True)
class StdParts:
    """Per physical channel (7), in the channel's units: between**2 + coarse**2 + fine**2 is about the
    channel's variance (the parts are not exactly orthogonal)."""

    between: list[float]  # std of the samples' means over the mask
    coarse: list[float]  # within a sample: the window-averaged map around the sample's mean
    fine: list[float]  # within a sample: the map around its window average


def std_parts(phys: torch.Tensor, mask: torch.Tensor, window: int = 9) -> StdParts:
    """phys: (N, 7, R, R) physical maps, N >= 2; mask: (R, R) bool texels to count; window: odd box size."""
    if phys.ndim != 4 or phys.shape[1] != 7 or len(phys) < 2:
        raise ValueError(f"expected (N >= 2, 7, R, R) maps, got shape {tuple(phys.shape)}")
    if mask.shape != phys.shape[-2:] or mask.dtype != torch.bool:
        raise ValueError(f"expected a bool mask of shape {tuple(phys.shape[-2:])}, got {mask.dtype} {tuple(mask.shape)}")
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 3, got {window}")
    x = phys.float()
    means = x[:, :, mask].mean(2)  # (N, 7)
    local = F.avg_pool2d(x, window, stride=1, padding=window // 2, count_include_pad=False)
    coarse = (local - means[:, :, None, None])[:, :, mask].square().mean((0, 2)).sqrt()
    fine = (x - local)[:, :, mask].square().mean((0, 2)).sqrt()
    return StdParts(means.std(0).tolist(), coarse.tolist(), fine.tolist())


def _bandpass(x: torch.Tensor, levels: int = 3) -> list[torch.Tensor]:
    """Laplacian pyramid bands, each upsampled back to (N, C, R, R), finest first."""
    bands, cur = [], x
    r = x.shape[-1]
    for _ in range(levels):
        low = F.avg_pool2d(cur, 2)
        up = F.interpolate(low, size=cur.shape[-2:], mode="bilinear", align_corners=False)
        bands.append(F.interpolate(cur - up, size=(r, r), mode="nearest"))
        cur = low
    return bands


def region_labels(regions: torch.Tensor) -> list[int]:
    """(R, R) uint8 label map -> its mapped labels (255 = unmapped) ascending: the order of the regions'
    blocks in ``reflectance_features``."""
    return sorted(int(v) for v in torch.unique(regions) if int(v) != 255)


DETAIL_LABELS = (1, 2, 5)  # skin, forehead, nose (shape_model region_uv): where the pores and wrinkles are


def detail_region(regions: torch.Tensor) -> torch.Tensor:
    """(R, R) uint8 label map -> (R, R) bool: the skin regions the modality link is measured on."""
    mask = torch.zeros(regions.shape, dtype=torch.bool, device=regions.device)
    for lab in DETAIL_LABELS:
        mask |= regions == lab
    return mask


def _region_masks(regions: torch.Tensor) -> torch.Tensor:
    """(R, R) uint8 labels -> (k, R, R) bool: each region of ``region_labels``; at least one is required."""
    labels = region_labels(regions)
    if not labels:
        raise ValueError("expected at least one mapped region (labels other than 255), got none")
    return torch.stack([regions == lab for lab in labels])


def _region_weights(regions: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(R, R) uint8 labels -> (k, R*R) in ``like``'s dtype: each region of ``region_labels`` as weights summing to 1."""
    onehot = _region_masks(regions).flatten(1).to(like)
    return onehot / onehot.sum(1, keepdim=True)


def region_band_energy(x: torch.Tensor, regions: torch.Tensor, levels: int = 3) -> torch.Tensor:
    """x: (N, C, R, R) float, any units; regions: (R, R) uint8 labels (255 unmapped) -> (N, k, levels, C)
    same dtype: the RMS of each Laplacian band (``_bandpass``, finest first: 1-2, 2-4, 4-8 ... texels) over each region
    of ``region_labels``. Differentiable (the BRDF-GAN's band and mottle terms)."""
    if x.ndim != 4 or not x.is_floating_point() or regions.shape != x.shape[2:] or regions.dtype != torch.uint8:
        raise ValueError(f"expected float (N, C, R, R) maps and (R, R) uint8 regions matching them, got "
                         f"{tuple(x.shape)} {x.dtype} and {tuple(regions.shape)} {regions.dtype}")
    if levels < 1 or x.shape[-1] % 2**levels:
        raise ValueError(f"levels must be >= 1 and halve the side {x.shape[-1]} exactly, got {levels}")
    w = _region_weights(regions, x)
    bands = torch.stack(_bandpass(x, levels), 1)  # (N, L, C, R, R)
    energy = bands.square().flatten(3) @ w.T  # (N, L, C, k)
    # the root's gradient is infinite at 0 (a flat region): there it is taken of a stand-in 1, as in
    # ``orientation_coherence``
    flat = energy <= 0
    return (torch.where(flat, torch.ones_like(energy), energy).sqrt() * ~flat).permute(0, 3, 1, 2)


def region_texel_grain(x: torch.Tensor, regions: torch.Tensor) -> torch.Tensor:
    """x: (N, C, R, R) float, any units; regions: (R, R) uint8 labels (255 unmapped) -> (N, k, C) same dtype: per
    sample and region of ``region_labels``, the mean |4-neighbour Laplacian| of each channel (edges replicated, so the
    map's border adds none). Its response grows with the square of the frequency, so it weighs single-texel grain
    (pores, speckle, strand edges) that the finest Laplacian-pyramid band (``region_band_energy``, 1-2 texels) shares
    with the octave below it: at 265.00 kimg the face's specular is 0.92-0.99 of the data's in that band and 0.60-0.69
    by this measure on the card (docs/brdf_gan.md, "Single-texel grain"). Differentiable almost everywhere."""
    if x.ndim != 4 or not x.is_floating_point() or regions.shape != x.shape[2:] or regions.dtype != torch.uint8:
        raise ValueError(f"expected float (N, C, R, R) maps and (R, R) uint8 regions matching them, got "
                         f"{tuple(x.shape)} {x.dtype} and {tuple(regions.shape)} {regions.dtype}")
    lap = _laplacian(x, "replicate")
    return (lap.abs().flatten(2) @ _region_weights(regions, x).T).transpose(1, 2)


def region_grain_evenness(x: torch.Tensor, regions: torch.Tensor, block: int = 8) -> torch.Tensor:
    """x: (N, C, R, R) float, any units; regions: (R, R) uint8 labels (255 unmapped) -> (N, k, C) same dtype, >= 0: per
    sample, region of ``region_labels`` and channel, how unevenly the grain is spread: the coefficient of variation
    (std / mean, over tiles) of the grain's RMS in the ``block`` x ``block`` tiles that lie wholly in the region, the
    grain being x minus its 3x3 mean (edges replicated). 0 for a region with fewer than 2 such tiles, or no grain.
    Invariant to a channel's scale and offset.

    The 354.76 kimg judge Q's tell: G's grain over the neck comes in patches where the data's is even (on float maps,
    the albedo's green over rows 196-254, columns 40-216 at 256^2, 8^2 tiles, q10 / q50 / q90: data 0.11 / 0.14 /
    0.34, G 0.21 / 0.26 / 0.32; docs/brdf_gan.md). Differentiable where the tiles' grain is not all zero."""
    if x.ndim != 4 or not x.is_floating_point() or regions.shape != x.shape[2:] or regions.dtype != torch.uint8:
        raise ValueError(f"expected float (N, C, R, R) maps and (R, R) uint8 regions matching them, got "
                         f"{tuple(x.shape)} {x.dtype} and {tuple(regions.shape)} {regions.dtype}")
    r = x.shape[-1]
    if block < 2 or r % block:
        raise ValueError(f"block must be at least 2 and divide the maps' side {r}, got {block}")
    grain = x - F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, 1)
    energy = F.avg_pool2d(grain.square(), block).flatten(2)  # (N, C, T)
    flat = energy <= 0  # the root's gradient is infinite at 0: taken of a stand-in 1 there
    rms = torch.where(flat, torch.ones_like(energy), energy).sqrt() * ~flat
    t = r // block
    tiles = regions.view(t, block, t, block).permute(0, 2, 1, 3).reshape(t * t, block * block)
    pure = (tiles == tiles[:, :1]).all(1)
    w = torch.stack([(pure & (tiles[:, 0] == lab)).to(x) for lab in region_labels(regions)])  # (k, T)
    n = w.sum(1)
    mean = rms @ w.T / n.clamp_min(1)
    var = (rms.square() @ w.T / n.clamp_min(1) - mean.square()).clamp_min(0)
    ok = (n >= 2) & (mean > 0) & (var > 0)
    cv = torch.where(ok, var, torch.ones_like(var)).sqrt() / torch.where(ok, mean, torch.ones_like(mean)) * ok
    return cv.transpose(1, 2)


def region_texel_tails(x: torch.Tensor, regions: torch.Tensor, k: float = 3.0, soft: float = 0.25) -> torch.Tensor:
    """x: (N, C, R, R) float, any units; regions: (R, R) uint8 labels (255 unmapped) -> (N, k', C, 2) same dtype in
    [0, 1]: per sample, region of ``region_labels`` and channel, the share of texels whose 4-neighbour Laplacian (edges
    replicated) lies more than ``k`` of the region's standard deviations above the region's mean (a pit: a texel darker
    than its neighbours) and more than ``k`` below (a bump), each texel counted by sigmoid((|z| - k) / soft), so
    differentiable. A flat region gives 0. Invariant to a channel's scale and offset.

    Every other grain measure (band RMS, spectra, ``region_texel_grain``) is blind to the detail's sign. The data's
    specular has pits and few bumps (96 maps, hard shares at 3 sd, per mille: skin 10.4 / 2.0, forehead 16.2 / 1.8,
    nose 5.6 / 0.0, neck 7.1 / 0.6; two halves within 0.5), G_ema's at 280.01 kimg not (7.6 / 5.4, 4.5 / 3.5, 1.1 /
    3.0, 3.2 / 3.3): the judges' missing crisp pore dots. Shares, not the skewness: a skewness term was met within 0.4
    kimg by a few deep pits (the specular's kurtosis 7 -> 30 on the skin) while D's loss fell to 0.02
    (docs/brdf_gan.md)."""
    if x.ndim != 4 or not x.is_floating_point() or regions.shape != x.shape[2:] or regions.dtype != torch.uint8:
        raise ValueError(f"expected float (N, C, R, R) maps and (R, R) uint8 regions matching them, got "
                         f"{tuple(x.shape)} {x.dtype} and {tuple(regions.shape)} {regions.dtype}")
    if not (k > 0 and soft > 0):
        raise ValueError(f"expected k > 0 and soft > 0, got {k} and {soft}")
    lap = _laplacian(x, "replicate").flatten(2)  # (N, C, R*R)
    w = _region_weights(regions, x).T  # (R*R, k')
    mean, square = lap @ w, lap.square() @ w
    var = square - mean.square()
    flat = var <= 1e-10 * square.clamp_min(torch.finfo(x.dtype).tiny)  # round-off of a flat region
    sd = torch.where(flat, torch.ones_like(var), var).sqrt()
    # each texel's own region (unmapped texels weigh 0 in w, so the one they get does not matter)
    own = _region_masks(regions).flatten(1).to(torch.uint8).argmax(0)
    z = (lap - mean[..., own]) / sd[..., own]
    shares = torch.stack([torch.sigmoid((z - k) / soft) @ w, torch.sigmoid((-z - k) / soft) @ w], -1)  # (N, C, k', 2)
    return (shares * ~flat[..., None]).transpose(1, 2)


def region_edge_sharpness(x: torch.Tensor, regions: torch.Tensor, span: int = 4) -> torch.Tensor:
    """x: (N, C, R, R) float, any units, R > span; regions: (R, R) uint8 labels (255 unmapped) -> (N, k, C) same dtype
    in [1 / span, 1] (0 where a region is flat): per sample, region of ``region_labels`` and channel, how much of a
    change across ``span`` texels happens in its largest single step. Over every row and column run of ``span`` steps,
    each in the region of its centre texel, the sum of (largest |step|) * w over the sum of (sum of |steps|) * w, w the
    run's net |change|, so that edges outweigh grain. A step edge gives 1, a linear ramp over the run 1 / span.
    Invariant to a channel's scale, offset and sign. Differentiable almost everywhere.

    The data's hair, brow, beard and lip edges are per-texel masks; G_ema's at 289.04 kimg were soft or doubled, the
    judges' second tell. In the log albedo luminance (64 maps, medians) data against G: lips 0.75 / 0.60, hairline
    0.58 / 0.52, skin 0.58 / 0.51 (its crisp pits), brow edges 0.52 / 0.48 (docs/brdf_gan.md)."""
    if x.ndim != 4 or not x.is_floating_point() or regions.shape != x.shape[2:] or regions.dtype != torch.uint8:
        raise ValueError(f"expected float (N, C, R, R) maps and (R, R) uint8 regions matching them, got "
                         f"{tuple(x.shape)} {x.dtype} and {tuple(regions.shape)} {regions.dtype}")
    r = x.shape[-1]
    if not 1 <= span < r:
        raise ValueError(f"expected 1 <= span < R = {r}, got {span}")
    w = _region_weights(regions, x).T  # (R*R, k)
    num = den = 0
    for t in (x, x.transpose(2, 3)):  # rows, then columns (a column run is a row run of the transpose)
        steps = (t[..., 1:] - t[..., :-1]).abs()  # (N, C, R, R-1)
        runs = torch.stack([steps[..., j : r - span + j] for j in range(span)], -1)  # runs starting at 0 .. R-span-1
        weight = (t[..., span:] - t[..., :-span]).abs()
        lo = span // 2  # the run from column c spans texels c .. c + span; its centre is c + span // 2
        top = F.pad(runs.amax(-1) * weight, (lo, span - lo))  # back to (N, C, R, R), 0 outside
        total = F.pad(runs.sum(-1) * weight, (lo, span - lo))
        if t is not x:
            top, total = top.transpose(2, 3), total.transpose(2, 3)
        num = num + top.flatten(2) @ w
        den = den + total.flatten(2) @ w
    flat = den <= 0
    return (num / torch.where(flat, torch.ones_like(den), den) * ~flat).transpose(1, 2)


# ``texel_lattice``'s entries, in order
LATTICE_PARTS = ("row_parity", "column_parity", "top", "bottom", "left", "right")
_LATTICE_EPS = 1e-6  # keeps a flat map's 0 / 0 at 1


def texel_lattice(x: torch.Tensor) -> torch.Tensor:
    """x: (N, C, R, R) float, any units, R >= 6 -> (N, C, 6) same dtype: per sample and channel, how the texel lattice
    shows (``LATTICE_PARTS``). Parities: the mean |step| between rows (columns) 2i and 2i + 1 over that between 2i + 1
    and 2i + 2; an upsampling's texel pairs make it < 1. Edges: the mean |step| between the border row (column) and
    the next over the mean |step| between the rows (columns) at least 2 texels inside; a zero-padded convolution's
    border makes it differ from the data's. The data's parities are 1.00 (0.975-1.023 per sample, network space,
    256^2), its edges per channel (docs/brdf_gan.md, "The lattice"). Differentiable almost everywhere."""
    if x.ndim != 4 or not x.is_floating_point() or x.shape[2] != x.shape[3] or x.shape[2] < 6:
        raise ValueError(f"expected float (N, C, R, R) maps with R >= 6, got {tuple(x.shape)} {x.dtype}")
    rows, cols = _mean_steps(x)
    e = _LATTICE_EPS

    def parity(steps):
        return (steps[..., 0::2].mean(-1) + e) / (steps[..., 1::2].mean(-1) + e)

    inner_r, inner_c = rows[..., 2:-2].mean(-1) + e, cols[..., 2:-2].mean(-1) + e
    return torch.stack([parity(rows), parity(cols), (rows[..., 0] + e) / inner_r, (rows[..., -1] + e) / inner_r,
                        (cols[..., 0] + e) / inner_c, (cols[..., -1] + e) / inner_c], -1)


def texel_phase(x: torch.Tensor, period: int = 4) -> torch.Tensor:
    """x: (N, C, R, R) float, any units, R > period -> (N, C, 2, period) same dtype: per sample and channel, the mean
    |step| between rows (then columns) i and i + 1 over the steps with i = k mod ``period``, each over the mean of the
    ``period`` groups: 1 everywhere without a lattice. Period 4 holds ``texel_lattice``'s parities (groups 0 + 2
    against 1 + 3) and the pattern of two upsamplings (64^2 -> 256^2).
    The 365.48 kimg judge Z1's tell: G's per-sample parities |p - 1| were 3-4x the data's in the albedo while their
    batch mean sat on the data's, which the lattice term pulls (docs/brdf_gan.md, "365.48 kimg")."""
    if x.ndim != 4 or not x.is_floating_point() or x.shape[2] != x.shape[3] or x.shape[2] <= period or period < 2:
        raise ValueError(f"expected float (N, C, R, R) maps with R > period >= 2, got {tuple(x.shape)} {x.dtype} "
                         f"and period {period}")
    n = (x.shape[2] - 1) // period * period  # whole periods of steps only, so that every group has as many

    def groups(steps):  # (N, C, R - 1) -> (N, C, period)
        g = steps[..., :n].unflatten(-1, (n // period, period)).mean(-2) + _LATTICE_EPS
        return g / g.mean(-1, keepdim=True)

    rows, cols = _mean_steps(x)
    return torch.stack([groups(rows), groups(cols)], 2)


def _mean_steps(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, C, R, R) -> two (N, C, R - 1): the mean |step| between rows i and i + 1, then between columns: what
    ``texel_lattice`` and ``texel_phase`` group."""
    return (x[:, :, 1:] - x[:, :, :-1]).abs().mean(3), (x[:, :, :, 1:] - x[:, :, :, :-1]).abs().mean(2)


def region_moments(x: torch.Tensor, regions: torch.Tensor) -> torch.Tensor:
    """x: (N, C, R, R) float, any units; regions: (R, R) uint8 labels (255 unmapped) -> (N, k, 2, C) same dtype:
    per sample and region of ``region_labels``, each channel's mean and standard deviation (population) over the
    region's texels. Differentiable (the BRDF-GAN's colour term)."""
    if x.ndim != 4 or not x.is_floating_point() or regions.shape != x.shape[2:] or regions.dtype != torch.uint8:
        raise ValueError(f"expected float (N, C, R, R) maps and (R, R) uint8 regions matching them, got "
                         f"{tuple(x.shape)} {x.dtype} and {tuple(regions.shape)} {regions.dtype}")
    w = _region_weights(regions, x).T  # (R*R, k)
    flat = x.flatten(2)
    mean = flat @ w  # (N, C, k)
    # centred on each texel's own region mean (the regions are disjoint): E[x^2] - E[x]^2 in float32 lost half
    # the digits of a nearly flat region's spread
    var = (flat - mean @ (w.T > 0).to(x)).square() @ w
    # the root's gradient is infinite at 0 (a flat region): there it is taken of a stand-in 1, as in
    # ``region_band_energy``
    zero = var <= 0
    std = torch.where(zero, torch.ones_like(var), var).sqrt() * ~zero
    return torch.stack([mean, std], 1).permute(0, 3, 1, 2)


def region_flat_share(normals: torch.Tensor, regions: torch.Tensor, tau: float = 1e-3) -> torch.Tensor:
    """normals: (N, 2+, R, R) float, unit normals' tangent-space x and y first (only they are read); regions: (R, R)
    uint8 labels (255 unmapped) -> (N, k) same dtype in [0, 1]: per sample and region of ``region_labels``, the mean
    over its texels of exp(-(x^2 + y^2) / tau^2), a soft share of the texels whose normal points straight out.

    The 358.06 kimg judge S's tell: the data draws some of the scalp, the triangles beside the jaw most of all, exactly
    flat (x = y = 0 to the 16-bit PNG's step), where G's normals lean a little everywhere (64 maps at tau 1e-3: the
    scalp's share 1.4 % +- 0.7 % in the data, 0.23 % +- 0.09 % in G; docs/brdf_gan.md). At tau 1e-3 a texel counts
    as flat when the judge's sheet (x 2.5, 8 bits) rounds it to the flat grey. Differentiable (the BRDF-GAN's
    normal-tilt term)."""
    if (normals.ndim != 4 or normals.shape[1] < 2 or not normals.is_floating_point()
            or regions.shape != normals.shape[2:] or regions.dtype != torch.uint8):
        raise ValueError(f"region_flat_share: expected float (N, 2+, R, R) normals and (R, R) uint8 regions matching "
                         f"them, got {tuple(normals.shape)} {normals.dtype} and {tuple(regions.shape)} {regions.dtype}")
    if not (math.isfinite(tau) and tau > 0):
        raise ValueError(f"region_flat_share: tau must be finite and > 0, got {tau}")
    flat = torch.exp(-(normals[:, 0].square() + normals[:, 1].square()) / tau ** 2)
    return flat.flatten(1) @ _region_weights(regions, normals).T


def _check_hair_share(albedo: torch.Tensor, zone: torch.Tensor, window: int) -> None:
    if albedo.ndim != 4 or albedo.shape[1] != 3 or not albedo.is_floating_point() or zone.shape != albedo.shape[2:] \
            or zone.dtype != torch.bool:
        raise ValueError(f"expected float (N, 3, R, R) albedo and an (R, R) bool zone matching it, got "
                         f"{tuple(albedo.shape)} {albedo.dtype} and {tuple(zone.shape)} {zone.dtype}")
    if not bool(zone.any()):
        raise ValueError("expected a zone of at least one texel, got an empty one")
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 1, got {window}")


def log_luminance(albedo: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) linear albedo -> (N, 1, H, W): log of the mean of r, g, b, floored at 1e-3 (a black texel reads
    log 1e-3, not -inf). Every luminance-band measure and term reads this one, so their values agree."""
    if albedo.ndim != 4 or albedo.shape[1] != 3 or not albedo.is_floating_point():
        raise ValueError(f"log_luminance: expected float (N, 3, H, W) linear albedo, got {tuple(albedo.shape)} "
                         f"{albedo.dtype}")
    return albedo.mean(1, keepdim=True).clamp_min(1e-3).log()


def _local_log_var(albedo: torch.Tensor, window: int) -> torch.Tensor:
    """(N, 3, R, R) linear albedo -> (N, R, R): the variance (>= 0) of the log luminance over a ``window``^2 box
    (edges: the box's texels inside the map)."""
    lum = log_luminance(albedo)
    mean = F.avg_pool2d(lum, window, 1, window // 2, count_include_pad=False)
    var = F.avg_pool2d(lum.square(), window, 1, window // 2, count_include_pad=False) - mean.square()
    return var.clamp_min(0)[:, 0]


def hair_share(albedo: torch.Tensor, zone: torch.Tensor, window: int = 5, threshold: float = 0.12) -> torch.Tensor:
    """albedo: (N, 3, R, R) linear, [0, 1]; zone: (R, R) bool -> (N,) float in [0, 1]: per sample, the share of the
    zone's texels where the std of the log luminance over a ``window``^2 box exceeds ``threshold``: hair strands
    against skin's pores and freckles (on the data's beard zone, shaven faces read below 0.05 and most bearded
    ones above 0.8). The log makes the threshold one contrast for every skin tone."""
    _check_hair_share(albedo, zone, window)
    return (_local_log_var(albedo, window).sqrt() > threshold)[:, zone].to(albedo.dtype).mean(1)


def soft_hair_share(albedo: torch.Tensor, zone: torch.Tensor, window: int = 5, threshold: float = 0.12,
                    softness: float = 0.02) -> torch.Tensor:
    """``hair_share`` with the step at ``threshold`` replaced by a sigmoid of width ``softness`` (in log luminance
    std), so that it has a gradient: (N,) float in (0, 1), the same inputs. It tends to ``hair_share`` as
    ``softness`` goes to 0. On 512 data maps at 256^2 (beard zone), mean and mean square: 0.203 / 0.143 at 0.02
    against the step's 0.176 / 0.147; at 0.04 the mean rose to 0.284, the smooth skin's near-threshold texels
    counting as part hair."""
    _check_hair_share(albedo, zone, window)
    return _soft_hair(albedo, window, threshold, softness)[:, zone].mean(1)


def _soft_hair(albedo: torch.Tensor, window: int, threshold: float, softness: float) -> torch.Tensor:
    """(N, 3, R, R) linear albedo -> (N, R, R) in (0, 1): ``soft_hair_share``'s texture test per texel."""
    if not (softness > 0 and math.isfinite(softness)):
        raise ValueError(f"softness must be finite and > 0, got {softness}")
    std = (_local_log_var(albedo, window) + 1e-6).sqrt()  # 1e-6: a finite gradient where the albedo is flat
    return torch.sigmoid((std - threshold) / softness)


def soft_hairline_share(albedo: torch.Tensor, reach: torch.Tensor, face: torch.Tensor, scalp: torch.Tensor,
                        window: int = 5, threshold: float = 0.12, softness: float = 0.02,
                        min_contrast: float = 0.3) -> torch.Tensor:
    """albedo: (N, 3, R, R) linear, [0, 1]; reach, face, scalp: (R, R) bool (``data.hairline_reach`` and
    ``data.hairline_references``) -> (N,) float in [0, 1]: per sample, the share of ``reach`` that is hair by its
    texture or by its colour, 1 - (1 - t)(1 - a). t is ``soft_hair_share``'s texture test; a is the log luminance's
    distance from the mean over ``face`` over the scalp mean's (over ``scalp``), clamped to [0, 1]. The two means
    carry no gradient, and their difference is floored at ``min_contrast`` in magnitude (log luminance): where hair
    and skin are alike, colour says little and texture decides.
    Texture alone counts a smooth band between skin and hair as skin: pulled on that measure from 207.88 kimg, G
    lowered its share by widening a blurred rim along the hairline, not by moving the hairline. A signed position
    between the two means (clamped) counted a rim darker or lighter than the skin, away from the hair, as skin, and
    G drew such rims too (docs/brdf_gan.md). Here only untextured, skin-coloured texels lower the share."""
    _check_hair_share(albedo, reach, window)
    _check_references(reach, face, scalp)
    _check_min_contrast(min_contrast)
    t = _soft_hair(albedo, window, threshold, softness)[:, reach]
    a = _hair_colour(albedo, face, scalp, min_contrast)[:, reach]
    return (1 - (1 - a) * (1 - t)).mean(1)


def _check_references(reach: torch.Tensor, face: torch.Tensor, scalp: torch.Tensor) -> None:
    for name, m in (("face", face), ("scalp", scalp)):
        if m.shape != reach.shape or m.dtype != torch.bool or not bool(m.any()):
            raise ValueError(f"expected a non-empty (R, R) bool {name} mask like the reach {tuple(reach.shape)}, got "
                             f"{tuple(m.shape)} {m.dtype} with {int(m.sum()) if m.dtype == torch.bool else '?'} texels")


def _check_min_contrast(min_contrast: float) -> None:
    if not (min_contrast > 0 and math.isfinite(min_contrast)):
        raise ValueError(f"min_contrast must be finite and > 0, got {min_contrast}")


def _hair_colour(albedo: torch.Tensor, face: torch.Tensor, scalp: torch.Tensor, min_contrast: float) -> torch.Tensor:
    """(N, 3, R, R) linear albedo -> (N, R, R) in [0, 1]: ``soft_hairline_share``'s colour test per texel, the log
    luminance's distance from the mean over ``face`` over the scalp mean's, the means without gradient."""
    lum = log_luminance(albedo)[:, 0]
    with torch.no_grad():
        f = lum[:, face].mean(1)
        c = (lum[:, scalp].mean(1) - f).abs().clamp_min(min_contrast)
    return ((lum - f[:, None, None]).abs() / c[:, None, None]).clamp(max=1)


def hairline_edge_coherence(albedo: torch.Tensor, reach: torch.Tensor, face: torch.Tensor, scalp: torch.Tensor,
                            sigma: float = 2.5, min_contrast: float = 0.3) -> torch.Tensor:
    """albedo: (N, 3, R, R) linear, [0, 1]; reach, face, scalp: (R, R) bool as ``soft_hairline_share``'s, R > 6 sigma
    -> (N,) float in [0, 1]: per sample, how smooth the hairline's outline runs. The ``orientation_coherence`` (window
    ``sigma`` texels) of the colour test a (``_hair_colour``: 0 skin, 1 hair), averaged over ``reach`` with weights
    |grad a| (central differences, no gradient through them), so that the edge between skin and hair counts, not the
    flat skin or hair beside it. A straight or gently curved edge gives ~1; a ragged one, whose gradients turn from
    texel to texel, less.
    The data's outline is ragged (``fitme dataset``: the hairline's offset noise down to 0.002 UV at 250 cycles);
    G_ema's at 308.28 kimg was a smooth egg on dark hair, a judge's first tell. At 256^2, 128 data maps against 128
    G_ema maps: mean 0.475 / 0.537, sd 0.069 / 0.129, the two distributions' KS distance 0.44 (two halves of the
    data: 0.12); G's smoothest outlines 0.78-0.80, the data's 0.57-0.58, both on dark hair (docs/brdf_gan.md)."""
    _check_hair_share(albedo, reach, 1)
    _check_references(reach, face, scalp)
    _check_min_contrast(min_contrast)
    a = _hair_colour(albedo, face, scalp, min_contrast)
    coherence = orientation_coherence(a, sigma)
    with torch.no_grad():
        gx, gy = _central_differences(a[:, None], "constant")
        w = (gx.square() + gy.square()).sqrt()[:, 0] * reach
    return (coherence * w).flatten(1).sum(1) / w.flatten(1).sum(1).clamp_min(1e-12)


def dark_speck_depth(albedo: torch.Tensor, zone: torch.Tensor, face: torch.Tensor, scalp: torch.Tensor,
                     q: float = 0.01) -> torch.Tensor:
    """albedo: (N, 3, R, R) linear, [0, 1]; zone, face, scalp: (R, R) bool (e.g. the hairline band of
    ``data.hairline_zones``, and ``data.hairline_references``) -> (N,) float >= 0, log luminance units: per sample, the
    mean over ``zone`` of how far each texel's log luminance falls below the darker of the face's and the scalp's ``q``
    quantiles (0 above it). The quantiles carry no gradient: a texel darker than nearly all of the sample's skin and hair
    pulls itself up, not the threshold down.
    G_ema's hairline at 308.28 kimg had dark specks along it, darker than its hair and its skin (a judge's tell); the
    data's has next to none. At 256^2 over the hairline band, 128 maps each: data 0.15e-3 (q90 0.38e-3), G_ema 5.7e-3
    (q90 11e-3); over the scalp just behind it 1.45e-3 against 11.4e-3 (docs/brdf_gan.md)."""
    _check_hair_share(albedo, zone, 1)
    _check_references(zone, face, scalp)
    if not 0 < q < 1:
        raise ValueError(f"q must be in (0, 1), got {q}")
    lum = log_luminance(albedo)[:, 0]
    with torch.no_grad():
        t = torch.minimum(torch.quantile(lum[:, face], q, dim=1), torch.quantile(lum[:, scalp], q, dim=1))
    return (t[:, None] - lum[:, zone]).clamp_min(0).mean(1)


def _windowed_power(x: torch.Tensor) -> torch.Tensor:
    """(N, C, R, R) -> (N, C, R, R): the FFT power (unshifted) of each map, its mean removed, under a periodic Hann
    window: without it the map's unmatched borders leak a broadband step into every row of the spectrum."""
    win = torch.hann_window(x.shape[-1], periodic=True, dtype=x.dtype, device=x.device)
    return torch.fft.fft2((x - x.mean((2, 3), keepdim=True)) * win[:, None] * win[None, :]).abs().square()


def _spectral_side(x: torch.Tensor, min_even: int | None = None) -> int:
    """R of float (N, C, R, R) maps, the spectral ratios' shared input check; ``min_even``: R must also be even and at
    least that."""
    if x.ndim != 4 or not x.is_floating_point() or x.shape[-1] != x.shape[-2]:
        raise ValueError(f"expected float (N, C, R, R) maps, got {tuple(x.shape)} {x.dtype}")
    r = x.shape[-1]
    if min_even is not None and (r % 2 or r < min_even):
        raise ValueError(f"expected an even R >= {min_even}, got {r}")
    return r


def nyquist_log_ratio(x: torch.Tensor, below: tuple[int, int] | None = None) -> torch.Tensor:
    """x: (N, C, R, R) float, any units, R even and > 2 * below[1] -> (N, C): per sample and channel, the log of the
    mean FFT energy on the Nyquist row and column (frequency R / 2 along v or u, every frequency along the other) over
    the mean energy of the rows and columns ``below`` (from R / 2 - below[1] up to, not including, R / 2 - below[0];
    default (2, 8), cut to (2, R / 2 - 2) below 32^2 for tiny maps), the map Hann-windowed.
    ~0 for white noise, very negative for smooth maps, large for a texel checkerboard (neighbours alternating).
    A judge told every G_ema map at 318.61 kimg by it: 64 maps each at 256^2, albedo (mean of r, g, b) data +0.08
    (q10-q90 -0.04 to +0.18) against +0.61 (+0.36 to +1.12), normals x -2.66 against +1.23 (docs/brdf_gan.md)."""
    r = _spectral_side(x)
    lo, hi = below if below is not None else (2, min(8, r // 2 - 2))
    if not 0 < lo < hi or r % 2 or r <= 2 * hi:
        raise ValueError(f"expected 0 < below[0] < below[1] and an even R > 2 * below[1], got below {below}, R {r}")
    f = _windowed_power(x)
    h = r // 2
    nyq = f[..., h, :].mean(-1) + f[..., :, h].mean(-1)
    ref = f[..., h - hi:h - lo, :].mean((-2, -1)) + f[..., :, h - hi:h - lo].mean((-2, -1))
    return (nyq.clamp_min(1e-30) / ref.clamp_min(1e-30)).log()


def corner_log_ratio(x: torch.Tensor, half_width: int | None = None) -> torch.Tensor:
    """x: (N, C, R, R) float, any units, R even and >= 8 -> (N, C): per sample and channel, the log of the mean FFT
    energy in the square of ``half_width`` k bins around the diagonal corner (R / 2, R / 2) (frequencies within k bins
    of Nyquist along both u and v) over the mean energy of the rest of the block [R / 4, 3 R / 4]^2 (both frequencies
    at least 1/4 cycle per texel), the map Hann-windowed. Default k = max(1, round(0.02 R)), 5 at 256^2; 0 <= k < R / 4.
    ~0 for white noise, large for a diagonal checkerboard (each texel against its diagonal neighbours), which
    ``nyquist_log_ratio`` dilutes over the whole Nyquist row and column. At 343.17 kimg (64 maps each at 256^2, k 5,
    q10 / q50 / q90) the G_ema normals x gave -3.97 / -3.56 / -3.26 against the data's -5.39 / -5.01 / -4.42, and the
    specular +0.16 against +0.01 at the median, after the 343.76 kimg judge found the specular's diagonal checkerboard
    (docs/brdf_gan.md)."""
    r = _spectral_side(x)
    k = max(1, round(0.02 * r)) if half_width is None else half_width
    if r % 2 or r < 8 or not 0 <= k < r // 4:
        raise ValueError(f"expected an even R >= 8 and 0 <= half_width < R / 4, got R {r}, half_width {k}")
    f = _windowed_power(x)
    h, q = r // 2, r // 4
    block = f[..., q:r - q + 1, q:r - q + 1]  # unshifted layout: bins R/4..3R/4 are the frequencies >= 1/4 cycle
    near = torch.zeros(block.shape[-2:], dtype=torch.bool, device=x.device)
    near[h - q - k:h - q + k + 1, h - q - k:h - q + k + 1] = True
    corner, rest = block[..., near].mean(-1), block[..., ~near].mean(-1)  # a mask, not a difference of sums
    return (corner.clamp_min(1e-30) / rest.clamp_min(1e-30)).log()


# ``band_log_ratio``'s default bands, cycles per texel (Chebyshev radius): just below Nyquist, and up to it
TOP_BANDS = ((7 / 16, 15 / 32), (15 / 32, 1 / 2))


def band_log_ratio(x: torch.Tensor, bands: tuple[tuple[float, float], ...] = TOP_BANDS,
                   reference: tuple[float, float] = (1 / 4, 3 / 8)) -> torch.Tensor:
    """x: (N, C, R, R) float, any units, R even and >= 16 -> (N, C, len(bands)): per sample, channel and band, the log
    of the mean FFT energy of the frequencies whose Chebyshev radius max(|u|, |v|) (cycles per texel) lies in the band
    [lo, hi) (a band ending at 1/2 includes Nyquist) over the mean energy of the ``reference`` band, the map
    Hann-windowed. Each band must hold at least one frequency.
    ``nyquist_log_ratio`` compares Nyquist with the rows just below it, and a peak there lowers it: G_ema's normals at
    346.00 kimg had a peak at 0.47-0.49 cycles per texel, ~300x the data's power over the face, which the Nyquist
    term had pushed in from Nyquist (docs/brdf_gan.md, "The layout as a gain"). Against a reference band where G and
    the data agree (1/4-3/8 cycle), every part of the spectrum's top shows."""
    r = _spectral_side(x, min_even=16)
    freq = torch.fft.fftfreq(r, device=x.device).abs()
    radius = torch.maximum(freq[:, None], freq[None, :])  # unshifted, as the FFT's bins; Nyquist is -1/2: |.| = 1/2
    f = _windowed_power(x)

    def mean_in(lo: float, hi: float) -> torch.Tensor:
        if not 0 <= lo < hi <= 0.5:
            raise ValueError(f"expected bands 0 <= lo < hi <= 1/2, got ({lo}, {hi})")
        inside = (radius >= lo) & ((radius < hi) | (hi == 0.5))
        if not inside.any():
            raise ValueError(f"the band ({lo}, {hi}) holds no frequency at R {r}")
        return f[..., inside].mean(-1)

    ref = mean_in(*reference).clamp_min(1e-30)
    return torch.stack([(mean_in(lo, hi).clamp_min(1e-30) / ref).log() for lo, hi in bands], -1)


def _edge_masks(radius: torch.Tensor, edges: tuple[float, ...], r: int, name: str, nyquist: bool) -> list[torch.Tensor]:
    """The profiles' shared bins: per pair of ``edges`` (at least 2, increasing, in [0, 1/2]), the mask of ``radius``
    (cycles per texel) in [lo, hi), or up to and including 1/2 for the last when ``nyquist``; each must hold a
    frequency at R ``r`` (``name``: "ring" or "band", for the error)."""
    pairs = list(zip(edges[:-1], edges[1:]))
    if len(edges) < 2 or any(not 0 <= lo < hi <= 0.5 for lo, hi in pairs):
        raise ValueError(f"expected at least 2 increasing edges in [0, 1/2], got {edges}")
    masks = [(radius >= lo) & ((radius < hi) | (nyquist and hi == 0.5)) for lo, hi in pairs]
    for (lo, hi), mask in zip(pairs, masks):
        if not mask.any():
            raise ValueError(f"the {name} ({lo}, {hi}) holds no frequency at R {r}")
    return masks


# ``radial_log_profile``'s default rings, cycles per texel (Euclidean radius): tenths of an octave's worth up to Nyquist
RADIAL_EDGES = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5)


def radial_log_profile(x: torch.Tensor, edges: tuple[float, ...] = RADIAL_EDGES) -> torch.Tensor:
    """x: (N, C, R, R) float, any units, R even and >= 16 -> (N, C, len(edges) - 1): per sample, channel and ring, the
    log of the mean FFT energy of the frequencies whose Euclidean radius |(u, v)| (cycles per texel) lies in
    [edges[i], edges[i + 1]) over the mean energy of all the frequencies in [edges[0], edges[-1]), the map
    Hann-windowed: the shape of the spectrum's fall, blind to the map's scale and offset. The rings leave out the
    diagonal corners beyond 1/2 cycle, which ``corner_log_ratio`` and ``band_log_ratio`` (Chebyshev bands) include.
    Each ring must hold at least one frequency.
    The 363.08 kimg judge V's tell: over the whole map the normals' x energy at 0.45-0.5 cycle over 0.15-0.2 read
    4 dB below the data's (network space, 64 maps at 256^2: G -25.2 dB against -20.9, q10-q90 of the data -21.7 to
    -20.1) while ``band_log_ratio``'s Chebyshev bands, which the Nyquist term holds, sat on the data's."""
    r = _spectral_side(x, min_even=16)
    freq = torch.fft.fftfreq(r, dtype=torch.float64, device=x.device)
    radius = (freq[:, None].square() + freq[None, :].square()).sqrt()
    rings = _edge_masks(radius, edges, r, "ring", nyquist=False)
    f = _windowed_power(x)
    ref = f[..., (radius >= edges[0]) & (radius < edges[-1])].mean(-1).clamp_min(1e-30)
    return torch.stack([(f[..., ring].mean(-1).clamp_min(1e-30) / ref).log() for ring in rings], -1)


# ``axis_log_profile``'s default bands, cycles per texel along one axis: 1/32 wide from 5/16 up to Nyquist
AXIS_EDGES = (10 / 32, 11 / 32, 12 / 32, 13 / 32, 14 / 32, 15 / 32, 16 / 32)


def axis_log_profile(x: torch.Tensor, edges: tuple[float, ...] = AXIS_EDGES) -> torch.Tensor:
    """x: (N, C, R, R) float, any units, R even and >= 16 -> (N, C, 2, len(edges) - 1): per sample and channel, along
    u (columns' frequency, every v) and then along v (every u), the log of the mean FFT energy of the frequencies whose
    |u| (or |v|) lies in [edges[i], edges[i + 1]) (a band ending at 1/2 includes Nyquist) over the mean energy of
    all the bands' frequencies, the map Hann-windowed: a 1-D spectrum's shape along one axis, summed over the other,
    as a row-by-row 1-D FFT gives it. ``radial_log_profile``'s rings mix the directions; a normal map's x varies most
    along u and its y along v, and a notch there shows in one axis only.
    The 372.22 kimg judge AC2's tell (docs/brdf_gan.md): on the sheet (``train.sheet_maps``, 48 maps at 256^2) the
    normals x along u and y along v held a notch at 0.41-0.45 cycle and a spike at 0.453 that the data has not."""
    r = _spectral_side(x, min_even=16)
    freq = torch.fft.fftfreq(r, dtype=torch.float64, device=x.device).abs()  # Nyquist is -1/2: |.| = 1/2
    bands = _edge_masks(freq, edges, r, "band", nyquist=True)
    whole = torch.stack(bands).any(0)
    f = _windowed_power(x)
    per_axis = torch.stack([f.mean(-2), f.mean(-1)], 2)  # (N, C, 2, R): energy by u (mean over v), by v (over u)
    ref = per_axis[..., whole].mean(-1).clamp_min(1e-30)
    return torch.stack([(per_axis[..., band].mean(-1).clamp_min(1e-30) / ref).log() for band in bands], -1)


def reflectance_features(phys: torch.Tensor, regions: torch.Tensor) -> np.ndarray:
    """(N, 7, R, R) physical maps, (R, R) uint8 region labels (255 unmapped) -> (N, 224) float64."""
    x = phys.float()
    means = (x.flatten(2) @ _region_weights(regions, x).T).transpose(1, 2)  # (N, k, 7)
    bands = region_band_energy(x, regions).flatten(2)  # (N, k, 21): band 0's 7 channels, then 1's, 2's
    return torch.cat([means, bands], 2).flatten(1).double().numpy()


def feature_parts(feats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 28 k) reflectance features -> (tone (N, 7 k): the region means, detail (N, 21 k): the band energies)."""
    if feats.ndim != 2 or feats.shape[1] % _PER_REGION:
        raise ValueError(f"expected (N, 28 * regions) reflectance features, got shape {feats.shape}")
    blocks = feats.reshape(len(feats), -1, _PER_REGION)
    return blocks[:, :, :7].reshape(len(feats), -1), blocks[:, :, 7:].reshape(len(feats), -1)


def region_albedo(feats: np.ndarray) -> np.ndarray:
    """(N, 28 k) reflectance features -> (N, k) each sample's mean linear albedo (mean of r, g, b) per
    region, in ``region_labels`` order."""
    tone, _ = feature_parts(feats)
    return tone.reshape(len(feats), -1, 7)[:, :, :3].mean(2)


def _region_patches(regions: torch.Tensor, patch: int) -> list[torch.Tensor]:
    """Per region of ``region_labels``: the (n,) long indices, in ``F.unfold`` order at stride patch/2, of the
    patch x patch windows wholly inside it."""
    onehot = _region_masks(regions)[:, None].float()  # (k, 1, R, R)
    inside = F.unfold(onehot, patch, stride=patch // 2).amin(1)  # (k, L)
    return [torch.nonzero(row > 0.5).flatten() for row in inside]


def region_spectrum(img: torch.Tensor, regions: torch.Tensor, patch: int = 16) -> torch.Tensor:
    """img: (N, R, R) float, any units; regions: (R, R) uint8 labels (255 unmapped) -> (N, k, patch, patch // 2 + 1)
    same dtype: per sample and region of ``region_labels``, the power spectrum of the finest Laplacian band
    (``_bandpass``: 1-2 texels) averaged over the Hann-windowed patch x patch windows (stride patch/2)
    wholly inside the region, normalised to sum 1. One half-plane of frequencies (``torch.fft.rfft2``
    layout: row fy mod patch, column fx, in cycles per patch); the columns that stand for two
    conjugate bins count twice, so the sum is over the whole plane. A region with no whole window, or a
    sample flat in it, gives zeros. Differentiable."""
    if img.ndim != 3 or not img.is_floating_point() or regions.shape != img.shape[1:] or regions.dtype != torch.uint8:
        raise ValueError(f"expected float (N, R, R) maps and (R, R) uint8 regions matching them, got "
                         f"{tuple(img.shape)} {img.dtype} and {tuple(regions.shape)} {regions.dtype}")
    if patch < 4 or patch % 2 or patch > img.shape[-1]:
        raise ValueError(f"patch must be even, at least 4 and at most the map size {img.shape[-1]}, got {patch}")
    band = _bandpass(img[:, None], 1)[0]
    hann = torch.hann_window(patch, periodic=False, dtype=img.dtype, device=img.device)
    cols = F.unfold(band, patch, stride=patch // 2)  # (N, patch^2, L)
    half = torch.full((patch // 2 + 1,), 2.0, dtype=img.dtype, device=img.device)
    half[0] = half[-1] = 1.0
    out = []
    for idx in _region_patches(regions, patch):
        if len(idx) == 0:
            out.append(img.new_zeros(len(img), patch, patch // 2 + 1))
            continue
        p = cols[:, :, idx.to(img.device)].transpose(1, 2).reshape(len(img), -1, patch, patch)
        p = (p - p.mean((2, 3), keepdim=True)) * hann[:, None] * hann
        power = torch.fft.rfft2(p).abs().square().mean(1) * half
        total = power.sum((1, 2), keepdim=True)
        out.append(power / torch.where(total > 0, total, torch.ones_like(total)))
    return torch.stack(out, 1)


def _check_spectra(a: torch.Tensor, b: torch.Tensor) -> None:
    if a.ndim != 4 or a.shape[1:] != b.shape[1:]:
        raise ValueError(f"expected two (N, k, P, P/2+1) spectra of the same regions, got {tuple(a.shape)} and {tuple(b.shape)}")


def spectrum_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a (N, k, P, P/2+1), b (M, k, P, P/2+1) ``region_spectrum`` of two sets -> (k,): per region, the total
    variation distance between their mean spectra, the share of the finest band's energy that sits at
    other frequencies (0: the same spread, 1: disjoint). Counts each conjugate pair once, as
    ``region_spectrum`` normalises."""
    _check_spectra(a, b)
    return 0.5 * (a.mean(0) - b.mean(0)).abs().sum((1, 2))


def spectrum_excess_peak(a: torch.Tensor, b: torch.Tensor) -> list[tuple[float, float, float]]:
    """a, b as ``spectrum_distance`` -> per region, where a's mean spectrum most exceeds b's: (fy, fx) in cycles
    per texel (fy signed, fx >= 0) and the excess's share of the energy. A lattice shows as a large excess
    at a fixed frequency."""
    _check_spectra(a, b)
    patch = a.shape[2]
    out = []
    for d in a.mean(0) - b.mean(0):
        i = int(torch.argmax(d))
        fy, fx = divmod(i, d.shape[1])
        fy = fy - patch if fy > patch // 2 else fy
        out.append((fy / patch, fx / patch, float(d.flatten()[i])))
    return out


def region_albedo_bands(feats: np.ndarray) -> np.ndarray:
    """(N, 28 k) reflectance features -> (N, k, 3) each sample's linear albedo band RMS (mean of r, g, b) per
    region of ``region_labels`` and band (finest first)."""
    _, detail = feature_parts(feats)
    return detail.reshape(len(feats), -1, 3, 7)[:, :, :, :3].mean(3)


def frechet_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Frechet distance between Gaussians fitted to feature rows a (N, F) and b (M, F)."""
    from scipy import linalg

    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    covmean = np.asarray(linalg.sqrtm(s1 @ s2)).real  # tiny imaginary parts from round-off
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1 + s2 - 2 * covmean))


def _divergence(n: torch.Tensor) -> torch.Tensor:
    """(N, 3, R, R) unit normals (+x = u right, +y = v up; image rows go down) -> (N, R, R) d nx/du + d ny/dv."""
    dx = n[:, 0, :, 2:] - n[:, 0, :, :-2]
    dy = n[:, 1, :-2, :] - n[:, 1, 2:, :]  # v grows upward: row above minus row below
    return F.pad(dx, (1, 1))[:, :, :] + F.pad(dy, (0, 0, 1, 1))


def _albedo_detail(x: torch.Tensor) -> torch.Tensor:
    """(N, 7, R, R) -> (N, R, R): the albedo's luminance minus its 9-texel mean."""
    lum = x[:, 0:3].mean(1, keepdim=True)
    return (lum - F.avg_pool2d(lum, 9, stride=1, padding=4, count_include_pad=False))[:, 0]


def _masked_corr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """(N, R, R) twice -> (N,): per-sample correlation over the texels of mask (None: all)."""
    a, b = (a.flatten(1), b.flatten(1)) if mask is None else (a[:, mask], b[:, mask])
    a = a - a.mean(1, keepdim=True)
    b = b - b.mean(1, keepdim=True)
    return (a * b).sum(1) / (a.norm(dim=1) * b.norm(dim=1) + 1e-12)


def detail_link(x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) float, differentiable: per sample, the correlation of the albedo's fine detail (luminance
    minus its 9-texel mean) with the normals' divergence (cavities < 0) over the texels of ``mask``
    (R, R) bool (None: all); positive when cavities are darker. x: (B, 7, R, R), physical maps (the
    card's ``modality_consistency``) or network space (the training term, ``train.link_loss``): on the
    skin regions (``detail_region``) the two agree in sign and order (data 0.376 / 0.394)."""
    if x.ndim != 4 or x.shape[1] != 7 or x.shape[2] < 9:
        raise ValueError(f"detail_link: expected (B, 7, R >= 9, R) maps, got {tuple(x.shape)}")
    if mask is not None and (mask.shape != x.shape[2:] or mask.dtype != torch.bool or int(mask.sum()) < 2):
        raise ValueError(f"detail_link: expected a bool mask of shape {tuple(x.shape[2:])} with >= 2 texels set, "
                         f"got {mask.dtype} {tuple(mask.shape)}")
    return _masked_corr(_albedo_detail(x), _divergence(x[:, 4:7]), mask)


def modality_consistency(phys: torch.Tensor, mask: torch.Tensor) -> tuple[float, float]:
    """(mean ``detail_link`` of matching pairs, the same for mismatched pairs (sample i's albedo with
    sample i+1's normals)). Cavities (divergence < 0) that are darker give a positive correlation."""
    detail, div = _albedo_detail(phys), _divergence(phys[:, 4:7])
    return float(_masked_corr(detail, div, mask).mean()), float(_masked_corr(detail, div.roll(1, 0), mask).mean())


def interpolation_smoothness(images: torch.Tensor) -> float:
    """images: (T, C, R, R) along a latent path. max step / mean step (1 = perfectly even)."""
    steps = (images[1:] - images[:-1]).abs().mean(dim=(1, 2, 3))
    return float(steps.max() / steps.mean().clamp(min=1e-12))


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """(N, 1, R, R) -> same, separable Gaussian (radius 3 sigma), reflected borders."""
    r = int(math.ceil(3 * sigma))
    t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    g = torch.exp(-t * t / (2 * sigma * sigma))
    g = g / g.sum()
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="reflect"), g.view(1, 1, 1, -1))
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="reflect"), g.view(1, 1, -1, 1))


def _central_differences(x: torch.Tensor, mode: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, C, R, R) -> gx, gy, each (N, C, R, R): x[u + 1] - x[u - 1] along columns and rows, the border texels padded
    by ``F.pad``'s ``mode`` ("replicate": the neighbour's difference; "constant": 0)."""
    gx = F.pad(x[..., :, 2:] - x[..., :, :-2], (1, 1, 0, 0), mode=mode)
    gy = F.pad(x[..., 2:, :] - x[..., :-2, :], (0, 0, 1, 1), mode=mode)
    return gx, gy


def _structure_tensor(img: torch.Tensor, sigma: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(N, R, R) -> jxx, jyy, jxy, each (N, 1, R, R): central-difference gradients' outer products, smoothed
    by a Gaussian of ``sigma`` texels."""
    if img.ndim != 3 or not img.is_floating_point():
        raise ValueError(f"expected a float (N, R, R) image, got {tuple(img.shape)} {img.dtype}")
    if not sigma > 0 or min(img.shape[1:]) <= 6 * sigma:
        raise ValueError(f"expected sigma > 0 and maps wider than 6 sigma, got sigma {sigma} for {tuple(img.shape[1:])}")
    gx, gy = _central_differences(img[:, None], "replicate")
    jxx, jyy, jxy = (gaussian_blur(a, sigma) for a in (gx * gx, gy * gy, gx * gy))
    return jxx, jyy, jxy


def orientation_coherence(img: torch.Tensor, sigma: float = 1.5) -> torch.Tensor:
    """img: (N, R, R) float, any units, R > 6 sigma. -> (N, R, R) in [0, 1]: (l1 - l2) / (l1 + l2) of the
    structure tensor (central-difference gradients, outer products smoothed by a Gaussian of ``sigma``
    texels). Parallel stripes give 1, isotropic white noise 0.24 at sigma 1.5 (0.13 at 3), a flat image 0."""
    jxx, jyy, jxy = _structure_tensor(img, sigma)
    # the smoothed tensor is positive semidefinite, so the root never exceeds the trace, and a flat
    # window (both 0) gives 0 without a batch-wide threshold; the root's gradient is infinite at 0, so
    # there it is taken of a stand-in 1 (the same values, finite gradients for the coherence term)
    disc = (jxx - jyy) ** 2 + 4 * jxy * jxy
    root = torch.where(disc > 0, torch.sqrt(torch.where(disc > 0, disc, torch.ones_like(disc))), torch.zeros_like(disc))
    return (root / (jxx + jyy).clamp(min=1e-30))[:, 0]


def orientation_field(img: torch.Tensor, sigma: float = 1.5) -> torch.Tensor:
    """img: (N, R, R) float -> (N, 2, R, R): coherence * (cos 2t, sin 2t), t the angle of the dominant
    gradient (the doubled angle makes t and t + pi, one stripe direction, the same vector). Its norm is
    ``orientation_coherence``; its mean over samples is long where every sample's stripes run the same
    way (the data's hair flows from the crown: 0.61 of a possible 0.67 on the scalp)."""
    jxx, jyy, jxy = _structure_tensor(img, sigma)
    return torch.cat([jxx - jyy, 2 * jxy], 1) / (jxx + jyy).clamp(min=1e-30)


def crown_window(resolution: int) -> tuple[slice, slice]:
    """Rows and columns of the crown in the UV layout at ``resolution``: rows R/128 to 5R/32 and columns 3R/8 to
    5R/8 (2-40 and 96-160 at 256^2), the top centre where the data's hair fans out from the whorl; the window
    ``docs/brdf_gan_crown_176kimg.png`` shows."""
    if resolution < 128 or resolution % 128:
        raise ValueError(f"crown_window needs a resolution that is a multiple of 128, got {resolution}")
    return slice(resolution // 128, 5 * resolution // 32), slice(3 * resolution // 8, 5 * resolution // 8)


def crown_flow(lum: torch.Tensor, sigma: float = 1.5) -> torch.Tensor:
    """lum: (N, R, R) float luminance, any units, R a multiple of 128 -> (N, 2, 32) same dtype: 32 column
    bins of R / 128 texels: ``orientation_field`` (coherence x (cos 2t, sin 2t), t the dominant gradient's angle)
    averaged over the ``crown_window``'s rows and each bin's columns. Component 0 is 1 for strands running
    along v (vertical in the map), -1 along u; component 1 is the strands' tilt. The data's mean over samples
    (256^2): component 1 runs from +0.6 to -0.6 across the window, through 0 at u = 0.5, while component 0
    peaks there (0.39). Differentiable (the BRDF-GAN's crown term); the field is taken on a band of rows
    below the window too, so that its lower edge is not a border."""
    if lum.ndim != 3 or not lum.is_floating_point() or lum.shape[1] != lum.shape[2]:
        raise ValueError(f"expected float (N, R, R) luminance, got {tuple(lum.shape)} {lum.dtype}")
    rows, cols = crown_window(lum.shape[-1])
    band = orientation_field(lum[:, : rows.stop + lum.shape[-1] // 32], sigma)  # (N, 2, rows', R)
    w = band[:, :, rows, cols].mean(2)  # (N, 2, cols)
    return w.unflatten(2, (-1, lum.shape[-1] // 128)).mean(3)


def _laplacian(x: torch.Tensor, mode: str) -> torch.Tensor:
    """(N, C, R, R) -> same: the 5-point Laplacian (4 neighbours minus 4x the texel), borders padded by ``mode``
    (``F.pad``'s "reflect" or "replicate")."""
    p = F.pad(x, (1, 1, 1, 1), mode=mode)
    return p[..., :-2, 1:-1] + p[..., 2:, 1:-1] + p[..., 1:-1, :-2] + p[..., 1:-1, 2:] - 4 * x


def _laplacian_ref(x: torch.Tensor) -> torch.Tensor:
    """Slow twin of ``detail_map``'s Laplacian: (N, C, R, R) -> same, loops over texels, reflected borders."""
    n, c, r, _ = x.shape
    out = torch.empty_like(x)
    for i in range(r):
        for j in range(r):
            up, down = abs(i - 1), r - 1 - abs(r - 1 - (i + 1))
            left, right = abs(j - 1), r - 1 - abs(r - 1 - (j + 1))
            out[:, :, i, j] = x[:, :, up, j] + x[:, :, down, j] + x[:, :, i, left] + x[:, :, i, right] - 4 * x[:, :, i, j]
    return out


def detail_map(x: torch.Tensor, sigma: float = 2.0) -> torch.Tensor:
    """x: (N, 7, R, R) network space -> (N, 3, R, R) same dtype, >= 0: the squared 5-point Laplacian (reflected
    borders) of the albedo's luminance (mean of the 3 sRGB-encoded channels) and of the normals' x and y, each
    blurred by a Gaussian of ``sigma`` texels: where in the layout a map has fine detail, texel by texel. Its mean
    over samples shows what the mean maps cannot: a band G leaves without strands whatever its sign (at 181.75 kimg
    the crown's centre columns had 0.07-0.15 of the data's energy, a seam light in one sample and dark in the next).
    Differentiable (the BRDF-GAN's detail-map term)."""
    if x.ndim != 4 or x.shape[1] != 7 or not x.is_floating_point() or x.shape[-1] != x.shape[-2]:
        raise ValueError(f"expected float (N, 7, R, R) maps in network space, got {tuple(x.shape)} {x.dtype}")
    if not sigma > 0 or x.shape[-1] <= 6 * sigma:
        raise ValueError(f"expected sigma > 0 and maps wider than 6 sigma, got sigma {sigma} for {tuple(x.shape[2:])}")
    lap = _laplacian(torch.cat([x[:, :3].mean(1, keepdim=True), x[:, 4:6]], 1), "reflect")
    n, c, r, _ = lap.shape
    return gaussian_blur(lap.square().reshape(n * c, 1, r, r), sigma).reshape(n, c, r, r)


def region_relief(lum: torch.Tensor, normals_xy: torch.Tensor, regions: torch.Tensor) -> torch.Tensor:
    """lum: (N, R, R) albedo luminance, any units; normals_xy: (N, 2, R, R) the normals' x and y, any scale;
    regions: (R, R) uint8 labels (255 unmapped) -> (N, k, 2) same dtype in [-1, 1]: per sample and region of
    ``region_labels``, the correlation of the luminance's finest Laplacian band (``_bandpass``: 1-2 texels)
    with each normal component's. The data's strands and pores are bright or dark across their whole width,
    while their normals tilt both ways, so its is ~0 (|r| <= 0.012 in every region); an albedo that carries
    its normals' slope, a relief lit from one side (G's embossed grey hair), is not. A flat region gives 0.
    Differentiable (the BRDF-GAN's relief term)."""
    if (lum.ndim != 3 or normals_xy.shape != (lum.shape[0], 2, *lum.shape[1:]) or not lum.is_floating_point()
            or regions.shape != lum.shape[1:] or regions.dtype != torch.uint8):
        raise ValueError(f"expected float (N, R, R) luminance, (N, 2, R, R) normals and (R, R) uint8 regions matching "
                         f"them, got {tuple(lum.shape)} {lum.dtype}, {tuple(normals_xy.shape)} and "
                         f"{tuple(regions.shape)} {regions.dtype}")
    return region_band_correlation(lum, normals_xy.to(lum), regions)


def region_band_correlation(a: torch.Tensor, b: torch.Tensor, regions: torch.Tensor, level: int = 0) -> torch.Tensor:
    """a: (N, R, R), b: (N, C, R, R), any units; regions: (R, R) uint8 labels (255 unmapped) -> (N, k, C) a's dtype in
    [-1, 1]: per sample and region of ``region_labels``, the correlation of a's Laplacian band ``level`` (``_bandpass``;
    0: the finest, 1-2 texels; 1: 2-4; 2: 4-8) with each channel of b's. A flat region gives 0. Differentiable."""
    _check_band_pair("region_band_correlation", a, b, regions, level)
    band = _bandpass(torch.cat([a[:, None], b.to(a)], 1), level + 1)[level]  # (N, 1 + C, R, R)
    return _paired_region_correlation(band[:, :1].expand_as(band[:, 1:]), band[:, 1:], regions)


def _check_level(level: int, resolution: int) -> None:
    if not 0 <= level or resolution % 2 ** (level + 1):
        raise ValueError(f"expected a band level >= 0 with R divisible by 2 ** (level + 1), got level {level}, "
                         f"R {resolution}")


def _check_band_maps(x: torch.Tensor, regions: torch.Tensor, level: int) -> None:
    """The per-region band measures' input check: float (N, C, R, R) maps, (R, R) uint8 regions, a band they hold."""
    if x.ndim != 4 or not x.is_floating_point() or regions.shape != x.shape[2:] or regions.dtype != torch.uint8:
        raise ValueError(f"expected float (N, C, R, R) maps and (R, R) uint8 regions matching them, got "
                         f"{tuple(x.shape)} {x.dtype} and {tuple(regions.shape)} {regions.dtype}")
    _check_level(level, x.shape[-1])


def region_band_skew(x: torch.Tensor, regions: torch.Tensor, level: int = 0) -> torch.Tensor:
    """x: (N, C, R, R) float, any units; regions: (R, R) uint8 labels (255 unmapped) -> (N, k, C) same dtype: per sample,
    region of ``region_labels`` and channel, the skewness (third central moment over the second's 1.5 power) of x's
    Laplacian band ``level`` (``_bandpass``; 0: the finest). The data's normals are a height field's slopes, whose
    bumps tilt both ways alike: ~0 in every region (docs/brdf_gan.md). A flat region gives 0. Differentiable."""
    _check_band_maps(x, regions, level)
    return _band_skew(_bandpass(x, level + 1)[level], _region_weights(regions, x).T).transpose(1, 2)


def _band_skew(band: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """band: (N, C, R, R); w: (R*R, k) ``_region_weights`` transposed -> (N, C, k): ``region_band_skew`` of a band."""
    band = band.flatten(2)  # (N, C, R*R)
    mean = band @ w  # (N, C, k)
    m2 = band.square() @ w - mean.square()
    m3 = band.pow(3) @ w - 3 * mean * (band.square() @ w) + 2 * mean.pow(3)
    # m3 / m2^1.5 without the root's infinite gradient at a flat region (as ``_paired_region_correlation``)
    flat = m2 <= 0
    return m3 / torch.where(flat, torch.ones_like(m2), m2).pow(1.5) * ~flat


def region_band_neighbour(x: torch.Tensor, regions: torch.Tensor, level: int = 0) -> torch.Tensor:
    """x: (N, C, R, R) float, any units; regions: (R, R) uint8 labels (255 unmapped) -> (N, k, C, 2) same dtype: per
    sample, region of ``region_labels`` and channel, the correlation of x's Laplacian band ``level`` (``_bandpass``; 0:
    the finest) with itself one texel over, along u and then along v: the autocovariance at lag 1 over the texels of
    the region (each paired with its neighbour at u + 1 or at the next row, the map's border wrapping) over the band's
    variance there. How smooth the band is from texel to texel, where its energy says how much there is: at 322.00 kimg
    G_ema's finest specular band was smoother than the data's in every region (skin 0.17 against 0.09), and its
    chromaticity on the scalp (0.36-0.38 against 0.15-0.16; docs/brdf_gan.md). A flat region gives 0. Differentiable."""
    _check_band_maps(x, regions, level)
    return _band_neighbour(_bandpass(x, level + 1)[level], _region_weights(regions, x).T, (3, 2)).transpose(1, 2)


def _band_neighbour(band: torch.Tensor, w: torch.Tensor, dims: tuple[int, ...]) -> torch.Tensor:
    """band: (N, C, R, R); w: (R*R, k) ``_region_weights`` transposed; dims: 3 along u (columns), 2 along v (rows) ->
    (N, C, k, len(dims)): ``region_band_neighbour`` of a band along each of ``dims``."""
    b = band.flatten(2)  # (N, C, R*R)
    mean = b @ w  # (N, C, k)
    var = b.square() @ w - mean.square()
    flat = var <= 0
    out = []
    for dim in dims:
        nb = torch.roll(band, -1, dims=dim).flatten(2)
        cov = (b * nb) @ w - mean * (nb @ w)
        out.append(cov / torch.where(flat, torch.ones_like(var), var) * ~flat)
    return torch.stack(out, -1)


def region_band_magnitude_correlation(a: torch.Tensor, b: torch.Tensor, regions: torch.Tensor,
                                      level: int = 0) -> torch.Tensor:
    """a: (N, R, R), b: (N, C, R, R), any units; regions: (R, R) uint8 labels (255 unmapped) -> (N, k, C) a's dtype in
    [-1, 1]: per sample and region of ``region_labels``, the correlation of the magnitude of a's Laplacian band
    ``level`` (``_bandpass``) with that of each channel of b's: whether a's grain and b's sit on the same texels,
    whatever their signs, which ``region_band_correlation`` cannot see (the 363.08 kimg judge W's tell: G's albedo
    edges and normals' bumps sat together too little on the body and too much in the hair). A flat region gives 0.
    Differentiable, but at a band's zeros."""
    _check_band_pair("region_band_magnitude_correlation", a, b, regions, level)
    band = _bandpass(torch.cat([a[:, None], b.to(a)], 1), level + 1)[level].abs()  # (N, 1 + C, R, R)
    return _paired_region_correlation(band[:, :1].expand_as(band[:, 1:]), band[:, 1:], regions)


def _check_band_pair(name: str, a: torch.Tensor, b: torch.Tensor, regions: torch.Tensor, level: int) -> None:
    """The paired band measures' input check: a float (N, R, R) map, (N, C, R, R) maps, (R, R) uint8 regions matching
    them, a band they hold. ``name`` leads the error."""
    if (a.ndim != 3 or b.ndim != 4 or b.shape[0] != a.shape[0] or b.shape[2:] != a.shape[1:] or not a.is_floating_point()
            or regions.shape != a.shape[1:] or regions.dtype != torch.uint8):
        raise ValueError(f"{name}: expected float (N, R, R) and (N, C, R, R) maps and (R, R) uint8 regions matching "
                         f"them, got {tuple(a.shape)} {a.dtype}, {tuple(b.shape)} and {tuple(regions.shape)} "
                         f"{regions.dtype}")
    _check_level(level, a.shape[-1])


def _paired_region_correlation(a: torch.Tensor, b: torch.Tensor, regions: torch.Tensor) -> torch.Tensor:
    """a, b: (N, C, R, R) float; regions: (R, R) uint8 -> (N, k, C) a's dtype in [-1, 1]: per sample, region and channel
    c, the correlation of a[:, c] with b[:, c] over the region's texels. A flat region gives 0."""
    w = _region_weights(regions, a).T  # (R*R, k)
    a, b = a.flatten(2), b.to(a).flatten(2)  # (N, C, R*R)
    ma, mb = a @ w, b @ w  # (N, C, k)
    both = (a.square() @ w - ma.square()).clamp_min(0) * (b.square() @ w - mb.square()).clamp_min(0)
    cov = (a * b) @ w - ma * mb
    # cov / sqrt(both) without the root's infinite gradient at a flat region (as ``region_band_energy``)
    flat = both <= 0
    corr = cov / torch.where(flat, torch.ones_like(both), both).sqrt() * ~flat
    return corr.transpose(1, 2)


BAND_STATISTICS = ("log_variance", "skew", "log_kurtosis", "neighbour")


def region_band_statistics(x: torch.Tensor, regions: torch.Tensor, levels: int = 4) -> torch.Tensor:
    """x: (N, C, R, R) float, any units, R divisible by 2^levels; regions: (R, R) uint8 labels (255 unmapped) ->
    (N, F) same dtype, named by ``band_statistic_names``: per Laplacian band (``_bandpass``, finest first), per channel
    and region of ``region_labels``, each of ``BAND_STATISTICS`` (the log of the variance, the skewness, the log of the
    kurtosis, the neighbour correlation along u of ``region_band_neighbour``); then per pair of channels and region, the
    band's correlation; after the bands, per channel, ``nyquist_log_ratio`` over the whole map. The ``screen``'s
    statistics and the BRDF-GAN's screen term's. A flat region's statistics are 0 (the logs floored at log 1e-20,
    -46). Differentiable."""
    if x.ndim != 4 or not x.is_floating_point() or levels < 1 or x.shape[-1] % 2 ** levels:
        raise ValueError(f"region_band_statistics: expected float (N, C, R, R) maps with R divisible by 2^levels "
                         f"(levels >= 1), got {tuple(x.shape)} {x.dtype} and levels {levels}")
    _check_band_maps(x, regions, levels - 1)
    w = _region_weights(regions, x).T  # (R*R, k)
    c = x.shape[1]
    first, second = ([p[i] for p in itertools.combinations(range(c), 2)] for i in (0, 1))

    def safe(num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
        return torch.where(den > 1e-20, num / den.clamp_min(1e-20), torch.zeros_like(num))

    feats = []
    for level, band in enumerate(_bandpass(x, levels)):
        b = band.flatten(2)  # (N, C, R*R)
        e1, e2, e3, e4 = (b ** p @ w for p in (1, 2, 3, 4))  # (N, C, k) raw moments
        var = (e2 - e1 ** 2).clamp_min(0)
        m4 = e4 - 4 * e1 * e3 + 6 * e1 ** 2 * e2 - 3 * e1 ** 4
        skew = _band_skew(band, w)  # (N, C, k)
        nbr = _band_neighbour(band, w, (3,))[..., 0]  # along u
        for v in (var.clamp_min(1e-20).log(), skew, safe(m4, var ** 2).clamp_min(1e-20).log(), nbr):
            feats.append(v.flatten(1))
        if first:  # (N, k, pairs) -> pair by pair, each over the regions
            feats.append(_paired_region_correlation(band[:, first], band[:, second], regions).transpose(1, 2).flatten(1))
    feats.append(nyquist_log_ratio(x))
    return torch.cat(feats, 1)


def band_statistic_names(channels: tuple[str, ...], regions: tuple[str, ...], levels: int = 4) -> list[str]:
    """The F names of ``region_band_statistics``' columns for maps of these channel names and regions (ascending
    labels): "band{level} {statistic} {channel} {region}", "band{level} correlation {channel}-{channel} {region}",
    "nyquist {channel}"."""
    names = []
    pairs = list(itertools.combinations(channels, 2))
    for level in range(levels):
        names += [f"band{level} {stat} {c} {r}" for stat in BAND_STATISTICS for c in channels for r in regions]
        names += [f"band{level} correlation {a}-{b} {r}" for a, b in pairs for r in regions]
    return names + [f"nyquist {c}" for c in channels]


def region_quantiles(x: torch.Tensor, regions: torch.Tensor, qs: tuple[float, ...]) -> torch.Tensor:
    """x: (N, C, R, R) float, any units; regions: (R, R) uint8 labels (255 unmapped); qs: levels in [0, 1] -> (N, k, C,
    len(qs)) same dtype: per sample, region of ``region_labels`` and channel, x's quantiles over the region's texels
    (``torch.quantile``, linear between order statistics). The data's darkest specular: its scalp's 0.1 % at 2/255,
    its brows' at 18/255 on every sample, where at 329.18 kimg G_ema's scalp sat at 0.014 (0.008-0.022 from sample to
    sample) and its brows at 0.044, below the data's floor (docs/brdf_gan.md). Differentiable (through the order
    statistics' values)."""
    if (x.ndim != 4 or not x.is_floating_point() or regions.shape != x.shape[2:] or regions.dtype != torch.uint8
            or not qs or not all(0 <= q <= 1 for q in qs)):
        raise ValueError(f"region_quantiles: expected float (N, C, R, R) maps, (R, R) uint8 regions matching them and "
                         f"levels in [0, 1], got {tuple(x.shape)} {x.dtype}, {tuple(regions.shape)} {regions.dtype} "
                         f"and {qs}")
    q = torch.tensor(qs, dtype=x.dtype, device=x.device)
    flat, values = regions.flatten().to(x.device), x.flatten(2)
    return torch.stack([torch.quantile(values[..., flat == lab], q, dim=-1).permute(1, 2, 0)
                        for lab in region_labels(regions)], 1)


def local_range(x: torch.Tensor, size: int = 3) -> torch.Tensor:
    """x: (N, C, R, R) float, any units -> (N, C, R, R) same dtype, >= 0: per texel and channel, the largest minus the
    smallest value in the ``size`` x ``size`` window centred on it (clipped at the map's borders). The 338.02 kimg judge
    S's measure: on the sheet, 0.38 % of the data's normal texels sat in 3 x 3 windows that vary by at most 2 of 255
    levels, G's 0.02 %; a crescent along the temples where the data's normals are flat, textured by G
    (docs/brdf_gan.md). Differentiable (through each window's largest and smallest texel)."""
    if x.ndim != 4 or not x.is_floating_point() or size < 1 or size % 2 == 0:
        raise ValueError(f"local_range: expected float (N, C, R, R) maps and an odd size >= 1, got {tuple(x.shape)} "
                         f"{x.dtype} and size {size}")
    pad = size // 2
    return F.max_pool2d(x, size, 1, pad) + F.max_pool2d(-x, size, 1, pad)


SLOPE_KERNELS = ("central", "sobel")


def region_slope_link(specular: torch.Tensor, normals: torch.Tensor, regions: torch.Tensor,
                      kernel: str = "central") -> torch.Tensor:
    """specular: (N, 1, R, R), any affine units; normals: (N, 3, R, R) (unit, or network space: only x and y are read);
    regions: (R, R) uint8 -> (N, k, 2) in [-1, 1]: per sample and region, the correlation of the specular's slope
    along u (central differences, replicated borders) with the normals' x, and of its slope along v (rows go down, v
    up) with their y. The data's scalp specular is its strands' height, so its slope is the normals' tilt at every
    scale (128 maps: -0.91 / -0.94, q90 -0.885), where G_ema's at 297.67 kimg was -0.86 / -0.89 (q10 -0.883): the
    297.67 judge K's measure, which ``region_specular_link``, the finest band only, could not see (0.882 vs 0.868).
    Differentiable (the BRDF-GAN's specular-slope term).

    ``kernel`` "sobel": each slope also averaged across its axis with weights 1, 2, 1, which is how ``fitme dataset``
    makes its normals from the height (cv2.Sobel, 3x3): on the scalp, where the specular is the strands' height, the
    data's correlation is then nearer -1 (32 maps, medians: x -0.926, y -0.946, against -0.885 central) and G_ema's
    at 354.76 kimg (-0.907, -0.925; q10 -0.923 against the data's -0.959) shows the 354.76 judge P's tell, the hair's
    normals a looser filter of its specular than the data's (docs/brdf_gan.md)."""
    if kernel not in SLOPE_KERNELS:
        raise ValueError(f"region_slope_link: kernel must be one of {SLOPE_KERNELS}, got {kernel!r}")
    if (specular.ndim != 4 or specular.shape[1] != 1 or not specular.is_floating_point()
            or normals.shape != (specular.shape[0], 3, *specular.shape[2:]) or regions.shape != specular.shape[2:]
            or regions.dtype != torch.uint8):
        raise ValueError(f"region_slope_link: expected float (N, 1, R, R) specular, (N, 3, R, R) normals and (R, R) "
                         f"uint8 regions matching them, got {tuple(specular.shape)} {specular.dtype}, "
                         f"{tuple(normals.shape)} and {tuple(regions.shape)} {regions.dtype}")
    p = F.pad(specular, (1, 1, 1, 1), mode="replicate")[:, 0]
    du = (p[:, :, 2:] - p[:, :, :-2]) / 2  # (N, R + 2, R): every padded row
    dv = (p[:, :-2, :] - p[:, 2:, :]) / 2  # (N, R, R + 2); v grows upward: the row above minus the row below
    if kernel == "sobel":
        du = (du[:, :-2] + 2 * du[:, 1:-1] + du[:, 2:]) / 4
        dv = (dv[..., :-2] + 2 * dv[..., 1:-1] + dv[..., 2:]) / 4
    else:
        du, dv = du[:, 1:-1], dv[..., 1:-1]
    return _paired_region_correlation(torch.stack([du, dv], 1), normals[:, :2], regions)


def filter_fit_r2(x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, size: int = 7) -> torch.Tensor:
    """x: (N, R, R) float, any units; y: (N, C, R, R) float; mask: (R, R) bool -> (N, C) float64 in [0, 1]: per sample
    and channel of y, the share of its variance over the masked texels that a least-squares linear filter of x
    explains (R^2): y regressed on the ``size`` x ``size`` neighbourhood of x (edges replicated) and a constant, fitted
    per sample and channel. 0 where y is flat there.

    The 354.76 kimg judge P's measure: the data's hair normals are a filter of its specular (``fitme dataset`` takes
    them from the height by a 3x3 Sobel, and on the scalp the specular is the strands' height), G_ema's less so (7x7,
    normals x on the scalp, 32 maps, q10 / q50 / q90: data 0.80 / 0.88 / 0.93, G 0.81 / 0.85 / 0.87), and on the neck
    more so (0.41 / 0.52 / 0.54 against 0.57 / 0.60 / 0.63). A card measure: not differentiated, float64."""
    if (x.ndim != 3 or not x.is_floating_point() or y.ndim != 4 or y.shape[:1] + y.shape[2:] != x.shape
            or not y.is_floating_point() or mask.shape != x.shape[1:] or mask.dtype != torch.bool):
        raise ValueError(f"filter_fit_r2: expected float (N, R, R) x, (N, C, R, R) y and an (R, R) bool mask matching "
                         f"them, got {tuple(x.shape)} {x.dtype}, {tuple(y.shape)} {y.dtype} and {tuple(mask.shape)} "
                         f"{mask.dtype}")
    if size < 1 or size % 2 == 0:
        raise ValueError(f"filter_fit_r2: size must be odd and positive, got {size}")
    m = int(mask.sum())
    if m <= size * size + 1:
        raise ValueError(f"filter_fit_r2: the mask must hold more than size^2 + 1 = {size * size + 1} texels, got {m}")
    x, y, keep = x.detach().double(), y.detach().double(), mask.flatten()
    h = size // 2
    out = torch.zeros(y.shape[:2], dtype=torch.float64)
    for i in range(x.shape[0]):  # one sample at a time: the taps of a batch at 256^2 would be hundreds of MB
        taps = F.unfold(F.pad(x[i, None, None], (h, h, h, h), mode="replicate"), size)[0][:, keep]  # (size^2, m)
        taps = taps - taps.mean(1, keepdim=True)  # centred: the constant's share drops out
        target = y[i].flatten(1)[:, keep]
        target = target - target.mean(1, keepdim=True)  # (C, m)
        total = target.square().sum(1)
        # the normal equations (size^2 unknowns), far faster than a least-squares solve over the m texels; gelsd
        # takes a flat or rank-deficient x (its minimum-norm solution explains the same share)
        moment = taps @ target.T  # (size^2, C)
        beta = torch.linalg.lstsq(taps @ taps.T, moment, driver="gelsd").solution
        explained = (beta * moment).sum(0)
        out[i] = torch.where(total > 0, explained / total.clamp_min(torch.finfo(total.dtype).tiny), 0).clamp(0, 1)
    return out


def region_specular_link(specular: torch.Tensor, normals: torch.Tensor, regions: torch.Tensor) -> torch.Tensor:
    """specular: (N, 1, R, R), any affine units (linear A_S or network space); normals: (N, 3, R, R) (unit, or network
    space: only x and y are read, and a scale does not change a correlation); regions: (R, R) uint8 -> (N, k) in
    [-1, 1]: per sample and region, ``region_band_correlation`` of the specular with the normals' divergence (bumps
    > 0). In the data the specular's pores and strands follow the normals' relief (96 maps: skin 0.46, forehead 0.63,
    nose 0.67, neck 0.64, scalp 0.88); at 275.01 kimg G_ema's was 0.24 / 0.47 / 0.46 / 0.32 / 0.79, the 275.01 judge's
    measured tell (docs/brdf_gan.md, "The specular follows the normals")."""
    if specular.ndim != 4 or specular.shape[1] != 1 or normals.shape != (specular.shape[0], 3, *specular.shape[2:]):
        raise ValueError(f"expected (N, 1, R, R) specular and (N, 3, R, R) normals, got {tuple(specular.shape)} and "
                         f"{tuple(normals.shape)}")
    return region_band_correlation(specular[:, 0], _divergence(normals)[:, None], regions)[..., 0]


def ring_profile(x: torch.Tensor, bands: torch.Tensor) -> torch.Tensor:
    """x: (N, C, R, R) float, any units; bands: (R, R) uint8 labels 0 .. K-1 (each present, K >= 2; 255 not counted),
    0 innermost -> (N, K - 1, C) same dtype: per sample and channel, the mean over each band but the outermost minus
    the mean over the outermost. A ring darker than the skin it lies in, whatever the sample's tone, is negative in
    log albedo (``data.eye_rings``: G_ema's "eyeshadow" at 289.04 kimg, docs/brdf_gan.md). Differentiable."""
    if x.ndim != 4 or not x.is_floating_point() or bands.shape != x.shape[2:] or bands.dtype != torch.uint8:
        raise ValueError(f"ring_profile: expected float (N, C, R, R) maps and (R, R) uint8 bands matching them, got "
                         f"{tuple(x.shape)} {x.dtype} and {tuple(bands.shape)} {bands.dtype}")
    labels = region_labels(bands)
    if len(labels) < 2 or labels != list(range(len(labels))):
        raise ValueError(f"ring_profile: expected bands labelled 0 .. K-1 with K >= 2, got labels {labels}")
    means = x.flatten(2) @ _region_weights(bands, x).T  # (N, C, K)
    return (means[..., :-1] - means[..., -1:]).transpose(1, 2)


def row_profile(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """x: (N, C, R, R) float, any units; mask: (R, R) bool, not empty -> (N, K, C) same dtype, K the rows holding mask
    texels, top to bottom: per sample and channel, each row's mean over the mask minus the whole mask's mean. The
    data's forehead has no rows of its own colour, so its log chromaticity's profile is flat (per sample, the largest
    row |deviation| smoothed over 5 rows: median 0.02 red-green); at 297.67 kimg G_ema drew a redder band across its
    middle (rows 50-58 of 38-70 at 256^2: mean +0.1, median per sample 0.09; the judges' "red band across the
    forehead", docs/brdf_gan.md). Differentiable."""
    if (x.ndim != 4 or not x.is_floating_point() or mask.shape != x.shape[2:] or mask.dtype != torch.bool
            or not bool(mask.any())):
        raise ValueError(f"row_profile: expected float (N, C, R, R) maps and a non-empty (R, R) bool mask matching "
                         f"them, got {tuple(x.shape)} {x.dtype} and {tuple(mask.shape)} {mask.dtype}")
    m = mask.to(x)
    counts = m.sum(1)
    rows = counts > 0
    sums = (x * m).sum(-1)  # (N, C, R)
    means = sums[..., rows] / counts[rows]
    return (means - sums.sum(-1, keepdim=True) / m.sum()).transpose(1, 2)


def region_coherence(img: torch.Tensor, regions: torch.Tensor, sigma: float = 1.5) -> torch.Tensor:
    """img: (N, R, R) float; regions: (R, R) uint8 labels (255 unmapped) -> (N, k) same dtype: each
    sample's mean ``orientation_coherence`` over each region of ``region_labels`` (ascending).
    Differentiable (the BRDF-GAN's coherence term)."""
    if regions.shape != img.shape[1:] or regions.dtype != torch.uint8:
        raise ValueError(f"expected (R, R) uint8 regions matching the maps {tuple(img.shape[1:])}, got "
                         f"{tuple(regions.shape)} {regions.dtype}")
    return orientation_coherence(img, sigma).flatten(1) @ _region_weights(regions, img).T


def strand_coherence(phys: torch.Tensor, regions: torch.Tensor, sigma: float = 1.5) -> np.ndarray:
    """(N, 7, R, R) physical maps, (R, R) uint8 region labels -> (k, 2) float64: per region of
    ``region_labels`` (ascending), the mean ``orientation_coherence`` of the albedo's luminance and of
    the normals' x component."""
    if phys.ndim != 4 or phys.shape[1] != 7 or regions.shape != phys.shape[2:]:
        raise ValueError(f"expected (N, 7, R, R) maps and (R, R) regions, got {tuple(phys.shape)} and {tuple(regions.shape)}")
    # every sample has as many texels in a region, so the mean of the samples' region means is the region's
    return torch.stack([region_coherence(m, regions, sigma).double().mean(0) for m in (phys[:, :3].mean(1), phys[:, 4])], 1).numpy()


def gamut_excess(albedo: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) linear albedo -> (N, 2, H, W) >= 0: per texel, how far the albedo leaves the data's hue gamut
    r >= g >= b: log g - log r and log b - log g where positive (each floored at 1e-3), else 0. Every texel of the data
    is inside (512 maps: min r / g and g / b exactly 1, at the grey eyeballs); G_ema's at 282 kimg were not: 0.9 % of
    texels greener than red and 0.8 % bluer than green, the judges' "greenish skin" and "blue casts in the beards"
    (docs/brdf_gan.md). ADA's colour jitter keeps the order (it scales saturation and contrast and shifts all three
    channels alike), yet D had not learned it in 280 kimg. Differentiable almost everywhere."""
    if albedo.ndim != 4 or albedo.shape[1] != 3 or not albedo.is_floating_point():
        raise ValueError(f"gamut_excess: expected float (N, 3, H, W) linear albedo, got {tuple(albedo.shape)} {albedo.dtype}")
    r, g, b = albedo.clamp_min(1e-3).log().unbind(1)
    return torch.stack([F.relu(g - r), F.relu(b - g)], 1)


def log_chroma(albedo: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) linear albedo -> (N, 2, H, W): log r - log g and (log r + log g) / 2 - log b (each floored at
    1e-3): opponent axes, red-green and yellow-blue, that a change of brightness (a scale of all three) leaves alone."""
    if albedo.ndim != 4 or albedo.shape[1] != 3 or not albedo.is_floating_point():
        raise ValueError(f"log_chroma: expected float (N, 3, H, W) linear albedo, got {tuple(albedo.shape)} {albedo.dtype}")
    r, g, b = albedo.clamp_min(1e-3).log().unbind(1)
    return torch.stack([r - g, (r + g) / 2 - b], 1)
